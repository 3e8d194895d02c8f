"""Every metric's parameters and version, as its record in the table of metrics (table.py) names them and
its result records them: LaneGAP's (ours: every threshold, MetricParams, the float tolerance EPS, and
METRIC_VERSION, the version recorded in every result file), CGNet's evaluator's (CGNetParams,
CGNET_VERSION; cgnet.py) and OpenLane-V2's (OpenLaneV2Params, OPENLANEV2_VERSION; openlanev2.py). Light:
`cli --help` reads the table, and this module imports no numpy."""

from __future__ import annotations

from dataclasses import asdict, dataclass

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
        from pipeline.geometry import Range  # numpy: loaded when a MetricParams is made, not at import

        Range.parse(self.bev_range)

    def as_dict(self) -> dict:
        return asdict(self)


# CGNet's evaluator's version, recorded in its result JSON: bump it whenever a change can move any digit.
CGNET_VERSION = 1


@dataclass(frozen=True)
class CGNetParams:
    """The evaluator's constants, in its units (decimetres) as CGNet's nuScenes dataset class sets them."""

    radius: float = 5.0  # GraphEvaluator(radius=5): pairs closer than this (squared distance < radius ** 2)
    interp_dist: float = 2.5  # edges cut into parts no longer than this
    prop_dist: float = 80.0  # the walk expands nodes whose depth is below this
    scale: float = 10.0  # key units per metre: positions are keyed in whole decimetres
    half_width: float = 150.0  # interpolated nodes kept in -half_width <= x < half_width
    half_length: float = 300.0  # and -half_length <= y < half_length
    topo_every: int = 10  # TOPO scores every 10th matched pair
    box: float = 1.0  # each node's R-tree entry is a square of this half-side (sets only the tie order)

    def __post_init__(self) -> None:
        for name in ("radius", "interp_dist", "prop_dist", "scale", "half_width", "half_length", "box"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, not {getattr(self, name)}")
        if self.topo_every < 1:
            raise ValueError(f"topo_every must be at least 1, not {self.topo_every}")

    def to_dict(self) -> dict:
        return asdict(self)


# OpenLane-V2's version, recorded in every result: bump it whenever a change can move any digit of DET_l or
# TOP_ll. 2: the graph path's DET_l and TOP_ll in the reference's float32 under its numpy 1.23, as the lane
# path's (a recall of exactly 0.7 or 0.9 now reaches its step: 8 / 11, not 7 / 11, for 7 of 10 lanes).
OPENLANEV2_VERSION = 2


@dataclass(frozen=True)
class OpenLaneV2Params:
    """Every constant of DET_l and TOP_ll, recorded in each result."""

    thresholds: tuple[float, ...] = (1.0, 2.0, 3.0)  # Fréchet distance thresholds, metres (DET_l averages)
    points: int = 11  # points per lane, even by arc length
    relax_rate: float = 5e-3  # the distance's relaxation: max(relax_floor, 1 - relax_rate * ego distance)
    relax_floor: float = 0.5
    ties: str = "threshold"  # equal confidences: "threshold" (one point of the curve) or "order" (lane order)
    bev_range: str = "30x60"  # the perception range the graphs were cut to (recorded, not applied)

    def __post_init__(self) -> None:
        if not self.thresholds or not all(t > 0 for t in self.thresholds):
            raise ValueError(f"thresholds must be positive, not {self.thresholds}")
        if self.points < 2:
            raise ValueError(f"points must be at least 2, not {self.points}")
        if self.ties not in ("threshold", "order"):
            raise ValueError(f"ties must be 'threshold' or 'order', not {self.ties!r}")
        from pipeline.geometry import Range  # numpy: loaded when they are made, not at import

        Range.parse(self.bev_range)

    def to_dict(self) -> dict:
        out = asdict(self)
        out["thresholds"] = list(self.thresholds)
        return out

    @classmethod
    def from_dict(cls, values: dict) -> OpenLaneV2Params:
        return cls(**{**values, "thresholds": tuple(values["thresholds"])})
