"""pipeline/splits/leakage.py: per non-training frame the distance to the nearest training frame of its city
and whether its BEV window shares ground with a training window (and how much of it), against brute-force
computations (shapely for the windows), its edge cases, a prepared synthetic dataset and its line."""

from __future__ import annotations

import json

import numpy as np
import pytest
import shapely

from pipeline import io
from pipeline.geometry import Range
from pipeline.splits.leakage import (
    COVER_POINTS,
    is_training,
    leakage_line,
    measure,
    reach,
    read_and_measure,
    window_corners,
    yaw_of,
)

WINDOW = Range()  # 30 x 60 m, x right, y forward
# the covered share is counted at 6765 points: on random windows it stays this close to shapely's exact area
COVER_TOLERANCE = 0.002
# an edge parallel to the window's sides is placed to 1 / 6765 of the window; the share is rounded to 4 places
EDGE = 1 / COVER_POINTS + 5e-5


def brute_force(splits, cities, xy, yaw, window=WINDOW) -> dict[str, np.ndarray]:
    """Per frame: the distance to the nearest training frame of its city (inf without one), whether its
    window intersects a training window of its city and the share of its area they cover (shapely's exact
    union); nan for training frames."""
    splits, cities = np.asarray(splits), np.asarray(cities)
    train = np.array([is_training(s) for s in splits])
    windows = shapely.polygons(window_corners(np.asarray(xy), np.asarray(yaw), window))
    out = {name: np.full(len(xy), np.nan) for name in ("distance", "overlapping", "covered")}
    for i in np.flatnonzero(~train):
        same = train & (cities == cities[i])
        others = xy[same]
        out["distance"][i] = np.sqrt(((others - xy[i]) ** 2).sum(axis=1)).min() if len(others) else np.inf
        hits = windows[same][shapely.intersects(windows[same], windows[i])]
        out["overlapping"][i] = float(len(hits) > 0)
        covered = shapely.intersection(shapely.union_all(hits), windows[i]).area if len(hits) else 0.0
        out["covered"][i] = covered / windows[i].area
    return out


def expected(truth: dict, mine: np.ndarray, range_m: float) -> dict:
    distances = truth["distance"][mine]
    finite = distances[np.isfinite(distances)]
    return {
        "frames": len(distances),
        "within_5m": round(float(np.mean(distances <= 5.0)), 4),
        "within_range": round(float(np.mean(distances <= range_m)), 4),
        "median_m": round(float(np.median(finite)), 2) if len(finite) else None,
        "overlapping": round(float(np.mean(truth["overlapping"][mine])), 4),
    }


def without(entry: dict, *keys: str) -> dict:
    return {k: v for k, v in entry.items() if k not in keys}


def test_distances_and_windows_agree_with_brute_force_per_split_and_city():
    rng = np.random.default_rng(7)
    n = 900
    splits = rng.choice(["train", "val", "test"], n, p=[0.6, 0.25, 0.15]).tolist()
    cities = rng.choice(["boston", "pittsburgh"], n).tolist()
    xy = rng.uniform(0, 900, (n, 2))
    yaw = rng.uniform(-np.pi, np.pi, n)
    result = measure(splits, cities, xy, yaw, WINDOW)
    truth = brute_force(splits, cities, xy, yaw)
    assert result["train_splits"] == ["train"] and result["range_m"] == 30.0 and result["window"] == "30x60"
    assert result["cover_points"] == COVER_POINTS
    assert list(result["splits"]) == ["test", "val"]  # sorted, training splits left out
    s, c = np.array(splits), np.array(cities)
    for split, entry in result["splits"].items():
        mine = s == split
        assert without(entry, "cities", "covered") == expected(truth, mine, 30.0)
        assert entry["covered"] == pytest.approx(np.mean(truth["covered"][mine]), abs=COVER_TOLERANCE)
        assert list(entry["cities"]) == ["boston", "pittsburgh"]
        for city, sub in entry["cities"].items():
            here = mine & (c == city)
            assert without(sub, "covered") == expected(truth, here, 30.0)
            assert sub["covered"] == pytest.approx(np.mean(truth["covered"][here]), abs=COVER_TOLERANCE)
        # the numbers are not degenerate: windows overlap well beyond 30 m, and cover part of each other
        assert 0 < entry["within_5m"] < entry["within_range"] < entry["overlapping"] < 1
        assert 0 < entry["covered"] < entry["overlapping"]
    json.dumps(result)  # JSON-able as it is


def test_windows_that_share_ground_beyond_the_range_are_counted():
    # the case: every val frame 50 m or more from training, yet each window shares ground with one
    train = np.array([[0.0, 0.0], [500.0, 0.0]])
    val = np.array([[0.0, 50.0], [540.0, 0.0]])  # ahead on the same heading; beside, turned a quarter
    result = measure(["train", "train", "val", "val"], ["a"] * 4, np.concatenate([train, val]),
                     np.array([0.0, 0.0, 0.0, np.pi / 2]), WINDOW)  # fmt: skip
    entry = result["splits"]["val"]
    assert entry["within_range"] == 0.0 and entry["overlapping"] == 1.0
    # 10 m of the 60 m length; and x 10..15 m by y -15..15 m (150 of 1800 m^2)
    assert entry["covered"] == pytest.approx((10 / 60 + 150 / 1800) / 2, abs=EDGE)


@pytest.mark.parametrize("yaw", [0.0, 0.3, -2.0])
def test_windows_corner_to_corner_a_hair_within_the_reach_overlap_and_a_hair_beyond_do_not(yaw):
    corner = np.array([15.0, 30.0])  # the training window's corner; the val window turned half a turn
    c, s = np.cos(yaw), np.sin(yaw)
    turn = np.array([[c, -s], [s, c]])
    for factor, overlaps in ((1.0 - 1e-6, 1.0), (1.0 + 1e-6, 0.0)):
        xy = np.stack([np.zeros(2), factor * 2 * turn @ corner])
        result = measure(["train", "val"], ["a", "a"], xy, np.array([yaw, yaw + np.pi]), WINDOW)
        entry = result["splits"]["val"]
        assert entry["overlapping"] == overlaps and entry["covered"] == 0.0
        assert np.hypot(*xy[1]) == pytest.approx(factor * reach(WINDOW))
    assert reach(WINDOW) == pytest.approx(np.hypot(30.0, 60.0))


def test_the_5m_boundary_is_inclusive():
    xy = np.array([[100.0, 200.0], [103.0, 204.0], [100.0, 205.01], [100.0, 230.0], [100.0, 230.02]])
    splits = ["train", "val", "val", "val", "val"]
    result = measure(splits, ["miami"] * 5, xy, np.zeros(5), WINDOW)
    val = result["splits"]["val"]
    assert val["within_5m"] == 0.25  # 5.0 m counts, 5.01 m does not
    assert val["within_range"] == 0.75  # 30.0 m counts, 30.02 m does not
    assert val["median_m"] == round(float(np.median([5.0, 5.01, 30.0, 30.02])), 2)
    assert val["overlapping"] == 1.0  # all of them along the 60 m length


def test_a_city_without_training_frames():
    xy = np.array([[0.0, 0.0], [3.0, 4.0], [10.0, 0.0], [0.0, 0.0], [1.0, 1.0]])
    splits = ["train", "val", "val", "val", "val"]
    cities = ["austin", "austin", "austin", "detroit", "detroit"]
    window = Range.parse("16x16")  # within_range: within 8 m
    val = measure(splits, cities, xy, np.zeros(5), window)["splits"]["val"]
    # detroit's frames have no training frame in their city, though one lies at the same x, y in austin
    assert val["cities"]["detroit"] == {"frames": 2, "within_5m": 0.0, "within_range": 0.0, "median_m": None,
                                        "overlapping": 0.0, "covered": 0.0,
                                        "no_training_frames_in_city": True}  # fmt: skip
    # austin: 5 m and 10 m off on the same heading: the 16 m windows share 12 x 13 and 6 x 16 of 256 m^2
    covered = (12 * 13 + 6 * 16) / 512
    assert val["cities"]["austin"] == {"frames": 2, "within_5m": 0.5, "within_range": 0.5, "median_m": 7.5,
                                       "overlapping": 1.0,
                                       "covered": pytest.approx(covered, abs=2 * EDGE)}  # fmt: skip
    assert (val["frames"], val["within_5m"], val["within_range"], val["median_m"]) == (4, 0.25, 0.25, 7.5)
    assert val["overlapping"] == 0.5 and val["covered"] == pytest.approx(covered / 2, abs=2 * EDGE)
    only = measure(["train", "val"], ["austin", "detroit"], xy[:2], np.zeros(2), window)["splits"]["val"]
    assert only["median_m"] is None and only["within_5m"] == 0.0 and only["overlapping"] == 0.0
    line = leakage_line(measure(splits, cities, xy, np.zeros(5), window), "original")
    assert line.endswith("(2 frames in a city without training frames)")


def test_no_training_frames_at_all():
    result = measure(["val", "test"], ["a", "b"], np.zeros((2, 2)), np.zeros(2), WINDOW)
    assert result == {"train_splits": [], "range_m": 30.0, "window": "30x60", "cover_points": 6765,
                      "splits": {}, "note": "no training frames: leakage not measured"}  # fmt: skip
    line = leakage_line(result, "original")
    assert line == "split scheme original; leakage: not measured (no training frames)"


def test_the_train_rule():
    assert is_training("train") and is_training("mini_train")
    assert not any(map(is_training, ("val", "mini_val", "test", "trainval", "training", "train_val")))
    xy = np.array([[0.0, 0.0], [0.0, 2.0], [0.0, 40.0]])
    splits = ["mini_train", "mini_val", "mini_val"]
    result = measure(splits, ["singapore-onenorth"] * 3, xy, np.zeros(3), WINDOW)
    assert result["train_splits"] == ["mini_train"] and list(result["splits"]) == ["mini_val"]
    val = result["splits"]["mini_val"]
    assert val["within_5m"] == 0.5 and val["within_range"] == 0.5 and val["median_m"] == 21.0


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="not one each"):
        measure(["train"], ["a", "b"], np.zeros((1, 2)), np.zeros(1), WINDOW)
    with pytest.raises(ValueError, match="not one each"):
        measure(["train", "val"], ["a", "a"], np.zeros((2, 2)), np.zeros(1), WINDOW)
    with pytest.raises(ValueError, match="positions are not finite"):
        measure(["train", "val"], ["a", "a"], np.array([[0.0, np.nan], [0.0, 0.0]]), np.zeros(2), WINDOW)
    with pytest.raises(ValueError, match="headings are not finite"):
        measure(["train", "val"], ["a", "a"], np.zeros((2, 2)), np.array([0.0, np.inf]), WINDOW)
    with pytest.raises(ValueError, match="positive"):
        measure(["train"], ["a"], np.zeros((1, 2)), np.zeros(1), Range(0.0, 0.0, -1.0, 1.0))


def test_the_yaw_of_a_quaternion():
    for yaw in (0.0, 0.7, -2.5, np.pi / 2):
        q = [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]  # a turn about z
        assert yaw_of(np.array([q]))[0] == pytest.approx(yaw)
    # a pitch of 10 deg after the yaw leaves the ground heading as it was
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_euler("ZY", [1.1, 0.17]).as_quat()
    assert yaw_of(np.array([[w, x, y, z]]))[0] == pytest.approx(1.1)


@pytest.mark.parametrize("kind", ["av2", "nuscenes"])
def test_read_and_measure_a_prepared_synthetic_dataset(synth_prepared, kind):
    data = synth_prepared[kind]
    columns = ["split", "city", "log_id", "pose_translation", "pose_rotation"]
    frames = io.read_table(data, "frames", columns=columns).to_pylist()
    splits = [f["split"] for f in frames]
    cities = [f["city"] for f in frames]
    xy = np.array([f["pose_translation"][:2] for f in frames])
    yaw = yaw_of(np.array([f["pose_rotation"] for f in frames]))
    # the BEV y axis points where the car drives: yaw + 90 deg is the direction from frame to frame
    logs = np.array([f["log_id"] for f in frames])
    for log in set(logs):
        step = np.diff(xy[logs == log], axis=0)
        moving = np.hypot(*step.T) > 0.2
        driven = np.arctan2(step[moving, 1], step[moving, 0])
        heading = yaw[logs == log][:-1][moving] + np.pi / 2
        off = np.abs(np.angle(np.exp(1j * (driven - heading))))
        assert np.median(off) < 0.05 and off.max() < 0.3  # on bends the chord lags the heading a little
    result = read_and_measure(data, WINDOW)
    train, val = ("train", "val") if kind == "av2" else ("mini_train", "mini_val")
    assert result["train_splits"] == [train] and list(result["splits"]) == [val]
    entry = result["splits"][val]
    truth = brute_force(splits, cities, xy, yaw)
    mine = np.array(splits) == val
    assert entry["frames"] == 20 == mine.sum()
    # the validation log drives a world that no training log visits: no frame within 5 m
    assert entry["within_5m"] == 0.0 and entry["median_m"] is not None
    assert without(entry, "cities", "covered") == expected(truth, mine, 30.0)
    assert entry["covered"] == pytest.approx(np.mean(truth["covered"][mine]), abs=COVER_TOLERANCE)
    assert result == measure(splits, cities, xy, yaw, WINDOW)


def test_leakage_line():
    test = {"frames": 1, "within_5m": 1.0, "within_range": 1.0, "median_m": 0.4, "overlapping": 1.0,
            "covered": 0.9712, "cities": {}}  # fmt: skip
    val = {"frames": 40, "within_5m": 0.0, "within_range": 0.0, "median_m": 85.21, "overlapping": 0.125,
           "covered": 0.0301, "cities": {}}  # fmt: skip
    splits = {"test": test, "val": val}
    result = {"train_splits": ["train"], "range_m": 30.0, "window": "30x60", "splits": splits}
    assert leakage_line(result, "original") == (
        "split scheme original; leakage: test 100.0 % of 1 frame within 5 m of a training frame (the same "
        "city), 100.0 % within 30 m, median 0.4 m, 100.0 % of the 30x60 m windows overlap a training window, "
        "97.1 % of their area covered on average; val 0.0 % of 40 frames within 5 m of a training frame "
        "(the same city), 0.0 % within 30 m, median 85.2 m, 12.5 % of the 30x60 m windows overlap a "
        "training window, 3.0 % of their area covered on average"
    )
    # a manifest written before the windows were measured: the distances alone
    distances = without(val, "overlapping", "covered")
    old = {"train_splits": ["train"], "range_m": 30.0, "splits": {"val": distances}}
    assert leakage_line(old, "original").endswith("0.0 % within 30 m, median 85.2 m")
    assert leakage_line(None, None) == (
        "split scheme unknown; leakage not measured (prepared before leakage was recorded)"
    )


def test_queries_in_chunks_give_the_same_result(monkeypatch):
    from pipeline.splits import leakage

    rng = np.random.default_rng(3)
    n = 400
    splits = rng.choice(["train", "val"], n, p=[0.7, 0.3]).tolist()
    xy, yaw = rng.uniform(0, 300, (n, 2)), rng.uniform(-np.pi, np.pi, n)
    whole = measure(splits, ["a"] * n, xy, yaw, WINDOW)
    monkeypatch.setattr(leakage, "MAX_CANDIDATES", 7)  # fewer than one query's candidates: one at a time
    assert measure(splits, ["a"] * n, xy, yaw, WINDOW) == whole
    assert 0 < whole["splits"]["val"]["covered"] < whole["splits"]["val"]["overlapping"] <= 1
