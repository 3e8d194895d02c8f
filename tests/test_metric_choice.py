"""`--metric` (issue 53): the published lane-graph metrics chosen by name in cli score, each under its own
name in the result, scored in the same workers as LaneGAP's; bad choices are one clear line."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from benchmark.graph_table import graphs_from_table, read_graph_table
from benchmark.metric.params import MetricParams
from benchmark.metric.table import METRICS, parse_metrics
from benchmark.score import score, score_frames
from cli import app
from pipeline.lane_graph import LaneGraph


def test_metric_names_parse_in_a_fixed_order_and_a_bad_one_is_named():
    assert [metric.name for metric in parse_metrics("openlanev2, lanegap")] == ["lanegap", "openlanev2"]
    assert parse_metrics(",".join(metric.name for metric in reversed(METRICS))) == METRICS
    expected = "--metric 'lanegap,topo': expected one or more of lanegap, cgnet, openlanev2"
    with pytest.raises(ValueError, match=expected):
        parse_metrics("lanegap,topo")


@pytest.fixture(scope="module")
def pairs(synth_prepared) -> list[tuple[LaneGraph, LaneGraph]]:
    """Each synthetic AV2 frame's ground truth against the next frame's (a prediction that is partly
    right), and the last frame against an empty prediction."""
    data = synth_prepared["av2"]
    gt = graphs_from_table(read_graph_table(data), data)
    frames = sorted(gt)
    return [(gt[b], gt[a]) for a, b in zip(frames, frames[1:])] + [(LaneGraph.empty(), gt[frames[0]])]


def test_a_variant_adds_its_own_result_and_leaves_lanegap_s_as_it_was(pairs):
    params = MetricParams()
    alone, counts = score_frames(pairs, params)
    both, both_counts = score_frames(pairs, params, metrics=parse_metrics("lanegap,openlanev2"))
    assert {key: value for key, value in both.items() if key != "openlanev2"} == alone
    assert (both_counts == counts).all()
    ol = both["openlanev2"]
    assert ol["frames"] == len(pairs) and 0.0 < ol["det_l"] < 1.0 and 0.0 < ol["top_ll"] < 1.0
    only, _ = score_frames(pairs, params, metrics=parse_metrics("openlanev2"))
    assert set(only) == {"openlanev2"} and only["openlanev2"] == ol


def test_workers_give_the_variant_the_same_digits(pairs):
    params = MetricParams()
    one, _ = score_frames(pairs, params, workers=1, metrics=METRICS)
    two, _ = score_frames(pairs, params, workers=2, metrics=METRICS)
    assert json.dumps(one, sort_keys=True) == json.dumps(two, sort_keys=True)


def test_cli_score_writes_each_metric_under_its_name(synth_prepared, tmp_path):
    data = synth_prepared["av2"]
    out = tmp_path / "all.json"
    args = ["--metric", "openlanev2,lanegap,cgnet", "--bootstrap", "0", "--out", str(out)]
    result = CliRunner().invoke(app, ["score", "--pred", str(data), "--gt", str(data), *args])
    assert result.exit_code == 0, result.output
    written = json.loads(out.read_text())
    assert written["directed"]["topo"]["f1"] == 1.0 and written["openlanev2"]["det_l"] == 1.0
    assert written["openlanev2"]["top_ll"] == 1.0 and "DET_l" in result.output
    assert [written["cgnet"][name]["f1"] for name in ("geo", "topo", "jtopo")] == [1.0, 1.0, 1.0]
    assert written["cgnet"]["version"] == 1 and "CGNet's evaluator" in result.output


def test_what_needs_lanegap_refuses_a_choice_without_it(synth_prepared, tmp_path):
    data = synth_prepared["av2"]
    with pytest.raises(ValueError, match="--out .*run folder holds LaneGAP's scores"):
        score(data, data, tmp_path / "run", metrics=parse_metrics("openlanev2"))
    assert not (tmp_path / "run").exists()
    result = CliRunner().invoke(app, ["score", "--pred", str(data), "--gt", str(data), "--metric", "nope"])
    assert result.exit_code == 1 and result.output.count("error:") == 1 and "--metric 'nope'" in result.output


def test_cli_report_adds_a_table_per_other_metric(synth_prepared, tmp_path):
    from benchmark.report.writer import write_report

    data = synth_prepared["av2"]
    score(data / "graphs", data, tmp_path / "runs" / "gt_as_prediction", bootstrap=0)  # an external run
    report = write_report([tmp_path / "runs"], tmp_path / "report", draws=0, metrics=METRICS)
    text = report.path.read_text()
    table = text[text.index("### OpenLane-V2's DET_l and TOP_ll"):]
    assert "| run | DET_l | TOP_ll |" in table and "| gt_as_prediction | 100.0 | 100.0 |" in table
    cgnet = text[text.index("### CGNet's metric"):]
    assert "| run | GEO P | GEO R | GEO F1 | TOPO P |" in cgnet
    assert "| gt_as_prediction | 100.0 | 100.0 | 100.0 | 100.0 |" in cgnet
    plain = write_report([tmp_path / "runs"], tmp_path / "plain", draws=0).path.read_text()
    assert "OpenLane-V2" not in plain


def test_cgnet_through_the_workers_equals_its_own_functions(pairs):
    from benchmark.metric.cgnet import cgnet_frame, cgnet_result
    from benchmark.metric.params import CGNetParams

    scored, _ = score_frames(pairs, MetricParams(), workers=2, metrics=parse_metrics("cgnet"))
    direct = cgnet_result([cgnet_frame(pred, gt, CGNetParams()) for pred, gt in pairs])
    assert scored == {"cgnet": direct} and 0.0 < direct["topo"]["f1"] < 1.0


def test_cgnet_says_when_the_data_reach_beyond_its_box(pairs):
    wide, _ = score_frames(pairs, MetricParams(bev_range="50x100"), metrics=parse_metrics("cgnet"))
    assert "50x100" in wide["cgnet"]["note"] and "drops the lanes beyond" in wide["cgnet"]["note"]
    assert "note" not in score_frames(pairs, MetricParams(), metrics=parse_metrics("cgnet"))[0]["cgnet"]
