"""`cli score` and `cli roundtrip`: graph-table reading and checking, the JSON, the command line."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from benchmark.graph_table import GraphTableError, graphs_from_table, read_graph_table
from benchmark.metric.params import MetricParams
from benchmark.metric.totals import score_graphs
from benchmark.score import score
from cli import app
from pipeline.io import SCHEMAS, read_table
from pipeline.lane_graph import LaneGraph

LANE = LaneGraph(np.array([0, 0], np.float32), np.array([0, 3], np.float32), np.array([0]), np.array([1]))
FORK = LaneGraph(
    np.array([0, 0, 0, 2.25], np.float32),
    np.array([0, 3, 6, 6], np.float32),
    np.array([0, 1, 1], np.int32),
    np.array([1, 2, 3], np.int32),
)


def row(frame_id: str, g: LaneGraph) -> dict:
    return {"frame_id": frame_id, "x": list(g.x), "y": list(g.y), "src": list(g.src), "dst": list(g.dst)}


def write(path, rows: list[dict], schema=SCHEMAS["graphs"]):
    pq.write_table(pa.Table.from_pylist(rows, schema), path)
    return path


@pytest.fixture
def gt_file(tmp_path):
    return write(tmp_path / "gt.parquet", [row("f/a", LANE), row("f/b", FORK)])


def test_perfect_prediction_and_the_json_shape(gt_file, tmp_path):
    out = tmp_path / "deep" / "metrics.json"
    result = score(gt_file, gt_file, out)
    assert list(result)[:5] == ["frames", "directed", "undirected", "miou", "metric_params"]
    assert result["frames"] == 2
    for mode in ("directed", "undirected"):
        assert list(result[mode]) == ["topo", "junction_topo"]
        for metric in result[mode].values():
            assert metric == {"precision": 1.0, "recall": 1.0, "f1": 1.0}
    assert result["metric_params"] == MetricParams().as_dict()
    assert json.loads(out.read_text()) == result


def test_a_frame_without_prediction_counts_as_empty(gt_file, tmp_path):
    pred = write(tmp_path / "pred.parquet", [row("f/b", FORK)])
    result = score(pred, gt_file)
    expected = score_graphs([(LaneGraph.empty(), LANE), (FORK, FORK)])
    assert result["directed"] == expected["directed"] and result["miou"] == expected["miou"]
    assert result["directed"]["topo"]["recall"] == pytest.approx(66 / (21 + 66))
    assert (result["frames"], result["frames_predicted"]) == (2, 1)


def test_params_reach_the_metric_and_the_file(gt_file):
    result = score(gt_file, gt_file, reach_radius=2.0, matching="optimal", bev_range="50x100")
    assert result["metric_params"]["reach_radius"] == 2.0
    assert result["metric_params"]["matching"] == "optimal"
    assert result["metric_params"]["bev_range"] == "50x100"


def test_more_workers_give_the_same_digits(prepared_av2, tmp_path):
    gt = read_table(prepared_av2, "graphs").slice(0, 24)
    graphs = graphs_from_table(gt, prepared_av2)
    rng = np.random.default_rng(0)
    noisy = [
        row(f, LaneGraph(g.x + rng.normal(0, 0.2, len(g.x)), g.y, g.src, g.dst))
        for f, g in sorted(graphs.items())
    ]
    pred = write(tmp_path / "pred.parquet", noisy)
    gt_path = write(tmp_path / "gt.parquet", gt.to_pylist())
    assert score(pred, gt_path, workers=2) == score(pred, gt_path, workers=1)


def test_a_prepared_dataset_is_ground_truth(prepared_av2, tmp_path):
    """Its `graphs` folder is read, the frames of the predicted frames' split are scored (those without a
    prediction as empty ones), and its perception range sets the mIoU grid."""
    first = read_table(prepared_av2, "graphs").slice(0, 3)
    pred = write(tmp_path / "pred.parquet", first.to_pylist())
    result = score(pred, prepared_av2)
    splits = dict(zip(*read_table(prepared_av2, "frames", ["frame_id", "split"]).to_pydict().values()))
    (split,) = {splits[f] for f in first.column("frame_id").to_pylist()}
    in_split = sum(s == split for s in splits.values())
    assert result["splits"] == [split] and len(splits) > in_split  # the other split is not scored
    counts = (result["frames"], result["frames_predicted"], result["frames_missing"])
    assert counts == (in_split, 3, in_split - 3)
    assert result["metric_params"]["bev_range"] == "30x60"
    assert 0 < result["directed"]["topo"]["recall"] < 0.05 and result["directed"]["topo"]["precision"] == 1.0


@pytest.mark.parametrize(
    "bad, message",
    [
        ({"x": [0.0, 1.0], "y": [0.0]}, "f/b: x and y have different lengths"),
        ({"src": [0, 1], "dst": [1]}, "f/b: src and dst have different lengths"),
        ({"src": [0], "dst": [5]}, "f/b: an edge index is out of range"),
        ({"src": [-1], "dst": [1]}, "f/b: an edge index is out of range"),
        ({"x": [0.0, float("nan")]}, "f/b: x or y is NaN or infinite"),
        ({"y": [0.0, float("inf")]}, "f/b: x or y is NaN or infinite"),
        ({"x": None}, "f/b: x is null"),
        ({"x": [0.0, None]}, "f/b: null in x"),
    ],
)
def test_malformed_rows_name_the_file_and_frame(tmp_path, gt_file, bad, message):
    good = {"frame_id": "f/b", "x": [0.0, 0.0], "y": [0.0, 3.0], "src": [0], "dst": [1]}
    pred = write(tmp_path / "pred.parquet", [row("f/a", LANE), {**good, **bad}])
    with pytest.raises(GraphTableError, match=f"pred.parquet: frame {message}"):
        score(pred, gt_file)


def test_tables_that_cannot_be_scored(tmp_path, gt_file):
    with pytest.raises(GraphTableError, match="frame f/zzz is not in the ground truth"):
        score(write(tmp_path / "p1.parquet", [row("f/zzz", LANE)]), gt_file)
    with pytest.raises(GraphTableError, match="frame f/a: more than one row"):
        score(write(tmp_path / "p2.parquet", [row("f/a", LANE), row("f/a", LANE)]), gt_file)
    with pytest.raises(GraphTableError, match="missing column"):
        read_graph_table(
            write(tmp_path / "p3.parquet", [{"frame_id": "f/a"}], pa.schema([("frame_id", pa.string())]))
        )
    floats = pa.schema(
        [(f.name, pa.list_(pa.float32())) if f.name == "src" else f for f in SCHEMAS["graphs"]]
    )
    with pytest.raises(GraphTableError, match="column src is list<.*float>, not a list of integers"):
        score(write(tmp_path / "p4.parquet", [row("f/a", LANE)], floats), gt_file)
    with pytest.raises(GraphTableError, match="missing.parquet: no such file"):
        score(tmp_path / "missing.parquet", gt_file, fmt="graph")
    (tmp_path / "junk.parquet").write_text("not parquet")
    with pytest.raises(GraphTableError, match="junk.parquet: not a readable Parquet graph table"):
        score(tmp_path / "junk.parquet", gt_file, fmt="graph")


def test_cli_score_prints_and_writes_the_json(gt_file, tmp_path):
    out = tmp_path / "m.json"
    run = CliRunner().invoke(app, ["score", "--pred", str(gt_file), "--gt", str(gt_file), "--out", str(out)])
    assert run.exit_code == 0, run.output
    lines = run.stdout.splitlines()
    assert len(lines) < 15 and any("directed Junction TOPO" in line for line in lines)
    topo_f1 = json.loads(out.read_text())["directed"]["topo"]["f1"]
    cells = [line for line in lines if "directed TOPO" in line][0].split()
    assert (cells[-4], cells[-2]) == (f"{topo_f1:.3f}", "1.000-1.000")  # F1 and its interval
    run = CliRunner().invoke(app, ["score", "--pred", str(gt_file), "--gt", str(gt_file), "--json"])
    assert json.loads(run.stdout) == json.loads(out.read_text())
    bad = write(tmp_path / "bad.parquet", [row("f/nope", LANE)])
    run = CliRunner().invoke(app, ["score", "--pred", str(bad), "--gt", str(gt_file)])
    assert run.exit_code == 1 and "f/nope" in run.output


def test_cli_roundtrip(prepared_av2, tmp_path):
    out = tmp_path / "rt.json"
    args = [
        "roundtrip",
        "--data",
        str(prepared_av2),
        "--via",
        "piece",
        "--out",
        str(out),
        "--frame-stride",
        "40",
    ]
    run = CliRunner().invoke(app, args)
    assert run.exit_code == 0, run.output
    result = json.loads(out.read_text())
    assert result["frames"] == 8 and result["directed"]["topo"]["f1"] == 1.0
    run = CliRunner().invoke(app, ["roundtrip", "--data", str(prepared_av2), "--via", "polygon"])
    assert run.exit_code == 2 and "Invalid value for '--via'" in run.output  # click's usage error
