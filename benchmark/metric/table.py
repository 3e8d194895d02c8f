"""The table of metrics: every lane-graph metric that `--metric` chooses among, one `Metric` record each, in
METRICS below, in the order they are computed, written and shown. `cli score`, `cli eval`, `cli report`, the
scoring workers (benchmark/score.py) and the console and report tables read a metric from its record alone;
no other module tests a metric's name (tests/test_metric_table.py holds them to it).

Adding a metric is its parameters, one module and one entry: its parameters (a frozen dataclass) and
their version go into params.py, which imports no numpy; the module holds its per-frame function (one
`Frame` in, a picklable contribution out) and its result function (the contributions in frame order in, a
JSON-able dict out, recording its parameters and version), its console table and its report row, as
openlanev2_entry.py does (its heavy code, imported at the first call, in openlanev2.py); the entry names
them all, the parameter type and the version included, in METRICS (docs/ARCHITECTURE.md).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from benchmark.metric import cgnet_entry, lanegap_entry, openlanev2_entry
from benchmark.metric.frame import Frame
from benchmark.metric.params import (
    CGNET_VERSION,
    METRIC_VERSION,
    OPENLANEV2_VERSION,
    CGNetParams,
    MetricParams,
    OpenLaneV2Params,
)

if TYPE_CHECKING:  # `cli --help` reads this table: its import loads neither numpy nor a metric's heavy module
    import numpy as np


@dataclass(frozen=True)
class Metric:
    """One metric: what `--metric` calls it, how one frame and then all frames are scored, and how it is
    shown. `always`: computed by every command and shown in each command's main table (score_table,
    eval_table, report.md's main table), its scores at the top level of a result, with per-frame counts
    for the bootstrap, as LaneGAP's own metric is; every other metric is written under its name and
    shown in a table of its own."""

    name: str  # the --metric word, and the key of its scores in a result (unless always)
    help: str  # what --metric's help says of it
    params: type  # its parameters, a frozen dataclass recorded in its result (made from the command's)
    version: int  # recorded in its result: bumped whenever a change can move a digit of its scores
    frame: Callable[[Frame, MetricParams], Any]  # one frame's contribution, picklable (in workers)
    result: Callable[[list, MetricParams], dict]  # the scores of the contributions, in frame order
    add: Callable[[Any, Any], Any] | None = None  # contributions that sum exactly, summed as they come
    counts: Callable[[list], np.ndarray] | None = None  # each frame's counts: the bootstrap's, in frame order
    console: Callable[[dict], tuple[list, list[str]]] | None = None  # its ((heading, rich table)s, notes)
    report_title: str = ""  # report.md's heading of its table
    report_header: tuple[str, ...] = ()  # its columns there, after the run's name
    report_row: Callable[[dict], list[str]] | None = None  # a run's cells there
    always: bool = False

    def scores(self, result: dict) -> dict:
        """Its scores in a result (`cli score`'s JSON, metrics.json)."""
        return result if self.always else result[self.name]


LANEGAP = Metric(
    name="lanegap", help="TOPO and Junction TOPO, ours", params=MetricParams, version=METRIC_VERSION,
    frame=lanegap_entry.frame_of, result=lanegap_entry.result_of, add=lanegap_entry.add,
    counts=lanegap_entry.counts_of, always=True,
)  # fmt: skip

METRICS: tuple[Metric, ...] = (
    LANEGAP,
    Metric(
        name="cgnet", help="CGNet's evaluator", params=CGNetParams, version=CGNET_VERSION,
        frame=cgnet_entry.frame_of, result=cgnet_entry.result_of, console=cgnet_entry.console_tables,
        report_title="CGNet's metric (its evaluator: GEO, TOPO, JTOPO)",
        report_header=cgnet_entry.REPORT_HEADER, report_row=cgnet_entry.report_row,
    ),
    Metric(
        name="openlanev2", help="DET_l, TOP_ll", params=OpenLaneV2Params, version=OPENLANEV2_VERSION,
        frame=openlanev2_entry.frame_of, result=openlanev2_entry.result_of,
        console=openlanev2_entry.console_tables, report_title="OpenLane-V2's DET_l and TOP_ll",
        report_header=openlanev2_entry.REPORT_HEADER, report_row=openlanev2_entry.report_row,
    ),
)  # fmt: skip

ALWAYS = tuple(metric for metric in METRICS if metric.always)
METRIC_HELP = (", ".join(f"{metric.name} ({metric.help})" for metric in METRICS)
               + ": comma-separated, each under its name in the result (docs/METRICS.md)")  # fmt: skip


def parse_metrics(text: str, option: str = "--metric", always: bool = False) -> tuple[Metric, ...]:
    """The chosen metrics of a comma-separated list, in METRICS' order; one clear line for a bad name.
    `always`: the always-computed ones too, as if named first (cli eval, cli report)."""
    if always:
        text = ",".join([*(metric.name for metric in ALWAYS), text])
    names = [name.strip() for name in text.split(",") if name.strip()]
    known = [metric.name for metric in METRICS]
    if not names or any(name not in known for name in names):
        raise ValueError(f"{option} {text!r}: expected one or more of {', '.join(known)}, comma-separated")
    return tuple(metric for metric in METRICS if metric.name in names)


class Contributions:
    """Each chosen metric's per-frame contributions in frame order (summed as they come where its record
    says they add up); picklable, so that the workers score every chosen metric in one pass."""

    def __init__(self, metrics: tuple[Metric, ...], metric_params: MetricParams):
        self.metrics = tuple(metric for metric in METRICS if metric in metrics)  # the table's order
        self.params = metric_params
        self.parts: list[list] = [[] for _ in self.metrics]

    def _put(self, metric: Metric, parts: list, contribution) -> None:
        if metric.add is not None and parts:
            parts[0] = metric.add(parts[0], contribution)
        else:
            parts.append(contribution)

    def add_frame(self, frame: Frame) -> None:
        for metric, parts in zip(self.metrics, self.parts):
            self._put(metric, parts, metric.frame(frame, self.params))

    def add(self, other: Contributions) -> None:
        """Another chunk's contributions, after this one's."""
        for metric, parts, more in zip(self.metrics, self.parts, other.parts):
            for contribution in more:
                self._put(metric, parts, contribution)

    def result(self) -> dict:
        """The always-computed metrics' scores at the top level, each other one's under its name."""
        out: dict = {}
        for metric, parts in zip(self.metrics, self.parts):
            scores = metric.result(parts, self.params)
            if metric.always:
                out.update(scores)
            else:
                out[metric.name] = scores
        return out

    def frame_counts(self) -> np.ndarray | None:
        """Each frame's counts for the bootstrap, from the first chosen metric that has them (None: none)."""
        return next((m.counts(p) for m, p in zip(self.metrics, self.parts) if m.counts is not None), None)


def console_tables(metrics: tuple[Metric, ...], result: dict) -> tuple[list, list[str]]:
    """The (heading, rich table) pairs and notes of each chosen metric that has a console table of its own;
    the always-computed one is each command's main table."""
    tables, notes = [], []
    for metric in metrics:
        if metric.console is not None:
            shown, said = metric.console(metric.scores(result))
            tables, notes = tables + shown, notes + said
    return tables, notes
