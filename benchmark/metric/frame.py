"""One frame as a metric's per-frame function takes it (benchmark/metric/table.py): the ground truth and the
prediction, with what the prediction's format says beyond its graph."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the table of metrics imports this: `cli --help` reads it, without numpy
    import numpy as np

    from pipeline.lane_graph import LaneGraph
    from pipeline.records import AnnotatedLanes


@dataclass(frozen=True)
class Frame:
    """One frame's ground truth and prediction. A metric takes what it needs: LaneGAP's and CGNet's the two
    graphs, OpenLane-V2's also the scores of the predicted lanes. A dataset whose lanes carry heights and
    link probabilities adds them here as fields of their own, for the metric that reads them."""

    pred: LaneGraph
    gt: LaneGraph
    pred_scores: np.ndarray | None = None  # one per edge of `pred`, its lane's confidence; None: no score
    # OpenLane-V2 data: the frame's annotated lanes, and a submission's predicted lanes as the file holds them
    gt_lanes: AnnotatedLanes | None = None
    pred_lanes: AnnotatedLanes | None = None
    # the frame's ground plane (ground_z, a, b: z = ground_z + a x + b y in the BEV frame), for the heights
    # of a graph prediction's lanes; None: level ground at z = 0
    ground: tuple[float, float, float] | None = None
