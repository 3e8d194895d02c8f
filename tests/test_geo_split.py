"""Geographic splits (pipeline/splits/geographic.py): the buffer to training ground holds, and by default no
val or test window shares ground with a training window whatever the headings; the shares come near the
original ones and are recorded per city; a split left without a frame is refused in one line; the result is
seeded and deterministic, cities stay apart, and the map is drawn."""

from __future__ import annotations

import json

import numpy as np
import pytest
import shapely
from typer.testing import CliRunner

from cli import app
from pipeline.geometry import Range
from pipeline.splits.geographic import (
    DEFAULT_BUFFER_M,
    DPI,
    PANEL_INCHES,
    draw_split_map,
    geographic,
    hilbert_index,
)
from pipeline.splits.leakage import measure, window_corners

BUFFER_M = 30.0
# Shares within 0.03 (absolute) of the targets: a city is cut into 27 groups (4 / 0.15), each ~3.7 % of its
# frames, so one group too many or too few moves a split by ~0.04; trying 16 seeded group orders, each
# corrected for the frames the buffer drops, lands within 0.015 in 200 road layouts x seeds we tried.
SHARE_TOLERANCE = 0.03


def roads(seed: int, n_roads: int = 6, length_m: int = 1200, extent_m: float = 1200.0) -> np.ndarray:
    """Frame positions every 1 m along n_roads gently curving roads that cross a square."""
    rng = np.random.default_rng(seed)
    points = []
    for _ in range(n_roads):
        heading = rng.uniform(0, 2 * np.pi) + np.cumsum(rng.normal(0, 0.002, length_m))
        steps = np.stack([np.cos(heading), np.sin(heading)], axis=1)
        points.append(rng.uniform(0, extent_m, 2) + np.cumsum(steps, axis=0))
    return np.concatenate(points)


def original_70_15_15(n: int, seed: int = 0) -> np.ndarray:
    counts = {"train": n * 70 // 100, "val": n * 15 // 100}
    labels = ["train"] * counts["train"] + ["val"] * counts["val"] + ["test"] * (n - sum(counts.values()))
    return np.random.default_rng(seed).permutation(np.array(labels))


def nearest(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Brute force: the distance from each point of a to its nearest point of b (inf without any)."""
    if not len(b):
        return np.full(len(a), np.inf)
    return np.concatenate(
        [np.sqrt(((a[i : i + 400, None] - b[None]) ** 2).sum(-1)).min(1) for i in range(0, len(a), 400)]
    )


def before_buffer(result, city: str, xy: np.ndarray) -> np.ndarray:
    """Each frame's split as its cell was assigned, before the buffer (from result.cells)."""
    cells = {(x, y): s for x, y, s in result.cells[city].tolist()}
    return np.array(
        [result.split_names[cells[c]] for c in map(tuple, np.floor(xy / 100.0).astype(int).tolist())]
    )


@pytest.fixture(scope="module")
def city():
    xy = roads(seed=7)
    return xy, original_70_15_15(len(xy))


def test_the_buffer_holds_and_left_out_frames_are_counted_exactly(city):
    xy, original = city
    result = geographic(["A"] * len(xy), xy, original, cell_m=100.0, buffer_m=BUFFER_M, seed=0)
    split = np.array(result.split, dtype=object)
    assigned = before_buffer(result, "A", xy)
    training = assigned == "train"
    distance = nearest(xy[~training], xy[training])

    assert len(xy) == 7200 and result.split_names == ["train", "test", "val"]
    assert (split[training] == "train").all()  # training frames are never dropped
    kept = split[~training] != None  # noqa: E711 (element-wise)
    assert (distance[kept] > BUFFER_M).all()
    assert np.array_equal(~kept, distance <= BUFFER_M)  # exactly the frames within the buffer go
    assert (split[~training][kept] == assigned[~training][kept]).all()
    assert result.left_out == {"A": int((~kept).sum())}
    assert 300 < result.left_out["A"] < 1500  # 30 m at each border crossing of a road, not the whole city
    assert result.parameters["groups"] == {"A": 27} and result.parameters["missing"] == {}
    assert len(result.cells["A"]) == len(np.unique(np.floor(xy / 100.0), axis=0))


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_the_kept_shares_come_near_the_original_ones(city, seed):
    xy, original = city
    result = geographic(["A"] * len(xy), xy, original, buffer_m=BUFFER_M, seed=seed)
    kept = [s for s in result.split if s is not None]
    assert result.parameters["targets"] == pytest.approx({"train": 0.70, "val": 0.15, "test": 0.15})
    for name, target in result.parameters["targets"].items():
        assert result.shares[name] == pytest.approx(kept.count(name) / len(kept))
        assert abs(result.shares[name] - target) <= SHARE_TOLERANCE, (name, result.shares)
    val_cells = result.cells["A"][result.cells["A"][:, 2] == result.split_names.index("val")]
    assert len(val_cells) >= 8  # several groups of cells, not one blob


def test_the_same_seed_gives_the_same_split_and_another_seed_another(city):
    xy, original = city
    cities = ["A"] * len(xy)
    first, again = geographic(cities, xy, original, seed=3), geographic(cities, xy, original, seed=3)
    other = geographic(cities, xy, original, seed=4)
    assert first.split == again.split and np.array_equal(first.cells["A"], again.cells["A"])
    assert first.left_out == again.left_out and first.shares == again.shares
    differ = sum(a != b for a, b in zip(first.split, other.split))
    assert differ > 1000, differ
    # the frames' order does not matter either
    order = np.random.default_rng(0).permutation(len(xy))
    shuffled = geographic(cities, xy[order], original[order], seed=3)
    assert shuffled.split == [first.split[i] for i in order]


def test_two_cities_at_the_same_coordinates_are_kept_apart(city):
    xy, original = city
    both = np.concatenate([xy, xy])
    cities = ["A"] * len(xy) + ["B"] * len(xy)
    result = geographic(cities, both, np.concatenate([original, original]), buffer_m=BUFFER_M, seed=0)
    split = np.array(result.split, dtype=object)
    a, b = split[: len(xy)], split[len(xy) :]
    for mine in (a, b):  # the buffer holds within each city
        training = mine == "train"
        held_out = (mine != "train") & (mine != None)  # noqa: E711
        assert (nearest(xy[held_out], xy[training]) > BUFFER_M).all()
    assert not np.array_equal(a, b)  # each city draws its own groups
    b_held_out = (b != "train") & (b != None)  # noqa: E711
    near_a_train = nearest(xy[b_held_out], xy[a == "train"]) <= BUFFER_M
    assert near_a_train.sum() > 100  # val / test frames of B on training ground of A: fine
    assert set(result.left_out) == {"A", "B"} and sum(result.left_out.values()) == int((split == None).sum())  # noqa: E711


def test_a_city_with_too_few_cells_gets_what_the_greedy_gives():
    big = roads(seed=1, n_roads=3, length_m=600)
    small = np.array([[5.0, 5.0], [6.0, 5.0], [150.0, 5.0], [151.0, 5.0]]) + 1e4  # two cells
    xy = np.concatenate([big, small])
    cities = ["big"] * len(big) + ["small"] * len(small)
    result = geographic(cities, xy, original_70_15_15(len(xy)), seed=0)
    assert result.parameters["groups"]["small"] == 2 and len(result.cells["small"]) == 2
    assert result.split[-4:] == ["train"] * 4  # both groups fall short of train's deficit
    assert result.parameters["missing"] == {"small": ["test", "val"]}


def test_one_original_split_or_none_for_training_is_refused():
    xy = roads(seed=2, n_roads=2, length_m=300)
    cities = ["A"] * len(xy)
    with pytest.raises(ValueError, match="at least two original splits.*only 'train'"):
        geographic(cities, xy, ["train"] * len(xy))
    with pytest.raises(ValueError, match="needs a training split .* found 'test', 'val'"):
        geographic(cities, xy, ["val", "test"] * (len(xy) // 2))
    with pytest.raises(ValueError, match="one city, one split and one x, y per frame"):
        geographic(cities[:-1], xy, ["train", "val"] * (len(xy) // 2))


def test_the_hilbert_curve_steps_from_cell_to_neighbouring_cell():
    x, y = np.meshgrid(np.arange(16), np.arange(16))
    d = hilbert_index(x.ravel(), y.ravel(), order=4)
    assert sorted(d.tolist()) == list(range(256))
    path = np.stack([x.ravel(), y.ravel()], 1)[np.argsort(d)]
    assert (np.abs(np.diff(path, axis=0)).sum(1) == 1).all()


def test_the_split_map_is_a_png_of_one_panel_per_city(city, tmp_path):
    from matplotlib.image import imread

    xy, original = city
    both = np.concatenate([xy, xy + 5e3])
    cities = ["boston-seaport"] * len(xy) + ["singapore-onenorth"] * len(xy)
    result = geographic(cities, both, np.concatenate([original, original]), seed=0)
    path = tmp_path / "maps" / "split_map.png"
    draw_split_map(cities, both, result.split, path, cells=result.cells, cell_m=100.0)
    side = int(PANEL_INCHES * DPI)
    assert imread(path).shape == (side, 2 * side, 4)
    assert [p.name for p in path.parent.iterdir()] == ["split_map.png"]  # no temporary file left

    four = ["a", "b", "c", "d"] * (len(xy) // 4)  # the original scheme: no cells; 2 rows of 3 panels
    draw_split_map(four, xy, list(original), tmp_path / "original.png")
    assert imread(tmp_path / "original.png").shape == (2 * side, 3 * side, 4)
    with pytest.raises(ValueError, match="needs cell_m"):
        draw_split_map(cities, both, result.split, tmp_path / "x.png", cells=result.cells)


def intersecting_pairs(xy: np.ndarray, yaw: np.ndarray, split: list, window: Range = Range()) -> int:
    """Brute force, independent of leakage.py's test: the (val or test, training) pairs of frames whose
    windows intersect (shapely's exact predicate on every pair whose bounding boxes meet)."""
    windows = shapely.polygons(window_corners(xy, yaw, window))
    split = np.array(split, dtype=object)
    train = split == "train"
    held_out = (split != "train") & (split != None)  # noqa: E711 (element-wise)
    pairs = shapely.STRtree(windows[train]).query(windows[held_out], predicate="intersects")
    return pairs.shape[1]


@pytest.mark.parametrize("seed", [0, 1])
def test_by_default_no_val_or_test_window_shares_ground_with_a_training_window(city, seed):
    xy, original = city
    rng = np.random.default_rng(seed)
    cities = ["A"] * len(xy)
    yaw = rng.uniform(-np.pi, np.pi, len(xy))  # any heading at all: the buffer must not depend on them
    result = geographic(cities, xy, original, seed=seed)
    assert result.parameters["buffer_m"] == DEFAULT_BUFFER_M == pytest.approx(np.hypot(30.0, 60.0))
    assert intersecting_pairs(xy, yaw, result.split) == 0
    leakage = measure(result.split, cities, xy, yaw, Range())["splits"]
    assert all(leakage[s]["overlapping"] == leakage[s]["covered"] == 0.0 for s in ("val", "test"))
    # the worst headings for it: every kept val or test window turned so that its far corner points at the
    # nearest training frame, and every training window's at the nearest val or test frame
    split = np.array(result.split, dtype=object)
    train, held_out = split == "train", (split != "train") & (split != None)  # noqa: E711
    corner = np.arctan2(30.0, 15.0)  # of the corner (15, 30) from the window's x axis
    for mine, theirs in ((held_out, train), (train, held_out)):
        nearest = np.argmin(((xy[mine][:, None] - xy[theirs][None]) ** 2).sum(-1), axis=1)
        towards = xy[theirs][nearest] - xy[mine]
        yaw[mine] = np.arctan2(towards[:, 1], towards[:, 0]) - corner
    assert intersecting_pairs(xy, yaw, result.split) == 0


def test_the_old_30m_buffer_stays_reachable_and_its_windows_share_ground(city):
    # the case: no val or test frame within 30 m of a training frame, yet their windows overlap
    xy, original = city
    cities = ["A"] * len(xy)
    yaw = np.random.default_rng(0).uniform(-np.pi, np.pi, len(xy))
    result = geographic(cities, xy, original, buffer_m=30.0, seed=0)
    assert result.parameters["buffer_m"] == 30.0
    assert intersecting_pairs(xy, yaw, result.split) > 100
    leakage = measure(result.split, cities, xy, yaw, Range())["splits"]
    for name in ("val", "test"):
        assert leakage[name]["within_range"] == 0.0 and leakage[name]["overlapping"] > 0.05
    assert sum(result.left_out.values()) < sum(geographic(cities, xy, original, seed=0).left_out.values())


def test_the_achieved_shares_are_recorded_per_split_and_city(city):
    xy, original = city
    both = np.concatenate([xy, xy[:2000] + 1e4])
    cities = ["A"] * len(xy) + ["B"] * 2000
    result = geographic(cities, both, np.concatenate([original, original[:2000]]), seed=0)
    split = np.array(result.split, dtype=object)
    achieved = result.achieved()
    assert achieved["targets"] == result.parameters["targets"] and achieved["shares"] == result.shares
    assert achieved["missing"] == {} and list(achieved["cities"]) == ["A", "B"]
    for name, members in (("A", slice(0, len(xy))), ("B", slice(len(xy), None))):
        mine = split[members]
        kept = [s for s in mine if s is not None]
        entry = achieved["cities"][name]
        assert entry["frames"] == len(kept) and entry["left_out"] == len(mine) - len(kept)
        assert entry["shares"] == {
            s: pytest.approx(kept.count(s) / len(kept)) for s in ("train", "test", "val")
        }
    assert achieved["cities"]["A"]["shares"] != achieved["cities"]["B"]["shares"]
    json.dumps(achieved)


def test_a_split_left_without_a_frame_is_refused_in_one_line():
    # two one-frame logs in two cities: each city one cell, all training ground; val would be empty
    xy = np.array([[5.0, 5.0], [5.0, 5.0]])
    with pytest.raises(ValueError) as error:
        geographic(["PIT", "WDC"], xy, ["train", "val"])
    assert str(error.value) == (
        "split 'val' (1 frame in the dataset) gets no frame: the cities PIT (1 frame in 1 cell), WDC (1 "
        "frame in 1 cell) have too few cells of --geo-cell 100 m to share out beyond the 67.08 m buffer to "
        "training ground; try a smaller --geo-cell (or the original split scheme)"
    )
    # one city, two frames 40 m apart: one cell of 100 m, or two of 10 m whose val frame the buffer takes
    pair = np.array([[1.0, 1.0], [41.0, 1.0]])
    with pytest.raises(ValueError, match=r"split 'val' .* the cities A \(2 frames in 1 cell\)"):
        geographic(["A", "A"], pair, ["train", "val"])
    with pytest.raises(ValueError, match=r"A \(2 frames in 2 cells\) .* --geo-cell 10 m"):
        geographic(["A", "A"], pair, ["train", "val"], cell_m=10.0)
    kept = geographic(["A", "A"], pair, ["train", "val"], cell_m=10.0, buffer_m=30.0)  # the old buffer
    assert sorted(kept.split) == ["train", "val"] and kept.shares == {"train": 0.5, "val": 0.5}


@pytest.fixture(scope="module")
def one_frame_logs(tmp_path_factory):
    """A synthetic AV2 root of two one-frame logs, a training and a validation one, in two worlds."""
    from pipeline.synth import synth

    out = tmp_path_factory.mktemp("one_frame_logs")
    synth(out, logs=2, frames_per_log=1, worlds=2, sensors=False, val_frames_per_log=1)
    return out / "av2" / "sensor"


def test_prepare_stops_before_any_shard_when_a_split_would_be_empty(one_frame_logs, tmp_path):
    out = tmp_path / "geo"
    result = CliRunner().invoke(app, ["prepare", "--dataset", "av2", "--root", str(one_frame_logs), "--out",
                                      str(out), "--split-scheme", "geographic"])  # fmt: skip
    assert result.exit_code == 1, result.output
    errors = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "Traceback" not in result.output, result.output
    assert "--split-scheme geographic: split 'val' (1 frame in the dataset) gets no frame" in errors[0]
    assert all(
        word in errors[0] for word in ("PIT (1 frame in 1 cell)", "WDC (1 frame in 1 cell)", "--geo-cell")
    )
    assert not out.exists()  # nothing written


def test_prepare_records_the_achieved_shares_in_the_manifest_and_the_summary(
    synth_raw, synth_prepared, tmp_path
):
    out = tmp_path / "geo"
    args = ["prepare", "--dataset", "av2", "--root", str(synth_raw / "av2" / "sensor"), "--out", str(out),
            "--split-scheme", "geographic", "--geo-cell", "50", "--geo-seed", "3"]  # fmt: skip
    result = CliRunner().invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["split_shares"] == summary["split_shares"] and "split_shares" not in manifest["last_run"]
    shares = summary["split_shares"]
    frames = _frames(out)
    kept = {s: sum(f["split"] == s for f in frames) for s in ("train", "val")}
    assert shares["shares"] == {s: pytest.approx(kept[s] / len(frames)) for s in kept}
    assert shares["targets"] == {"train": 0.75, "val": 0.25}
    (city,) = shares["cities"].values()
    assert city["frames"] == len(frames) and city["shares"] == shares["shares"]
    assert (
        city["left_out"] == summary["frames_in_buffer"] == len(_frames(synth_prepared["av2"])) - len(frames)
    )
    row = manifest["leakage"]["splits"]["val"]
    assert row["frames"] == kept["val"] > 0 and row["overlapping"] == row["covered"] == 0.0
    table = CliRunner().invoke(app, [*args, "--overwrite"])
    assert table.exit_code == 0, table.output
    assert "geographic split: shares of the kept frames (target)" in table.output
    assert (
        "0.0 % of the 30x60 m windows overlap a training window, 0.0 % of their area covered" in table.output
    )


def _frames(data) -> list[dict]:
    from pipeline.io import read_table

    return read_table(data, "frames", columns=["split", "city"]).to_pylist()


@pytest.mark.parametrize(
    "option, value", [("--geo-buffer", "inf"), ("--geo-buffer", "nan"), ("--geo-buffer", "-1"),
                      ("--geo-cell", "inf"), ("--geo-cell", "nan"), ("--geo-cell", "-5")],
)  # fmt: skip
def test_a_geo_option_that_is_not_a_finite_length_is_refused_before_any_log_is_indexed(
    one_frame_logs, tmp_path, monkeypatch, option, value
):
    import pipeline.prepare

    monkeypatch.setattr(pipeline.prepare, "index_jobs", lambda jobs: pytest.fail("logs were indexed"))
    out = tmp_path / "geo"
    result = CliRunner().invoke(app, ["prepare", "--dataset", "av2", "--root", str(one_frame_logs), "--out",
                                      str(out), "--split-scheme", "geographic", option, value])  # fmt: skip
    assert result.exit_code in (1, 2), result.output  # 2: the command line's own range check
    said = [line for line in result.output.splitlines() if option in line]
    assert said and "cell_m" not in result.output and "Traceback" not in result.output, result.output
    if result.exit_code == 1:  # ours, in one line with the value
        assert [line for line in said if line.startswith("error:") and value in line] == said, said
    assert not out.exists()
