"""The sensor-blind floor of `cli eval` (baselines/floor.py): its baselines, its cache, its margins."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest
from test_baselines_train import cli_train_toy, write_toy_dataset
from typer.testing import CliRunner

from baselines import floor as floor_module
from baselines.evaluate import evaluate
from baselines.floor import blind_floor, contract_margins, floor_margins, other_log_partners, spread
from benchmark.graph_table import graphs_from_table, read_graph_table
from benchmark.metric.params import MetricParams
from benchmark.score import score_pairs
from cli import app
from pipeline.lane_graph import LaneGraph


def fork() -> LaneGraph:
    """A lane that splits in two at (0, 0): one directed junction."""
    return LaneGraph(
        np.array([0.0, 0.0, -3.0, 3.0]), np.array([-20.0, 0.0, 20.0, 20.0]),
        np.array([0, 1, 1], np.int32), np.array([1, 2, 3], np.int32),
    )  # fmt: skip


def frame(frame_id: str, log_id: str, timestamp_ns: int) -> dict:
    return {"frame_id": frame_id, "log_id": log_id, "timestamp_ns": timestamp_ns}


def test_spread_keeps_the_ends_and_the_count():
    assert spread(list(range(10)), 4) == [0, 3, 6, 9]
    assert spread([1, 2], 32) == [1, 2]


def test_other_log_partners_take_the_same_position_in_the_next_log():
    frames = [frame("b/0", "b", 0), frame("a/1", "a", 1), frame("a/0", "a", 0), frame("a/2", "a", 2),
              frame("b/1", "b", 1)]  # fmt: skip
    assert other_log_partners(frames) == {
        "a/0": "b/0",
        "a/1": "b/1",
        "a/2": "b/0",
        "b/0": "a/0",
        "b/1": "a/1",
    }
    assert other_log_partners([frame("a/0", "a", 0), frame("a/1", "a", 1)]) == {}


def test_constant_prior_of_identical_graphs_scores_one_and_one_log_has_no_other_sensors(tmp_path):
    frames = [frame(f"toy/{i}", "toy", i) for i in range(3)]
    ground_truth = {f["frame_id"]: fork() for f in frames}
    predictions = {f["frame_id"]: LaneGraph.empty() for f in frames}
    params = MetricParams()
    floor = blind_floor(predictions, ground_truth, frames, sorted(ground_truth), "train", params, tmp_path)
    assert floor["other_log_sensors"] is None
    assert floor["absent"] == {
        "other_log_sensors": "the split has a single log (toy): no other log's sensors"
    }
    prior = floor["constant_prior"]
    assert prior["frame_id"] == "toy/0" and prior["train_f1"] == 1.0 and not prior["cached"]
    assert prior["candidates"] == prior["scored_frames"] == 3 and prior["frames"] == 3
    for mode in ("directed", "undirected"):
        assert prior[mode]["topo"]["f1"] == prior[mode]["junction_topo"]["f1"] == 1.0
    assert floor["f1"] == {mode: {"topo": 1.0, "junction_topo": 1.0} for mode in ("directed", "undirected")}
    # the empty predictions score 0: the margin over the floor is -1 everywhere
    metrics = score_pairs([(predictions[f], ground_truth[f]) for f in sorted(ground_truth)], params)
    assert floor_margins({**metrics, "floor": floor})["directed"] == {"topo": -1.0, "junction_topo": -1.0}
    with pytest.raises(ValueError, match="no floor"):
        floor_margins(metrics)


@pytest.fixture(scope="module")
def two_log_run(tmp_path_factory):
    """A LiDAR LaneGAP trained one epoch on 4 toy frames, frames 0-1 in log a, 2-3 in log b."""
    root = tmp_path_factory.mktemp("floor")
    data = write_toy_dataset(root, frames=4)
    shard = data / "frames" / "train__toy.parquet"
    frames = pq.read_table(shard)
    log_ids = ["a" if int(f.rsplit("/", 1)[1]) < 2 else "b" for f in frames["frame_id"].to_pylist()]
    pq.write_table(frames.set_column(frames.schema.get_field_index("log_id"), "log_id", [log_ids]), shard)
    run = root / "run"
    cli_train_toy(data, run)
    return run, data


def test_eval_writes_the_floor_and_the_margin(two_log_run):
    run, data = two_log_run
    result = CliRunner().invoke(app, ["eval", "--run", str(run), "--device", "cpu"])
    assert result.exit_code == 0, result.output
    assert "margin" in result.output and "constant prior: the ground truth of av2/toy/" in result.output
    metrics = json.loads((run / "metrics.json").read_text())
    floor = metrics["floor"]
    assert set(floor) == {"other_log_sensors", "constant_prior", "best_constant", "absent", "f1", "margin"}
    assert floor["absent"] == {}
    # other log's sensors: the model's prediction for the partner frame, scored on the frame's own GT
    predictions = graphs_from_table(pq.read_table(run / "predictions.parquet"), run)
    ground_truth = graphs_from_table(read_graph_table(data), data)
    partner = {0: 2, 1: 3, 2: 0, 3: 1}
    pairs = [(predictions[f"av2/toy/{partner[i]}"], ground_truth[f"av2/toy/{i}"]) for i in range(4)]
    expected = score_pairs(pairs, MetricParams(**metrics["metric_params"]))
    assert floor["other_log_sensors"]["directed"] == expected["directed"]
    assert floor["other_log_sensors"]["undirected"] == expected["undirected"]
    prior = floor["constant_prior"]
    assert prior["frame_id"] in ground_truth and prior["split"] == "train" and prior["frames"] == 4
    assert prior["candidates"] == 4 and prior["scored_frames"] == 4
    for mode in ("directed", "undirected"):
        for metric in ("topo", "junction_topo"):
            best = max(floor["other_log_sensors"][mode][metric]["f1"], prior[mode][metric]["f1"])
            assert floor["f1"][mode][metric] == best
            assert floor["margin"][mode][metric] == pytest.approx(metrics[mode][metric]["f1"] - best)
    assert floor_margins(metrics) == floor["margin"]
    # the best constant in hindsight: of the same candidates, the best on the evaluated frames themselves
    best = floor["best_constant"]
    assert best["candidates"] == 4 and best["scored_frames"] == 4 and best["split"] == "train"
    hindsight = {}
    for candidate in (f"av2/toy/{i}" for i in range(4)):
        pairs = [
            (ground_truth[candidate], ground_truth[f"av2/toy/{i}"])
            for i in range(4)
            if i != int(candidate[-1])
        ]
        hindsight[candidate] = score_pairs(pairs, MetricParams(**metrics["metric_params"]))["directed"][
            "topo"
        ]["f1"]
    assert best["hindsight_f1"] == max(hindsight.values())
    assert hindsight[best["frame_id"]] == max(hindsight.values())
    pairs = [(ground_truth[best["frame_id"]], ground_truth[f"av2/toy/{i}"]) for i in range(4)]
    assert best["directed"] == score_pairs(pairs, MetricParams(**metrics["metric_params"]))["directed"]
    margins = contract_margins(metrics)
    for metric in ("topo", "junction_topo"):
        f1 = metrics["directed"][metric]["f1"]
        assert margins["sensors"][metric] == f1 - floor["other_log_sensors"]["directed"][metric]["f1"]
        assert margins["best_constant"][metric] == f1 - best["directed"][metric]["f1"]


def test_prior_search_is_cached_beside_the_data(two_log_run, monkeypatch):
    run, data = two_log_run
    cache = data / "floor_cache"
    for path in cache.glob("*.json"):
        path.unlink()
    calls = []

    def counted(pairs, params, workers=1):
        calls.append(len(pairs))
        return score_pairs(pairs, params, workers)

    monkeypatch.setattr(floor_module, "score_pairs", counted)
    first = evaluate(run, device="cpu")["floor"]["constant_prior"]
    # other log's sensors (4 frames), 4 candidates each on the 3 other frames, the prior (4 frames);
    # the same for the best constant in hindsight, on the evaluated frames
    assert calls == [4, 3, 3, 3, 3, 4, 3, 3, 3, 3, 4] and not first["cached"]
    (written,) = cache.glob("constant_prior__train__*.json")
    assert json.loads(written.read_text())["frame_id"] == first["frame_id"]
    calls.clear()
    second = evaluate(run, device="cpu")["floor"]["constant_prior"]
    assert calls == [4, 4, 4] and second["cached"]
    assert {**first, "cached": True} == second


def test_no_floor_leaves_it_out(two_log_run):
    run, _ = two_log_run
    result = CliRunner().invoke(app, ["eval", "--run", str(run), "--device", "cpu", "--no-floor"])
    assert result.exit_code == 0, result.output
    metrics = json.loads((run / "metrics.json").read_text())
    assert "floor" not in metrics and "margin" not in result.output
    with pytest.raises(ValueError, match="no floor"):
        floor_margins(metrics)
