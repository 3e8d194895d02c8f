"""`cli score --format maptrv2|cgnet` (or auto, the default): other codebases' result files, written here
from the ground truth in each codebase's own conventions (docs/guide/score.md), scored as they are."""

from __future__ import annotations

import json
import pickle
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from benchmark.formats.cgnet_json import merge_equal_points
from benchmark.graph_table import graphs_from_table, read_graph_table
from benchmark.metric.params import MetricParams
from benchmark.score import score, score_pairs
from cli import app
from pipeline.io import SCHEMAS, read_table
from pipeline.lane_graph import LaneGraph

MAPTRV2_CENTERLINE = {"cls_name": "centerline", "type": 3}
CGNET_CENTERLINE = {"cls_name": "centerline", "type": 0}


def to_source(xy: np.ndarray, dataset: str) -> np.ndarray:
    """Our BEV frame (x right, y forward) -> the codebase's: nuScenes LIDAR_TOP is ours; AV2's egovehicle
    frame has x forward, y left."""
    xy = np.asarray(xy, np.float64)
    return xy if dataset == "nuscenes" else np.stack([xy[:, 1], -xy[:, 0]], axis=1)


def vector(xy: np.ndarray, score: float, kind: dict, z: bool = False) -> dict:
    pts = [[float(x), float(y), 0.5] if z else [float(x), float(y)] for x, y in xy]
    return {"pts": pts, "pts_num": len(pts), **kind, "confidence_level": score}


def token_of(frame: dict) -> str:
    return frame["sample_token"] or f"{frame['log_id']}_{frame['timestamp_ns']}"


def frames_of(data: Path, split: str = "val", stride: int = 1) -> list[dict]:
    """The frames of the split whose name ends with `split` (nuScenes mini's are mini_train, mini_val)."""
    table = read_table(data, "frames", ["frame_id", "split", "sample_token", "log_id", "timestamp_ns"])
    rows = sorted((r for r in table.to_pylist() if r["split"].endswith(split)), key=lambda r: r["frame_id"])
    return rows[::stride]


def lines_of(data: Path, table: str) -> dict[str, list[np.ndarray]]:
    rows = read_table(data, table, ["frame_id", "x", "y"]).to_pylist()
    out: dict[str, list[np.ndarray]] = {}
    for r in rows:
        out.setdefault(r["frame_id"], []).append(np.stack([r["x"], r["y"]], axis=1))
    return out


def write_results(path: Path, records: list[dict]) -> Path:
    path.write_text(json.dumps({"meta": {"use_camera": True}, "results": records}))
    return path


def maptrv2_file(data: Path, dataset: str, path: Path, stride: int = 1, z: bool = False) -> Path:
    """MapTRv2's file of the val frames: each ground-truth path a centerline (score 0.9), a low-scoring
    wrong centerline (0.35, under MapTRv2's 0.4) and a divider across the road (another class)."""
    paths = lines_of(data, "paths")
    records = []
    for frame in frames_of(data, stride=stride):
        vectors = [
            vector(to_source(p, dataset), 0.9, MAPTRV2_CENTERLINE, z) for p in paths[frame["frame_id"]]
        ]
        wrong = to_source(np.array([[-14.0, 29.0], [14.0, -29.0]]), dataset)
        vectors.append(vector(wrong, 0.35, MAPTRV2_CENTERLINE, z))
        vectors.append(vector(wrong, 0.99, {"cls_name": "divider", "type": 0}, z))
        records.append({"sample_token": token_of(frame), "vectors": vectors})
    return write_results(path, records)


def cgnet_file(data: Path, dataset: str, path: Path) -> Path:
    """CGNet's file: each ground-truth piece (their linked endpoints are one point, as CGNet's decoder
    snaps them) at score 0.8, and a wrong one at 0.25 (under CGNet's 0.3)."""
    pieces = lines_of(data, "pieces")
    records = []
    for frame in frames_of(data):
        vectors = [
            vector(to_source(p, dataset), 0.8, CGNET_CENTERLINE) for p in pieces.get(frame["frame_id"], [])
        ]
        vectors.append(
            vector(to_source(np.array([[-14.0, 29.0], [14.0, -29.0]]), dataset), 0.25, CGNET_CENTERLINE)
        )
        records.append({"sample_token": token_of(frame), "vectors": vectors})
    return write_results(path, records)


def f1s(result: dict) -> list[float]:
    return [
        result[mode][metric]["f1"]
        for mode in ("directed", "undirected")
        for metric in ("topo", "junction_topo")
    ]


@pytest.mark.parametrize("dataset", ["nuscenes", "av2"])
def test_maptrv2_and_cgnet_files_of_the_ground_truth_score_one(synth_prepared, tmp_path, dataset):
    data = synth_prepared[dataset]
    n_val = len(frames_of(data))
    maptrv2 = score(maptrv2_file(data, dataset, tmp_path / "m.json"), data, fmt="maptrv2")
    cgnet = score(cgnet_file(data, dataset, tmp_path / "c.json"), data, fmt="cgnet")
    for result in (maptrv2, cgnet):
        assert f1s(result) == [1.0] * 4 and result["frames"] == n_val and result["splits"][0].endswith("val")
        assert result["external"]["frames_not_in_file"] == 0 and result["external"]["points_clipped"] == 0
    assert maptrv2["external"]["vectors_kept"] == sum(
        len(lines_of(data, "paths")[f["frame_id"]]) for f in frames_of(data)
    )
    assert maptrv2["external"]["min_score"] == 0.4 and cgnet["external"]["min_score"] == 0.3
    # auto tells them apart; a kept score of 0.3 takes MapTRv2's wrong centerline, 0.2 CGNet's
    assert score(tmp_path / "m.json", data, fmt="auto")["external"]["format"] == "maptrv2"
    assert score(tmp_path / "c.json", data, fmt="auto")["external"]["format"] == "cgnet"
    assert score(tmp_path / "m.json", data, fmt="maptrv2", min_score=0.3)["directed"]["topo"]["precision"] < 1
    assert score(tmp_path / "c.json", data, fmt="cgnet", min_score=0.2)["directed"]["topo"]["precision"] < 1
    # another class as the scored one: the dividers alone, nothing of the ground truth
    dividers = score(tmp_path / "m.json", data, fmt="maptrv2", class_name="divider")
    assert dividers["external"]["vectors_kept"] == n_val and dividers["directed"]["topo"]["f1"] < 0.05


def test_av2_every_fourth_sweep_scores_the_frames_in_the_file(synth_prepared, tmp_path):
    """MapTRv2 loads every 4th AV2 validation sweep: the other three are not empty predictions."""
    data = synth_prepared["av2"]
    n_val = len(frames_of(data))
    result = score(
        maptrv2_file(data, "av2", tmp_path / "av2map_results.json", stride=4, z=True), data, fmt="maptrv2"
    )
    assert result["frames"] == len(frames_of(data, stride=4)) == result["external"]["frames_in_file"]
    assert result["external"]["frames_not_in_file"] == n_val - result["frames"] > 0
    gt = graphs_from_table(read_graph_table(data), data)
    itself = score_pairs(
        [(gt[f["frame_id"]], gt[f["frame_id"]]) for f in frames_of(data, stride=4)], MetricParams()
    )
    assert f1s(result) == f1s(itself) and result["directed"]["topo"]["f1"] == 1.0  # no junction: J-TOPO 0


def write_prepared(root: Path, dataset: str, graph: LaneGraph) -> tuple[Path, str]:
    """A one-frame prepared dataset (manifest, frames, graphs) of a given ground-truth graph; its token."""
    frame_id, token = (
        ("nuscenes/scene-0001/1000", "a" * 32) if dataset == "nuscenes" else ("av2/log-1/1000", None)
    )
    frame = {"frame_id": frame_id, "dataset": dataset, "split": "val", "sample_token": token,
             "log_id": frame_id.split("/")[1], "timestamp_ns": 1000}  # fmt: skip
    row = {"frame_id": frame_id, "x": graph.x.tolist(), "y": graph.y.tolist(), "src": graph.src.tolist(),
           "dst": graph.dst.tolist()}  # fmt: skip
    for name, rows in (("frames", [frame]), ("graphs", [row])):
        (root / name).mkdir(parents=True)
        pq.write_table(pa.Table.from_pylist(rows, SCHEMAS[name]), root / name / "log.parquet")
    manifest = {"dataset": dataset, "schema_version": 3, "parameters": {"bev_range": "30x60"}}
    (root / "manifest.json").write_text(json.dumps(manifest))
    return root, token or "log-1_1000"


# lanes on one side only, one way: a lane on the right going forward that forks to the right
TRUNK = np.array([[6.0, -25.0], [6.0, -5.0], [6.0, 10.0]])
BRANCHES = [np.array([[6.0, 10.0], [6.0, 28.0]]), np.array([[6.0, 10.0], [10.0, 17.0], [13.0, 27.0]])]


@pytest.mark.parametrize("dataset", ["nuscenes", "av2"])
def test_an_axis_the_av2_turn_or_a_direction_wrong_fails(tmp_path, dataset):
    paths = [np.concatenate([TRUNK, b[1:]]) for b in BRANCHES]
    points = np.concatenate([TRUNK, BRANCHES[0][1:], BRANCHES[1][1:]])
    graph = LaneGraph(points[:, 0].astype(np.float32), points[:, 1].astype(np.float32),
                      np.array([0, 1, 2, 2, 4], np.int32), np.array([1, 2, 3, 4, 5], np.int32))  # fmt: skip
    data, token = write_prepared(tmp_path / "data", dataset, graph)

    def scored(transform, name: str) -> dict:
        vectors = [vector(transform(p), 0.9, MAPTRV2_CENTERLINE) for p in paths]
        path = write_results(tmp_path / f"{name}.json", [{"sample_token": token, "vectors": vectors}])
        return score(path, data, fmt="maptrv2")

    assert f1s(scored(lambda p: to_source(p, dataset), "right")) == [1.0] * 4
    mirrored = scored(lambda p: to_source(p * [-1, 1], dataset), "mirrored")
    swapped = scored(lambda p: to_source(p[:, ::-1], dataset), "swapped")
    wrong_turn = scored(lambda p: -to_source(p, dataset), "turn")  # AV2: turned +90 deg, not -90
    reversed_ = scored(lambda p: to_source(p[::-1], dataset), "reversed")
    for wrong in (mirrored, swapped, wrong_turn):
        assert max(f1s(wrong)) < 0.1
    assert reversed_["directed"]["topo"]["f1"] < 0.1 and reversed_["undirected"]["topo"]["f1"] == 1.0
    if dataset == "av2":  # the file read as if it were in our frame: the turn is needed
        unturned = scored(lambda p: p, "unturned")
        assert max(f1s(unturned)) < 0.1


def test_points_outside_the_range_are_clipped_as_the_ground_truth(tmp_path):
    lane = np.array([[6.0, -30.0], [6.0, 30.0]])
    graph = LaneGraph(lane[:, 0].astype(np.float32), lane[:, 1].astype(np.float32), np.array([0], np.int32),
                      np.array([1], np.int32))  # fmt: skip
    data, token = write_prepared(tmp_path / "data", "nuscenes", graph)
    long = np.array([[6.0, -40.0], [6.0, 0.0], [6.0, 45.0]])
    path = write_results(
        tmp_path / "r.json", [{"sample_token": token, "vectors": [vector(long, 0.9, MAPTRV2_CENTERLINE)]}]
    )
    result = score(path, data, fmt="maptrv2")
    assert result["external"]["points_clipped"] == 2  # unclipped, 25 m past the range: false positives
    assert result["directed"]["topo"]["f1"] == result["undirected"]["topo"]["f1"] == 1.0


def test_graph_table_and_json_score_identically(synth_prepared, tmp_path):
    """The converted graphs written as a run folder's graph table score as the JSON did."""
    data = synth_prepared["nuscenes"]
    rng = np.random.default_rng(0)
    paths = lines_of(data, "paths")
    records = []
    for frame in frames_of(data):
        vectors = [vector((p + rng.normal(0, 0.3, p.shape)).astype(np.float32), 0.9, MAPTRV2_CENTERLINE)
                   for p in paths[frame["frame_id"]][1:]]  # fmt: skip
        records.append({"sample_token": frame["sample_token"], "vectors": vectors})
    path = write_results(tmp_path / "noisy.json", records)
    run = tmp_path / "runs" / "maptrv2"
    from_json = score(path, data, fmt="maptrv2", out=run, bootstrap=50)
    from_table = score(run / "predictions.parquet", data)
    assert 0.2 < from_json["directed"]["topo"]["f1"] < 0.95
    for mode in ("directed", "undirected"):
        for metric in ("topo", "junction_topo"):
            assert from_table[mode][metric]["f1"] == pytest.approx(from_json[mode][metric]["f1"], abs=1e-6)
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["model"] == "external" and metrics["params"] is None and metrics["split"] == "mini_val"
    assert metrics["external"]["format"] == "maptrv2" and len(metrics["external"]["sha256"]) == 64
    assert pq.read_table(run / "frame_counts.parquet").num_rows == metrics["frames"] == len(frames_of(data))


def test_cgnet_graph_merges_exactly_equal_points_only():
    a = np.array([[0.0, 0.0], [0.0, 5.0]])
    b = np.array([[0.0, 5.0], [3.0, 9.0]])
    c = np.array([[0.0, 5.0 + 1e-6], [-3.0, 9.0]])  # not snapped: a separate vertex
    graph = merge_equal_points([a, b, c])
    assert len(graph.x) == 5 and sorted(zip(graph.src.tolist(), graph.dst.tolist())) == [
        (0, 1),
        (1, 2),
        (3, 4),
    ]


@pytest.mark.parametrize(
    "record, message",
    [
        ({"vectors": []}, r"results\[0\]: no sample_token"),
        ({"pts": [[0, 0]]}, r"sample T: vectors\[0\].pts has 1 point"),
        ({"pts": [[0, 0], [1, float("nan")]]}, r"sample T: vectors\[0\].pts holds a NaN"),
        ({"cls_name": "lane"}, r"sample T: vectors\[0\].cls_name 'lane' is not one of maptrv2's"),
        ({"confidence_level": None}, r"sample T: vectors\[0\].confidence_level None"),
        ({"pts": [[0, 0, 0, 0], [1, 1, 1, 1]]}, r"sample T: vectors\[0\].pts is not a list of \[x, y\]"),
    ],
)  # fmt: skip
def test_malformed_records_name_the_file_sample_and_field(tmp_path, synth_prepared, record, message):
    if "vectors" not in record:  # a change to one good vector
        good = {"pts": [[0, 0], [1, 1]], "cls_name": "centerline", "confidence_level": 0.9}
        record = {"sample_token": "T", "vectors": [{**good, **record}]}
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({"results": [record]}))
    with pytest.raises(ValueError, match=f"bad.json: {message}"):
        score(path, synth_prepared["nuscenes"], fmt="maptrv2")


def test_unknown_ids_pickles_and_formats_are_refused(synth_prepared, tmp_path):
    data = synth_prepared["nuscenes"]
    unknown = write_results(
        tmp_path / "u.json", [{"sample_token": f"{i:032x}", "vectors": []} for i in range(5)]
    )
    with pytest.raises(
        ValueError, match=r"5 of 5 samples are not frames of the ground truth .*first: 0{32}, "
    ):
        score(unknown, data, fmt="maptrv2")
    train = frames_of(data, split="train")[0]
    other = write_results(tmp_path / "t.json", [{"sample_token": train["sample_token"], "vectors": []}])
    with pytest.raises(ValueError, match="1 samples are not of --split mini_val.*split mini_train"):
        score(other, data, fmt="maptrv2", split="mini_val")
    pickled = tmp_path / "results.pkl"
    pickled.write_bytes(pickle.dumps({"results": []}))
    for fmt in ("graph", "maptrv2", "cgnet"):
        with pytest.raises(ValueError, match="results.pkl: a pickle, refused: reading one can run code"):
            score(pickled, data, fmt=fmt)
    with pytest.raises(ValueError, match='results.pkl: not an OpenLane-V2 submission: no "results" dict'):
        score(pickled, data)  # auto: the one reader of pickles says why it does not read this one
    with pytest.raises(ValueError, match="u.json: a JSON file, not a graph table; pass --format"):
        score(unknown, data, fmt="graph")
    with pytest.raises(ValueError, match="--min-score: only for a result file"):
        score(unknown, data, fmt="graph", min_score=0.5)
    with pytest.raises(ValueError, match="--class-name boundary: not a cgnet class"):
        score(unknown, data, fmt="cgnet", class_name="boundary")


def test_cli_scores_sweeps_and_writes_a_run_folder(synth_prepared, tmp_path):
    data = synth_prepared["av2"]
    path = maptrv2_file(data, "av2", tmp_path / "av2map_results.json", stride=2)
    run = tmp_path / "external"
    result = CliRunner().invoke(app, ["score", "--pred", str(path), "--gt", str(data), "--format", "maptrv2",
                                      "--sweep", "--out", str(run), "--bootstrap", "20"])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "frames scored (those in the file)" in result.output and "F1 by kept score" in result.output
    metrics = json.loads((run / "metrics.json").read_text())
    sweep = {row["min_score"]: row for row in metrics["sweep"]}
    assert sweep[0.4]["directed"]["topo"] == 1.0 and sweep[0.3]["directed"]["topo"] < 1.0
    assert sweep[0.1]["vectors_kept"] > sweep[0.4]["vectors_kept"] == sweep[0.8]["vectors_kept"]
    trained = tmp_path / "ours"
    trained.mkdir()
    (trained / "config.json").write_text("{}")
    refused = CliRunner().invoke(app, ["score", "--pred", str(path), "--gt", str(data), "--format", "maptrv2",
                                       "--out", str(trained)])  # fmt: skip
    assert refused.exit_code == 1 and "holds a trained run (config.json)" in refused.output
    assert sorted(p.name for p in trained.iterdir()) == ["config.json"]


def test_a_nuscenes_dataset_prepared_before_sample_tokens_is_refused(synth_prepared, tmp_path):
    data = tmp_path / "old"
    shutil.copytree(synth_prepared["nuscenes"], data)
    for shard in (data / "frames").glob("*.parquet"):
        pq.write_table(pq.read_table(shard).drop_columns(["sample_token"]), shard)
    path = maptrv2_file(synth_prepared["nuscenes"], "nuscenes", tmp_path / "m.json")
    result = CliRunner().invoke(app, ["score", "--pred", str(path), "--gt", str(data), "--format", "maptrv2"])
    assert result.exit_code == 1
    error = [line for line in result.output.splitlines() if line.strip()]
    assert (
        len(error) == 1 and "column sample_token: missing" in error[0] and "re-run `cli prepare`" in error[0]
    )


def test_a_result_file_without_vectors_scores_alike_in_both_and_auto_asks_which(tmp_path):
    """An empty prediction is a submission (every frame scores 0 recall): MapTRv2's and CGNet's readers score
    it alike, but the result records whose file it is (its format, kept score and modeling), which nothing
    in the file tells: auto asks in one line rather than guess."""
    data, token = write_prepared(tmp_path / "data", "nuscenes", LaneGraph(
        np.array([6, 6], np.float32), np.array([-25, 10], np.float32), np.array([0], np.int32),
        np.array([1], np.int32)))  # fmt: skip
    path = write_results(tmp_path / "empty.json", [{"sample_token": token, "vectors": []}])
    maptrv2, cgnet = (score(path, data, fmt=fmt, bootstrap=0) for fmt in ("maptrv2", "cgnet"))
    assert maptrv2["directed"]["topo"] == {"precision": 0.0, "recall": 0.0, "f1": 0.0}
    assert {k: v for k, v in maptrv2.items() if k != "external"} == {
        k: v for k, v in cgnet.items() if k != "external"
    }
    assert (maptrv2["external"]["format"], maptrv2["external"]["min_score"]) == ("maptrv2", 0.4)
    assert (cgnet["external"]["format"], cgnet["external"]["min_score"]) == ("cgnet", 0.3)
    run = CliRunner().invoke(app, ["score", "--pred", str(path), "--gt", str(data), "--bootstrap", "0"])
    error = [line for line in run.output.splitlines() if line.strip()]
    assert run.exit_code == 1 and error == [
        f"error: {path}: no vectors to tell MapTRv2 from CGNet: pass --format maptrv2 or cgnet"
    ]
    nothing = write_results(tmp_path / "nothing.json", [])  # no sample at all: what each reader says
    for fmt in ("maptrv2", "cgnet", "auto"):
        with pytest.raises(ValueError, match=r"^\S*nothing.json: no sample in its results list$"):
            score(nothing, data, fmt=fmt, bootstrap=0)


def test_graphs_refusal_of_a_json_points_at_the_formats_that_read_it(tmp_path, monkeypatch):
    """`--format graph` on a result JSON names maptrv2 and cgnet, never auto (which cannot tell an empty
    one's codebase); the guide quotes the lines as they are."""
    data, token = write_prepared(tmp_path / "data", "nuscenes", LaneGraph.empty())
    monkeypatch.chdir(tmp_path)
    (tmp_path / "maptrv2" / "pts_bbox").mkdir(parents=True)
    path = write_results(
        Path("maptrv2/pts_bbox/nuscmap_results.json"), [{"sample_token": token, "vectors": []}]
    )
    with pytest.raises(ValueError) as refused:
        score(path, data, fmt="graph")
    line = f"{path}: a JSON file, not a graph table; pass --format maptrv2 or cgnet"
    assert str(refused.value) == line
    table = Path("my_predictions.parquet")
    pq.write_table(pa.Table.from_pylist([], SCHEMAS["graphs"]), table)
    with pytest.raises(ValueError) as refused:
        score(table, data, min_score=0.5)
    options_line = (
        "--min-score: only for a result file of another codebase (--format maptrv2 or cgnet); "
        "my_predictions.parquet is read as a graph table"
    )
    assert str(refused.value) == options_line
    guide = (Path(__file__).resolve().parents[1] / "docs" / "guide" / "score.md").read_text()
    assert f"`error: {line}`" in guide and f"`error: {options_line}`" in guide
    assert score(path, data, fmt="maptrv2", bootstrap=0)["frames"] == 1  # the advice reads it


@pytest.mark.parametrize("given", ["inf", "1.5", "-0.1", "nan"])
def test_a_kept_score_outside_0_to_1_is_refused_in_one_line(tmp_path, given):
    """Confidences are probabilities: a kept score above 1 would drop every vector unsaid."""
    data, token = write_prepared(tmp_path / "data", "nuscenes", LaneGraph.empty())
    path = write_results(tmp_path / "r.json", [{"sample_token": token, "vectors": [
        vector(TRUNK, 0.9, MAPTRV2_CENTERLINE)]}])  # fmt: skip
    run = CliRunner().invoke(app, ["score", "--pred", str(path), "--gt", str(data), "--min-score", given])
    assert run.exit_code != 0 and "--min-score" in run.output, run.output
    assert "frames scored" not in run.output
    with pytest.raises(ValueError, match=rf"^--min-score {given}: not a confidence from 0 to 1$"):
        score(path, data, min_score=float(given))
