"""The published lane-graph metrics that `--metric` chooses among: LaneGAP's (ours, totals.py), CGNet's
(cgnet.py) and OpenLane-V2's DET_l / TOP_ll (openlanev2.py), each scored per frame, gathered in order."""

from __future__ import annotations

from pipeline.lane_graph import LaneGraph

METRICS = ("lanegap", "cgnet", "openlanev2")
OTHERS = METRICS[1:]


def parse_metrics(text: str, option: str = "--metric") -> tuple[str, ...]:
    """The chosen metrics of a comma-separated list, in METRICS' order; one clear line for a bad name."""
    names = [name.strip() for name in text.split(",") if name.strip()]
    if not names or any(name not in METRICS for name in names):
        raise ValueError(f"{option} {text!r}: expected one or more of {', '.join(METRICS)}, comma-separated")
    return tuple(name for name in METRICS if name in names)


# Each variant's module is imported where it is first used: a score under one metric loads no other.
def variant_frame(name: str, pred: LaneGraph, gt: LaneGraph, bev_range: str, scores=None) -> dict:
    """What one frame contributes to the variant `name` (picklable: computed in the scoring workers).
    `scores`: one per edge of `pred`, its lanes' confidences for OpenLane-V2 (None: 1.0); CGNet's has none."""
    if name == "cgnet":
        from benchmark.metric.cgnet import CGNetParams, cgnet_frame

        return cgnet_frame(pred, gt, CGNetParams())
    from benchmark.metric.openlanev2 import OpenLaneV2Params, openlanev2_frame

    return openlanev2_frame(pred, gt, OpenLaneV2Params(bev_range=bev_range), pred_scores=scores)


def variant_result(name: str, frames: list[dict]) -> dict:
    """The variant's scores over the frames' records, with its parameters and version."""
    if name == "cgnet":
        from benchmark.metric.cgnet import cgnet_result

        return cgnet_result(frames)
    from benchmark.metric.openlanev2 import openlanev2_result

    return openlanev2_result(frames)


class VariantScores:
    """The per-frame records of the chosen other metrics, in frame order; picklable, so that the workers
    that sum LaneGAP's counts score these too."""

    def __init__(self, names: tuple[str, ...], bev_range: str):
        self.names = tuple(name for name in names if name in OTHERS)
        self.bev_range = bev_range
        self.records: dict[str, list[dict]] = {name: [] for name in self.names}

    def add_frame(self, pred: LaneGraph, gt: LaneGraph, scores=None) -> None:
        """One frame; `scores`: one per edge of `pred`, or None (variant_frame)."""
        for name in self.names:
            self.records[name].append(variant_frame(name, pred, gt, self.bev_range, scores))

    def add(self, other: VariantScores) -> None:
        """Another chunk's records, after this one's."""
        for name in self.names:
            self.records[name] += other.records[name]

    def results(self) -> dict[str, dict]:
        results = {name: variant_result(name, self.records[name]) for name in self.names}
        if "cgnet" in results and wider_than_cgnet(self.bev_range):
            results["cgnet"]["note"] = (
                f"the data's range is {self.bev_range}: CGNet's evaluator keeps x in [-15, 15), "
                "y in [-30, 30) m, and drops the lanes beyond, as CGNet does"
            )
        return results


def wider_than_cgnet(bev_range: str) -> bool:
    """Whether the range reaches beyond the fixed box of CGNet's evaluator (30 x 60 m)."""
    from pipeline.geometry import Range

    r = Range.parse(bev_range)
    return r.x_min < -15 or r.x_max > 15 or r.y_min < -30 or r.y_max > 30
