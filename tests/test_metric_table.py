"""The table of metrics (benchmark/metric/table.py) is the one place that knows a metric by name: no other
module compares a metric's name or reads a result by it, and a metric added to the table alone is chosen by
--metric, scored, written under its name, printed and given its report table."""

from __future__ import annotations

import ast
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from benchmark.metric import table
from benchmark.metric.frame import Frame
from benchmark.metric.params import MetricParams
from benchmark.metric.table import METRICS, Metric
from pipeline.lane_graph import LaneGraph

REPO = Path(__file__).resolve().parents[1]
TABLE = Path("benchmark/metric/table.py")


def names_tested(root: Path, names: set[str]) -> list[str]:
    """`file:line` of each comparison with a metric's name (==, !=, in, not in; also against a literal
    tuple, list or set of names) and each subscript or .get by one, in benchmark/, baselines/ and cli.py
    outside the table."""
    files = [p for folder in ("benchmark", "baselines") for p in (root / folder).rglob("*.py")]
    found = []
    for path in [*files, root / "cli.py"]:
        if path.relative_to(root) == TABLE:
            continue

        def is_name(node) -> bool:
            if isinstance(node, ast.Constant):
                return node.value in names
            return isinstance(node, (ast.Tuple, ast.List, ast.Set)) and any(map(is_name, node.elts))

        for node in ast.walk(ast.parse(path.read_text())):
            compared = isinstance(node, ast.Compare) and any(map(is_name, [node.left, *node.comparators]))
            indexed = isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant)
            got = isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "get"
            first = node.args[0] if got and node.args else None
            hit = (compared or (indexed and is_name(node.slice))
                   or (isinstance(first, ast.Constant) and is_name(first)))  # fmt: skip
            if hit:
                found.append(f"{path.relative_to(root)}:{node.lineno}")
    return found


def test_no_module_outside_the_table_tests_a_metric_s_name():
    assert names_tested(REPO, {metric.name for metric in METRICS}) == []


def test_the_check_sees_each_way_of_testing_a_name(tmp_path):
    (tmp_path / "benchmark" / "metric").mkdir(parents=True)
    (tmp_path / "baselines").mkdir()
    (tmp_path / "cli.py").write_text('MODEL = {"cgnet": 1}\nx = MODEL.get("model", "cgnet")\n')
    (tmp_path / TABLE).write_text('if name == "cgnet": pass\n')
    (tmp_path / "benchmark" / "a.py").write_text(
        'if "cgnet" in metrics: pass\nif m != "cgnet": pass\nif m in ("x", "cgnet"): pass\n'
        'r = result["cgnet"]\ns = result.get("cgnet")\nok = result["other"]\n'
    )
    assert names_tested(tmp_path, {"cgnet"}) == [f"benchmark/a.py:{line}" for line in (1, 2, 3, 4, 5)]


# A metric of this test alone: the frames and edges of the predictions, through the table's entry only.
@dataclasses.dataclass(frozen=True)
class EdgesParams:
    """The test metric's parameters: it has no setting."""


def edges_frame(frame, params) -> dict:
    return {"pred_edges": len(frame.pred.src), "gt_edges": len(frame.gt.src)}


def edges_result(frames: list[dict], params) -> dict:
    return {"frames": len(frames), "pred_edges": sum(f["pred_edges"] for f in frames),
            "gt_edges": sum(f["gt_edges"] for f in frames), "params": {}, "version": 1}  # fmt: skip


def edges_console(scores: dict):
    from rich.table import Table

    shown = Table("edges", "pred", "gt")
    shown.add_row("all", str(scores["pred_edges"]), str(scores["gt_edges"]))
    return [(f"edges over {scores['frames']} frames", shown)], ["edges: a metric of the test"]


EDGES = Metric(
    name="edges", help="edge counts", params=EdgesParams, version=1, frame=edges_frame, result=edges_result,
    console=edges_console,
    report_title="Edge counts", report_header=("pred edges", "gt edges"),
    report_row=lambda scores: [str(scores["pred_edges"]), str(scores["gt_edges"])],
)  # fmt: skip


def test_a_metric_added_to_the_table_alone_runs_through_every_command(synth_prepared, tmp_path, monkeypatch):
    from benchmark.graph_table import graphs_from_table, read_graph_table
    from benchmark.report.writer import write_report
    from benchmark.score import score
    from cli import app

    monkeypatch.setattr(table, "METRICS", (*METRICS, EDGES))
    data = synth_prepared["av2"]
    edges = sum(len(g.src) for g in graphs_from_table(read_graph_table(data), data).values())
    out = tmp_path / "edges.json"
    args = ["score", "--pred", str(data), "--gt", str(data), "--metric", "edges,lanegap", "--bootstrap", "0"]
    result = CliRunner().invoke(app, [*args, "--out", str(out)])
    assert result.exit_code == 0, result.output
    written = json.loads(out.read_text())
    frames = written["frames"]
    counted = {"frames": frames, "pred_edges": edges, "gt_edges": edges, "params": {}, "version": 1}
    assert written["edges"] == counted
    assert written["directed"]["topo"]["f1"] == 1.0  # LaneGAP's beside it, at the top level
    assert f"edges over {frames} frames" in result.output and "a metric of the test" in result.output
    score(data / "graphs", data, tmp_path / "runs" / "gt", bootstrap=0)
    chosen = table.parse_metrics("edges", always=True)
    report = write_report([tmp_path / "runs"], tmp_path / "report", draws=0, metrics=chosen)
    text = report.path.read_text()
    assert "### Edge counts" in text and f"| gt | {edges} | {edges} |" in text


def test_every_record_names_its_parameter_dataclass_and_its_int_version():
    for metric in METRICS:
        assert dataclasses.is_dataclass(metric.params) and isinstance(metric.params, type), metric.name
        assert metric.params.__dataclass_params__.frozen, metric.name
        assert type(metric.version) is int and metric.version >= 1, metric.name


# A fork on the ground truth's side, its prediction a straight lane 0.2 m off: every metric scores it.
FORK_GT = LaneGraph(np.array([0.0, 0, -4, 4], np.float32), np.array([-10.0, 0, 10, 10], np.float32),
                    np.array([0, 1, 1], np.int32), np.array([1, 2, 3], np.int32))  # fmt: skip
STRAIGHT = LaneGraph(np.array([0.2, 0.2, 0.2], np.float32), np.array([-10.0, 0, 10], np.float32),
                     np.array([0, 1], np.int32), np.array([1, 2], np.int32))  # fmt: skip


@pytest.mark.parametrize("bev_range", ["30x60", "50x100"])
def test_each_result_records_its_record_s_parameters_and_version(bev_range):
    command = MetricParams(bev_range=bev_range)
    contributions = table.Contributions(METRICS, command)
    contributions.add_frame(Frame(STRAIGHT, FORK_GT))
    result = json.loads(json.dumps(contributions.result()))  # as the result file holds it
    for metric in METRICS:
        scores = metric.scores(result)
        version, params = ("metric_version", "metric_params") if metric.always else ("version", "params")
        assert scores[version] == metric.version, metric.name
        # the metric's parameters: its defaults, with the settings it shares with the command's taken from it
        shared = {f.name for f in dataclasses.fields(metric.params)} & set(command.as_dict())
        expected = metric.params(**{name: getattr(command, name) for name in shared})
        assert scores[params] == json.loads(json.dumps(dataclasses.asdict(expected))), metric.name
        assert scores["frames"] == 1, metric.name


def test_importing_cli_and_its_help_load_no_numpy():
    code = (
        "import sys, cli; loaded = 'numpy' in sys.modules"
        "; cli.app(['score', '--help'], standalone_mode=False); print(loaded, 'numpy' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.strip().endswith("False False"), done.stdout + done.stderr
