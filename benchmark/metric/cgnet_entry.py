"""CGNet's metric as its entry in the table of metrics (benchmark/metric/table.py) reads it: the evaluator of
cgnet.py on one frame and over the frames under a command's MetricParams (with a note when the data's range
reaches beyond the evaluator's box), its console table and its report row. cgnet.py (the evaluator's port)
is imported at the first call: the table's import stays light (`cli --help` reads it)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from benchmark.metric.frame import Frame
from benchmark.metric.params import CGNetParams

if TYPE_CHECKING:
    from rich.table import Table

    from benchmark.metric.params import MetricParams

NAMES = (("GEO", "geo"), ("TOPO", "topo"), ("JTOPO", "jtopo"))  # (shown name, result key)
STATS = ("precision", "recall", "f1")


def frame_of(frame: Frame, params: MetricParams) -> dict:
    """cgnet_frame of one frame, under the evaluator's own constants (the command's thresholds are ours)."""
    from benchmark.metric.cgnet import cgnet_frame

    return cgnet_frame(frame.pred, frame.gt, CGNetParams())


def result_of(frames: list[dict], params: MetricParams) -> dict:
    """cgnet_result of the frames, with a note when the range reaches beyond the evaluator's box."""
    from benchmark.metric.cgnet import cgnet_result

    result = cgnet_result(frames)
    if wider_than_cgnet(params.bev_range):
        result["note"] = (
            f"the data's range is {params.bev_range}: CGNet's evaluator keeps x in [-15, 15), "
            "y in [-30, 30) m, and drops the lanes beyond, as CGNet does"
        )
    return result


def wider_than_cgnet(bev_range: str) -> bool:
    """Whether the range reaches beyond the fixed box of CGNet's evaluator (30 x 60 m)."""
    from pipeline.geometry import Range

    r = Range.parse(bev_range)
    return r.x_min < -15 or r.x_max > 15 or r.y_min < -30 or r.y_max > 30


def console_tables(result: dict) -> tuple[list[tuple[str, Table]], list[str]]:
    """GEO, TOPO and JTOPO precision, recall and F1 as (heading, table), with the note."""
    from rich.table import Table

    def cell(value: float | None) -> str:  # None: no frame had a number (CGNet's NaN skipped)
        return "-" if value is None else f"{value:.3f}"

    table = Table("CGNet metric", "precision", "recall", "F1")
    for name, key in NAMES:
        table.add_row(name, *(cell(result[key][stat]) for stat in STATS))
    heading = f"CGNet's evaluator: per-frame scores averaged over {result['frames']} frames"
    return [(heading, table)], [result["note"]] if "note" in result else []


REPORT_HEADER = tuple(f"{name} {part}" for name, _ in NAMES for part in ("P", "R", "F1"))


def report_row(result: dict) -> list[str]:
    """A run's cells in %, as report.md's main table writes its scores."""
    return ["–" if result[key][stat] is None else f"{100 * result[key][stat]:.1f}"
            for _, key in NAMES for stat in STATS]  # fmt: skip
