"""Bootstrap intervals over frames (benchmark/metric/bootstrap.py): exact cases, golden values, the paired
difference, the per-frame counts behind them, and `cli score --bootstrap`."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from test_score import FORK, LANE
from typer.testing import CliRunner

from benchmark.metric import bootstrap
from benchmark.metric.params import MetricParams
from benchmark.metric.totals import FRAME_COLUMNS, score_graphs
from benchmark.score import score_frames, score_pairs
from cli import app
from pipeline.io import SCHEMAS
from pipeline.lane_graph import LaneGraph

MERGE = LaneGraph(
    np.array([-2.25, 0, 0, 0], np.float32),
    np.array([0, 0, 3, 6], np.float32),
    np.array([0, 1, 2], np.int32),
    np.array([2, 2, 3], np.int32),
)


def shifted(g: LaneGraph, dx: float) -> LaneGraph:
    return LaneGraph(g.x + np.float32(dx), g.y, g.src, g.dst)


def fixture_pairs() -> list[tuple[LaneGraph, LaneGraph]]:
    """Eight frames of (prediction, ground truth): perfect, shifted, truncated, empty and swapped."""
    return [
        (FORK, FORK),
        (shifted(FORK, 0.3), FORK),
        (LANE, FORK),
        (LaneGraph.empty(), MERGE),
        (MERGE, MERGE),
        (shifted(MERGE, 0.6), MERGE),
        (FORK, MERGE),
        (LANE, LANE),
    ]


# Computed once by this code (1,000 draws, seed 0); test_a_draw_is_the_metric_on_the_resampled_frames
# checks the draws against the metric itself. A change of the draws or of the pooling moves these digits.
GOLDEN = {
    "directed": {"topo": [0.30550294515804055, 0.8691809720203778],
                 "junction_topo": [0.29629629629629634, 0.8936450092659162]},
    "undirected": {"topo": [0.2850627486991123, 0.87891954613422],
                   "junction_topo": [0.3928170594837262, 0.903181818181818]},
}  # fmt: skip


def test_a_perfect_prediction_has_the_interval_one_one():
    pairs = [(g, g) for g in (FORK, MERGE, FORK, MERGE, FORK)]  # every frame has a junction
    result = score_pairs(pairs, MetricParams(), bootstrap=1000)
    for mode in ("directed", "undirected"):
        for metric in ("topo", "junction_topo"):
            assert result[mode][metric]["f1"] == 1.0
            assert result[mode][metric]["f1_ci"] == [1.0, 1.0]
    assert result["bootstrap"] == {"draws": 1000, "seed": 0, "level": 0.95, "over": "frames",
                                   "interval": "percentile"}  # fmt: skip


def test_the_fixture_intervals_are_golden_and_hold_the_point_estimates():
    result = score_pairs(fixture_pairs(), MetricParams(), bootstrap=1000)
    for mode, by_metric in GOLDEN.items():
        for metric, interval in by_metric.items():
            assert result[mode][metric]["f1_ci"] == pytest.approx(interval, abs=1e-12), (mode, metric)
            low, high = result[mode][metric]["f1_ci"]
            assert low < result[mode][metric]["f1"] < high


def test_the_counts_pool_back_to_the_scores():
    result, counts = score_frames(fixture_pairs(), MetricParams())
    assert counts.shape == (8, len(FRAME_COLUMNS))
    pooled = bootstrap.pooled_f1(counts, np.ones((1, len(counts))))
    for (mode, metric), f1 in pooled.items():
        assert f1[0] == pytest.approx(result[mode][metric]["f1"], abs=1e-12)
    # the frames in processes give the same rows, in the pairs' order
    _, in_two = score_frames(fixture_pairs() * 3, MetricParams(), workers=2)
    np.testing.assert_array_equal(in_two, np.concatenate([counts] * 3))


def test_a_draw_is_the_metric_on_the_resampled_frames():
    pairs = fixture_pairs()
    _, counts = score_frames(pairs, MetricParams())
    w = bootstrap.weights(len(pairs), 5)
    pooled = bootstrap.pooled_f1(counts, w)
    for d in range(5):
        resampled = [pairs[f] for f in np.repeat(np.arange(len(pairs)), w[d].astype(int))]
        direct = score_graphs(resampled, MetricParams())
        for (mode, metric), f1 in pooled.items():
            assert f1[d] == pytest.approx(direct[mode][metric]["f1"], abs=1e-12)


def test_the_draws_resample_frames_and_are_seeded():
    w = bootstrap.weights(7, 500)
    assert w.shape == (500, 7) and (w.sum(axis=1) == 7).all()
    assert np.array_equal(w, bootstrap.weights(7, 500))
    assert not np.array_equal(w, bootstrap.weights(7, 500, seed=1))
    # each frame is in a draw 1 time on average
    assert abs(w.mean() - 1) < 1e-12 and 0.9 < w[:, 0].mean() < 1.1


def test_the_paired_interval_of_a_run_against_itself_is_zero():
    _, counts = score_frames(fixture_pairs(), MetricParams())
    paired = bootstrap.paired(counts, counts)
    assert paired == {mode: {"topo": [0.0, 0.0], "junction_topo": [0.0, 0.0]} for mode in bootstrap.MODES}


def test_a_paired_difference_is_tighter_than_the_two_intervals():
    """Same frames, same draws: a run that beats another on every frame leads; the frame-to-frame spread
    both share cancels in the difference."""
    truth = [FORK, MERGE, FORK, MERGE, LANE, FORK, MERGE, FORK]
    better = [(shifted(g, 0.1), g) for g in truth]
    worse = [(shifted(g, 0.1) if i % 2 else LaneGraph.empty(), g) for i, g in enumerate(truth)]
    (a, counts_a), (b, counts_b) = score_frames(better, MetricParams()), score_frames(worse, MetricParams())
    low, high = bootstrap.paired(counts_a, counts_b)["directed"]["topo"]
    assert 0 < low <= a["directed"]["topo"]["f1"] - b["directed"]["topo"]["f1"] <= high
    with pytest.raises(ValueError, match="same"):
        bootstrap.paired(counts_a, counts_b[:3])


def test_no_draws_no_intervals_and_negative_draws_refused():
    result = score_pairs(fixture_pairs(), MetricParams(), bootstrap=0)
    assert "bootstrap" not in result and "f1_ci" not in result["directed"]["topo"]
    with pytest.raises(ValueError, match="--bootstrap must be 0"):
        score_pairs(fixture_pairs(), MetricParams(), bootstrap=-1)


def test_frame_counts_file_round_trip(tmp_path):
    _, counts = score_frames(fixture_pairs(), MetricParams())
    ids = [f"log/{i}" for i in range(len(counts))]
    bootstrap.write_frame_counts(tmp_path / "c.parquet", ids, counts)
    read_ids, read_counts = bootstrap.read_frame_counts(tmp_path / "c.parquet")
    assert read_ids == ids and np.array_equal(read_counts, counts)
    pq.write_table(pa.table({"frame_id": ids}), tmp_path / "bad.parquet")
    with pytest.raises(ValueError, match="bad.parquet: not a per-frame count table"):
        bootstrap.read_frame_counts(tmp_path / "bad.parquet")


def test_cli_score_prints_and_writes_the_intervals(tmp_path):
    def table(rows):
        rows = [{"frame_id": f, "x": list(g.x), "y": list(g.y), "src": list(g.src), "dst": list(g.dst)}
                for f, g in rows]  # fmt: skip
        return pa.Table.from_pylist(rows, SCHEMAS["graphs"])

    pairs = fixture_pairs()
    pq.write_table(table([(f"f/{i}", p) for i, (p, _) in enumerate(pairs)]), tmp_path / "pred.parquet")
    pq.write_table(table([(f"f/{i}", g) for i, (_, g) in enumerate(pairs)]), tmp_path / "gt.parquet")
    args = ["score", "--pred", str(tmp_path / "pred.parquet"), "--gt", str(tmp_path / "gt.parquet")]
    result = CliRunner().invoke(app, args + ["--out", str(tmp_path / "s.json")])
    assert result.exit_code == 0, result.output
    written = json.loads((tmp_path / "s.json").read_text())
    low, high = GOLDEN["directed"]["topo"]
    assert written["directed"]["topo"]["f1_ci"] == pytest.approx([low, high], abs=1e-12)
    assert f"{low:.3f}-{high:.3f}" in result.output and "95 % interval" in result.output
    result = CliRunner().invoke(app, args + ["--bootstrap", "0", "--out", str(tmp_path / "s0.json")])
    assert result.exit_code == 0 and "f1_ci" not in (tmp_path / "s0.json").read_text()
    result = CliRunner().invoke(app, args + ["--bootstrap", "-5"])
    assert result.exit_code != 0 and "--bootstrap" in result.output
