"""The table of metrics (benchmark/metric/table.py) is the one place that knows a metric by name: no other
module compares a metric's name or reads a result by it, and a metric added to the table alone is chosen by
--metric, scored, written under its name, printed and given its report table."""

from __future__ import annotations

import ast
import json
from pathlib import Path

from typer.testing import CliRunner

from benchmark.metric import table
from benchmark.metric.table import METRICS, Metric

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
def edges_frame(frame, params) -> dict:
    return {"pred_edges": len(frame.pred.src), "gt_edges": len(frame.gt.src)}


def edges_result(frames: list[dict], params) -> dict:
    return {"frames": len(frames), "pred_edges": sum(f["pred_edges"] for f in frames),
            "gt_edges": sum(f["gt_edges"] for f in frames), "version": 1}  # fmt: skip


def edges_console(scores: dict):
    from rich.table import Table

    shown = Table("edges", "pred", "gt")
    shown.add_row("all", str(scores["pred_edges"]), str(scores["gt_edges"]))
    return [(f"edges over {scores['frames']} frames", shown)], ["edges: a metric of the test"]


EDGES = Metric(
    name="edges", help="edge counts", frame=edges_frame, result=edges_result, console=edges_console,
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
    assert written["edges"] == {"frames": frames, "pred_edges": edges, "gt_edges": edges, "version": 1}
    assert written["directed"]["topo"]["f1"] == 1.0  # LaneGAP's beside it, at the top level
    assert f"edges over {frames} frames" in result.output and "a metric of the test" in result.output
    score(data / "graphs", data, tmp_path / "runs" / "gt", bootstrap=0)
    chosen = table.parse_metrics("edges", always=True)
    report = write_report([tmp_path / "runs"], tmp_path / "report", draws=0, metrics=chosen)
    text = report.path.read_text()
    assert "### Edge counts" in text and f"| gt | {edges} | {edges} |" in text
