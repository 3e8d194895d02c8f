"""The other published metrics in report.md (`cli report --metric`): one table per variant of each block,
the same runs on the same frames as its main table, scored here from each run's predictions.parquet."""

from __future__ import annotations

from benchmark.metric.params import MetricParams
from benchmark.metric.table import Metric
from benchmark.report.measured_tables import block_graphs, markdown_table
from benchmark.report.runs import Block
from benchmark.score import score_frames
from pipeline.lane_graph import LaneGraph

NOTE = ("Computed here, not read from metrics.json: each run's predictions.parquet scored under the metric "
        "as its own codebase defines it (docs/METRICS.md), on the frames of the main table. The paper's "
        "published rows stand beside LaneGAP's metric only, the one they were measured with.")  # fmt: skip


def variant_sections(block: Block, metrics: tuple[Metric, ...], workers: int) -> list[str]:
    """One table per metric of `metrics` that has a report row (LaneGAP's is the main table), with its notes
    (none without predictions)."""
    others = [metric for metric in metrics if metric.report_row is not None]
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
            result = metric.scores(score_frames(pairs, params, workers, (metric,))[0])
            rows.append([run.name, *metric.report_row(result)])
            notes |= {result[key] for key in ("note", "range") if key in result}
        if rows:
            header = ["run", *metric.report_header]
            md += [f"### {metric.report_title}", "", markdown_table(header, rows), "", NOTE, ""]
            md += [f"- {note}" for note in sorted(notes)] + ([""] if notes else [])
    return md
