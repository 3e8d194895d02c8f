"""The metric's parameters: every threshold (MetricParams), the float tolerance EPS, and METRIC_VERSION,
the version of the metric recorded in every result file."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from pipeline.geometry import Range

# Float noise below this many metres never decides a threshold: "d < 0.45" is read d < 0.45 - EPS, so
# that a prediction shifted by exactly 0.45 m or a reach of exactly 50 steps of 0.15 m has one answer.
EPS = 1e-9

# The metric's version, recorded in every result JSON (`cli score`, `cli eval`, `cli roundtrip`): bump it
# whenever a change can move any digit of a score, so that published numbers stay comparable
# (tests/test_faults.py holds golden values that fail until it is bumped).
METRIC_VERSION = 1


@dataclass(frozen=True)
class MetricParams:
    """Every threshold of the metric, recorded in each result file."""

    step: float = 0.15  # densification: no edge longer than this
    match_radius: float = 0.45  # vertices closer than this may be paired
    reach_radius: float = 7.5  # Reach(v): path distance from v below this
    matching: str = "greedy"  # "greedy" (LaneExtraction lineage) or "optimal" (maximum cardinality)
    bev_range: str = "30x60"  # mIoU grid: the perception range, WIDTHxLENGTH metres
    miou_resolution: float = 0.15  # mIoU grid cell size
    miou_line_width: float = 0.75  # both graphs are drawn this wide for mIoU

    def __post_init__(self) -> None:
        if self.matching not in ("greedy", "optimal"):
            raise ValueError(f"matching must be 'greedy' or 'optimal', not {self.matching!r}")
        for name in ("step", "match_radius", "reach_radius", "miou_resolution", "miou_line_width"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, not {getattr(self, name)}")
        Range.parse(self.bev_range)

    def as_dict(self) -> dict:
        return asdict(self)
