"""The other published metrics in report.md (`cli report --metric`): one table per variant of each block,
the same runs on the same frames as its main table, scored here from each run's predictions.parquet."""

from __future__ import annotations

from benchmark.metric.params import MetricParams
from benchmark.report.measured_tables import block_graphs, markdown_table
from benchmark.report.runs import Block
from benchmark.score import score_frames
from pipeline.lane_graph import LaneGraph

TITLES = {"cgnet": "CGNet's metric (its evaluator: GEO, TOPO, JTOPO)",
          "openlanev2": "OpenLane-V2's DET_l and TOP_ll"}  # fmt: skip
NOTE = ("Computed here, not read from metrics.json: each run's predictions.parquet scored under the metric "
        "as its own codebase defines it (docs/METRICS.md), on the frames of the main table. The paper's "
        "published rows stand beside LaneGAP's metric only, the one they were measured with.")  # fmt: skip


def header(metric: str) -> list[str]:
    if metric == "cgnet":
        return ["run", *(f"{name} {part}" for name in ("GEO", "TOPO", "JTOPO") for part in ("P", "R", "F1"))]
    return ["run", "DET_l", "TOP_ll"]


def row(metric: str, result: dict) -> list[str]:
    """A run's cells in %, as the main table writes its scores."""
    if metric == "cgnet":  # None: no frame had a number (CGNet's NaN skipped)
        return ["–" if result[name][part] is None else f"{100 * result[name][part]:.1f}"
                for name in ("geo", "topo", "jtopo") for part in ("precision", "recall", "f1")]  # fmt: skip
    return [f"{100 * result['det_l']:.1f}", f"{100 * result['top_ll']:.1f}"]


def variant_sections(block: Block, metrics: tuple[str, ...], workers: int) -> list[str]:
    """One table per metric of `metrics` other than LaneGAP's, with its notes (none without predictions)."""
    others = [metric for metric in metrics if metric != "lanegap"]
    if not others or block.data is None:
        return []
    gt, predictions, _ = block_graphs(block)
    params = MetricParams(**block.metric_params)
    md = []
    for metric in others:
        rows, notes = [], set()
        for run in block.scored:
            if run.name not in predictions:
                continue
            ours = predictions[run.name]
            frames = sorted(ours) if run.external is not None else sorted(gt)  # as `cli score` scores them
            pairs = [(ours.get(f, LaneGraph.empty()), gt[f]) for f in frames]
            result = score_frames(pairs, params, workers, (metric,))[0][metric]
            rows.append([run.name, *row(metric, result)])
            notes |= {result[key] for key in ("note", "range") if key in result}
        if rows:
            md += [f"### {TITLES[metric]}", "", markdown_table(header(metric), rows), "", NOTE, ""]
            md += [f"- {note}" for note in sorted(notes)] + ([""] if notes else [])
    return md
