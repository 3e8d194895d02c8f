"""pipeline/splits/leakage.py: the distance of each non-training frame to the nearest training frame of its
city, against a brute-force computation, its edge cases, a prepared synthetic dataset and its line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline import io
from pipeline.splits.leakage import is_training, leakage_line, measure, read_and_measure


def brute_force(splits, cities, xy) -> np.ndarray:
    """Each frame's distance to the nearest training frame of its city (inf without one; nan for training)."""
    splits, cities = np.asarray(splits), np.asarray(cities)
    train = np.array([is_training(s) for s in splits])
    out = np.full(len(xy), np.nan)
    for i in np.flatnonzero(~train):
        others = xy[train & (cities == cities[i])]
        out[i] = np.sqrt(((others - xy[i]) ** 2).sum(axis=1)).min() if len(others) else np.inf
    return out


def expected(distances: np.ndarray, range_m: float) -> dict:
    finite = distances[np.isfinite(distances)]
    return {
        "frames": len(distances),
        "within_5m": round(float(np.mean(distances <= 5.0)), 4),
        "within_range": round(float(np.mean(distances <= range_m)), 4),
        "median_m": round(float(np.median(finite)), 2) if len(finite) else None,
    }


def test_distances_agree_with_brute_force_per_split_and_city():
    rng = np.random.default_rng(7)
    n = 900
    splits = rng.choice(["train", "val", "test"], n, p=[0.6, 0.25, 0.15]).tolist()
    cities = rng.choice(["boston", "pittsburgh"], n).tolist()
    xy = rng.uniform(0, 400, (n, 2))
    result = measure(splits, cities, xy, 30.0)
    truth = brute_force(splits, cities, xy)
    assert result["train_splits"] == ["train"] and result["range_m"] == 30.0
    assert list(result["splits"]) == ["test", "val"]  # sorted, training splits left out
    s, c = np.array(splits), np.array(cities)
    for split, entry in result["splits"].items():
        mine = s == split
        assert {k: v for k, v in entry.items() if k != "cities"} == expected(truth[mine], 30.0)
        assert list(entry["cities"]) == ["boston", "pittsburgh"]
        for city, sub in entry["cities"].items():
            assert sub == expected(truth[mine & (c == city)], 30.0)
        assert 0 < entry["within_5m"] < entry["within_range"] < 1  # the numbers are not degenerate
    json.dumps(result)  # JSON-able as it is


def test_the_5m_boundary_is_inclusive():
    xy = np.array([[100.0, 200.0], [103.0, 204.0], [100.0, 205.01], [100.0, 230.0], [100.0, 230.02]])
    splits = ["train", "val", "val", "val", "val"]
    result = measure(splits, ["miami"] * 5, xy, 30.0)
    val = result["splits"]["val"]
    assert val["within_5m"] == 0.25  # 5.0 m counts, 5.01 m does not
    assert val["within_range"] == 0.75  # 30.0 m counts, 30.02 m does not
    assert val["median_m"] == round(float(np.median([5.0, 5.01, 30.0, 30.02])), 2)


def test_a_city_without_training_frames():
    xy = np.array([[0.0, 0.0], [3.0, 4.0], [10.0, 0.0], [0.0, 0.0], [1.0, 1.0]])
    splits = ["train", "val", "val", "val", "val"]
    cities = ["austin", "austin", "austin", "detroit", "detroit"]
    val = measure(splits, cities, xy, 8.0)["splits"]["val"]
    # detroit's frames have no training frame in their city, though one lies at the same x, y in austin
    assert val["cities"]["detroit"] == {"frames": 2, "within_5m": 0.0, "within_range": 0.0,
                                        "median_m": None, "no_training_frames_in_city": True}  # fmt: skip
    assert val["cities"]["austin"] == {"frames": 2, "within_5m": 0.5, "within_range": 0.5, "median_m": 7.5}
    assert (val["frames"], val["within_5m"], val["within_range"], val["median_m"]) == (4, 0.25, 0.25, 7.5)
    assert "no_training_frames_in_city" not in val["cities"]["austin"]
    only = measure(["train", "val"], ["austin", "detroit"], xy[:2], 8.0)["splits"]["val"]
    assert only["median_m"] is None and only["within_5m"] == 0.0
    line = leakage_line(measure(splits, cities, xy, 8.0), "original")
    assert line.endswith("median 7.5 m (2 frames in a city without training frames)")


def test_no_training_frames_at_all():
    result = measure(["val", "test"], ["a", "b"], np.zeros((2, 2)), 30.0)
    assert result == {"train_splits": [], "range_m": 30.0, "splits": {},
                      "note": "no training frames: leakage not measured"}  # fmt: skip
    line = leakage_line(result, "original")
    assert line == "split scheme original; leakage: not measured (no training frames)"


def test_the_train_rule():
    assert is_training("train") and is_training("mini_train")
    assert not any(map(is_training, ("val", "mini_val", "test", "trainval", "training", "train_val")))
    xy = np.array([[0.0, 0.0], [0.0, 2.0], [0.0, 40.0]])
    result = measure(["mini_train", "mini_val", "mini_val"], ["singapore-onenorth"] * 3, xy, 30.0)
    assert result["train_splits"] == ["mini_train"] and list(result["splits"]) == ["mini_val"]
    val = result["splits"]["mini_val"]
    assert val["within_5m"] == 0.5 and val["within_range"] == 0.5 and val["median_m"] == 21.0


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="not one each"):
        measure(["train"], ["a", "b"], np.zeros((1, 2)), 30.0)
    with pytest.raises(ValueError, match="not finite"):
        measure(["train", "val"], ["a", "a"], np.array([[0.0, np.nan], [0.0, 0.0]]), 30.0)
    with pytest.raises(ValueError, match="positive"):
        measure(["train"], ["a"], np.zeros((1, 2)), 0.0)


@pytest.mark.parametrize("kind", ["av2", "nuscenes"])
def test_read_and_measure_a_prepared_synthetic_dataset(synth_prepared, kind):
    data = synth_prepared[kind]
    frames = io.read_table(data, "frames", columns=["split", "city", "pose_translation"]).to_pylist()
    splits = [f["split"] for f in frames]
    cities = [f["city"] for f in frames]
    xy = np.array([f["pose_translation"][:2] for f in frames])
    result = read_and_measure(data, 30.0)
    train, val = ("train", "val") if kind == "av2" else ("mini_train", "mini_val")
    assert result["train_splits"] == [train] and list(result["splits"]) == [val]
    entry = result["splits"][val]
    truth = brute_force(splits, cities, xy)[np.array(splits) == val]
    assert entry["frames"] == 20 == len(truth)
    # the validation log drives a world that no training log visits: no frame within 5 m
    assert entry["within_5m"] == 0.0 and entry["median_m"] is not None
    assert {k: v for k, v in entry.items() if k != "cities"} == expected(truth, 30.0)
    assert result == measure(splits, cities, xy, 30.0)


def test_leakage_line():
    test = {"frames": 1, "within_5m": 1.0, "within_range": 1.0, "median_m": 0.4, "cities": {}}
    val = {"frames": 40, "within_5m": 0.0, "within_range": 0.125, "median_m": 85.21, "cities": {}}
    result = {"train_splits": ["train"], "range_m": 30.0, "splits": {"test": test, "val": val}}
    assert leakage_line(result, "original") == (
        "split scheme original; leakage: test 100.0 % of 1 frame within 5 m of a training frame (the same "
        "city), 100.0 % within 30 m, median 0.4 m; val 0.0 % of 40 frames within 5 m of a training frame "
        "(the same city), 12.5 % within 30 m, median 85.2 m"
    )
    assert leakage_line(None, None) == (
        "split scheme unknown; leakage not measured (prepared before leakage was recorded)"
    )
