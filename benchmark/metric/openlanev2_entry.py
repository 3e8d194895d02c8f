"""OpenLane-V2's DET_l and TOP_ll (openlanev2.py) as its entry in the table of metrics
(benchmark/metric/table.py) reads it: one frame's contribution at the command's range with the prediction's
lane scores (on OpenLane-V2 data, its annotated lanes against the submission's lanes or the graph's), the
scores over the frames, its console table and its report row. openlanev2.py is imported at the first call:
the table's import stays light (`cli --help` reads it)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from benchmark.metric.frame import Frame
from benchmark.metric.params import OpenLaneV2Params

if TYPE_CHECKING:
    from rich.table import Table

    from benchmark.metric.params import MetricParams

REPORT_HEADER = ("DET_l", "TOP_ll")


def frame_of(frame: Frame, params: MetricParams) -> dict:
    """One frame's contribution at the command's range. With OpenLane-V2's annotated lanes (frame.gt_lanes),
    the lane path: them against the submission's lanes as they are, or against the predicted graph's lanes
    (annotated_of_graph, heights from the frame's ground plane); else openlanev2_frame of the two graphs,
    with the prediction's lane scores."""
    from benchmark.metric import openlanev2

    ol_params = OpenLaneV2Params(bev_range=params.bev_range)
    if frame.gt_lanes is None:
        return openlanev2.openlanev2_frame(frame.pred, frame.gt, ol_params, pred_scores=frame.pred_scores)
    if frame.pred_lanes is not None:
        return openlanev2.openlanev2_lanes_frame(frame.pred_lanes, frame.gt_lanes, ol_params)
    pred = openlanev2.annotated_of_graph(frame.pred, frame.ground, frame.pred_scores, ol_params.points)
    scored = frame.pred_scores is not None
    return openlanev2.openlanev2_lanes_frame(pred, frame.gt_lanes, ol_params, openlanev2.FROM_GRAPH, scored)


def result_of(frames: list[dict], params: MetricParams) -> dict:
    """openlanev2_result of the frames (their records hold the parameters they were scored with)."""
    from benchmark.metric.openlanev2 import openlanev2_result

    return openlanev2_result(frames)


def console_tables(result: dict) -> tuple[list[tuple[str, Table]], list[str]]:
    """DET_l and TOP_ll, overall and at each threshold, as (heading, table), with the notes."""
    from rich.table import Table

    def cell(value: float) -> str:
        return f"{value:.3f}"

    table = Table("OpenLane-V2", "value", *(f"at {t} m" for t in result["det_l_by_threshold"]))
    table.add_row("DET_l", cell(result["det_l"]), *map(cell, result["det_l_by_threshold"].values()))
    table.add_row("TOP_ll", cell(result["top_ll"]), *map(cell, result["top_ll_by_threshold"].values()))
    heading = f"OpenLane-V2's DET_l and TOP_ll over {result['frames']} frames, {result['range']}"
    notes = [f"OpenLane-V2 confidences: {result['confidences']}"]
    if "follows" in result:  # the lane path, on OpenLane-V2's own annotated lanes
        notes += [
            f"OpenLane-V2 predictions: {result['predictions']}",
            f"OpenLane-V2 lane path follows {result['follows']}",
            result["not_computed"],
        ]
    return [(heading, table)], notes + ([result["note"]] if "note" in result else [])


def report_row(result: dict) -> list[str]:
    """A run's cells in %, as report.md's main table writes its scores."""
    return [f"{100 * result['det_l']:.1f}", f"{100 * result['top_ll']:.1f}"]
