"""The published lane-graph metrics that `--metric` chooses among: LaneGAP's (ours, totals.py) and
OpenLane-V2's DET_l / TOP_ll (openlanev2.py), each scored per frame and gathered in frame order."""

from __future__ import annotations

from pipeline.lane_graph import LaneGraph

METRICS = ("lanegap", "openlanev2")
OTHERS = METRICS[1:]


def parse_metrics(text: str, option: str = "--metric") -> tuple[str, ...]:
    """The chosen metrics of a comma-separated list, in METRICS' order; one clear line for a bad name."""
    names = [name.strip() for name in text.split(",") if name.strip()]
    if not names or any(name not in METRICS for name in names):
        raise ValueError(f"{option} {text!r}: expected one or more of {', '.join(METRICS)}, comma-separated")
    return tuple(name for name in METRICS if name in names)


# Each variant's module is imported where it is first used: a score under one metric loads no other.
def variant_frame(name: str, pred: LaneGraph, gt: LaneGraph, bev_range: str) -> dict:
    """What one frame contributes to the variant `name` (picklable: computed in the scoring workers)."""
    from benchmark.metric.openlanev2 import OpenLaneV2Params, openlanev2_frame

    return openlanev2_frame(pred, gt, OpenLaneV2Params(bev_range=bev_range))


def variant_result(name: str, frames: list[dict]) -> dict:
    """The variant's scores over the frames' records, with its parameters and version."""
    from benchmark.metric.openlanev2 import openlanev2_result

    return openlanev2_result(frames)


class VariantScores:
    """The per-frame records of the chosen other metrics, in frame order; picklable, so that the workers
    that sum LaneGAP's counts score these too."""

    def __init__(self, names: tuple[str, ...], bev_range: str):
        self.names = tuple(name for name in names if name in OTHERS)
        self.bev_range = bev_range
        self.records: dict[str, list[dict]] = {name: [] for name in self.names}

    def add_frame(self, pred: LaneGraph, gt: LaneGraph) -> None:
        for name in self.names:
            self.records[name].append(variant_frame(name, pred, gt, self.bev_range))

    def add(self, other: VariantScores) -> None:
        """Another chunk's records, after this one's."""
        for name in self.names:
            self.records[name] += other.records[name]

    def results(self) -> dict[str, dict]:
        return {name: variant_result(name, self.records[name]) for name in self.names}
