"""LaneGAP's metric (ours: TOPO, Junction TOPO, mIoU; totals.py) as its entry in the table of metrics
(benchmark/metric/table.py) reads it: one frame's sums, their exact addition, the scores and each frame's
counts for the bootstrap. Its console table and report rows are each command's main table (benchmark/tables.py
score_table and eval_table, benchmark/report/measured_tables.py main_table). The metric's modules are
imported at the first call: the table's import stays light (`cli --help` reads it)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from benchmark.metric.frame import Frame

if TYPE_CHECKING:
    import numpy as np

    from benchmark.metric.params import MetricParams
    from benchmark.metric.totals import Totals


def frame_of(frame: Frame, params: MetricParams) -> Totals:
    """One frame's sums, a Totals of that frame alone."""
    from benchmark.metric.totals import Totals

    totals = Totals(params)
    totals.add_frame(frame.pred, frame.gt)
    return totals


def add(total: Totals, more: Totals) -> Totals:
    """`more` (the next frames' sums) added into `total`: exact, so any grouping gives the same digits."""
    total.add(more)
    return total


def result_of(sums: list[Totals], params: MetricParams) -> dict:
    """The scores of the frames' sums (one Totals, or none for no frame), with METRIC_VERSION."""
    from benchmark.metric.params import METRIC_VERSION
    from benchmark.metric.totals import Totals

    totals = sums[0] if sums else Totals(params)
    return {**totals.result(), "metric_version": METRIC_VERSION}


def counts_of(sums: list[Totals]) -> np.ndarray:
    """Each frame's counts in frame order (Totals.frame_table): the bootstrap's and frame_counts.parquet's."""
    import numpy as np

    from benchmark.metric.totals import FRAME_COLUMNS

    return sums[0].frame_table() if sums else np.zeros((0, len(FRAME_COLUMNS)))
