"""TOPO and Junction TOPO of a predicted lane graph against the ground truth: one frame's sums in each mode
(frame_counts), and the scores over a set of frames with mIoU (Totals, score_graphs).

docs/METRICS.md is the definition; benchmark/metric implements it step by step, assembled here:
densify (densify.py) -> candidate pairs and matching P (candidates.py, matching.py) -> for each pair:
Reach sets and their matching (reach.py) -> sums (this module); mIoU is iou.py.

The per-pair work (two shortest-path searches and one matching for each of ~3,000 pairs per frame)
is the hot path, so it runs in numba kernels over flat arrays. tests/test_metrics.py keeps a plain
networkx reading of the definition and checks that both agree exactly, pair by pair.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from benchmark.metric.candidates import Candidates, candidate_pairs
from benchmark.metric.densify import Dense, densify
from benchmark.metric.iou import IouCounts, iou_counts
from benchmark.metric.matching import Matching, match
from benchmark.metric.params import MetricParams
from benchmark.metric.reach import pair_counts
from pipeline.lane_graph import LaneGraph


def ratio(num: float, den: float) -> float:
    return num / den if den else 0.0


def prf(pre_sum: float, pre_den: float, rec_sum: float, rec_den: float) -> dict:
    p, r = ratio(pre_sum, pre_den), ratio(rec_sum, rec_den)
    return {"precision": p, "recall": r, "f1": ratio(2 * p * r, p + r)}


class FractionSum:
    """A sum of fractions m / s kept exact, as the total numerator of each denominator s: the sums
    over pairs and frames come out the same whatever their order, and equal the reference's."""

    def __init__(self, numerators: np.ndarray | None = None):
        self.numerators = np.zeros(0, np.int64) if numerators is None else numerators

    @classmethod
    def of(cls, m: np.ndarray, s: np.ndarray) -> FractionSum:
        return cls(np.bincount(s, weights=m).astype(np.int64) if len(s) else None)

    def __add__(self, other: FractionSum) -> FractionSum:
        a, b = self.numerators, other.numerators
        if len(a) < len(b):
            a, b = b, a
        total = a.copy()
        total[: len(b)] += b
        return FractionSum(total)

    def __eq__(self, other) -> bool:
        if not isinstance(other, FractionSum):
            return False
        # trailing zeros say nothing
        return np.array_equal(np.trim_zeros(self.numerators, "b"), np.trim_zeros(other.numerators, "b"))

    def __repr__(self) -> str:
        return f"FractionSum({self.value()})"

    def value(self) -> float:
        s = np.flatnonzero(self.numerators)
        return math.fsum(self.numerators[s] / s)


# The columns of a per-frame count table (TopoCounts.vector of each mode): precision sum and its
# denominator, recall sum and its denominator, then the same four of Junction TOPO.
FRAME_FIELDS = ("pre", "n_pred", "rec", "n_gt", "junction_pre", "n_anchored", "junction_rec", "n_junctions")
FRAME_COLUMNS = tuple(f"{mode}.{name}" for mode in ("directed", "undirected") for name in FRAME_FIELDS)


@dataclass
class TopoCounts:
    """The sums of one mode (directed or undirected) over the frames added so far."""

    pre: FractionSum = field(default_factory=FractionSum)  # sum over pairs of m / |S_p|
    rec: FractionSum = field(default_factory=FractionSum)  # sum over pairs of m / |S_g|
    n_pred: int = 0
    n_gt: int = 0
    junction_pre: FractionSum = field(default_factory=FractionSum)
    junction_rec: FractionSum = field(default_factory=FractionSum)
    n_anchored: int = 0
    n_junctions: int = 0

    def add(self, other: TopoCounts) -> None:
        for name, value in vars(other).items():
            setattr(self, name, getattr(self, name) + value)

    def vector(self) -> list[float]:
        """The sums as numbers, in FRAME_FIELDS order: one frame's row of the bootstrap's count table."""
        return [self.pre.value(), self.n_pred, self.rec.value(), self.n_gt, self.junction_pre.value(),
                self.n_anchored, self.junction_rec.value(), self.n_junctions]  # fmt: skip

    def scores(self) -> dict:
        return {
            "topo": prf(self.pre.value(), self.n_pred, self.rec.value(), self.n_gt),
            "junction_topo": prf(
                self.junction_pre.value(), self.n_anchored, self.junction_rec.value(), self.n_junctions
            ),
        }


def junction_anchors(gt: Dense, cand: Candidates, m: Matching) -> tuple[np.ndarray, np.ndarray]:
    """(junction, anchor) of the anchored junctions: the paired vertex, else the nearest one."""
    junctions = np.flatnonzero(gt.junction)
    anchor = m.partner_b[junctions]
    alone = np.flatnonzero((anchor < 0) & (cand.b_ptr[junctions + 1] > cand.b_ptr[junctions]))
    # each b's pairs are in rank order, (distance, a): the first is the nearest, ties by index
    anchor[alone] = cand.a[cand.b_rank[cand.b_ptr[junctions[alone]]]]
    return junctions[anchor >= 0], anchor[anchor >= 0]


def mode_counts(pred: Dense, gt: Dense, cand: Candidates, m: Matching, params: MetricParams) -> TopoCounts:
    """TOPO and Junction TOPO sums of one frame in one mode."""
    pair_p, pair_g = m.pairs
    j_gt, j_pred = junction_anchors(gt, cand, m)
    # the junctions' pairs go in the same kernel call; a paired junction's pair is then counted twice
    all_p, all_g = np.concatenate([pair_p, j_pred]), np.concatenate([pair_g, j_gt])
    both = pair_counts(pred, gt, all_p, all_g, cand, m, params)
    topo, junc = slice(0, len(pair_p)), slice(len(pair_p), None)
    return TopoCounts(
        pre=FractionSum.of(both.matched[topo], both.size_pred[topo]),
        rec=FractionSum.of(both.matched[topo], both.size_gt[topo]),
        n_pred=pred.n,
        n_gt=gt.n,
        junction_pre=FractionSum.of(both.matched[junc], both.size_pred[junc]),
        junction_rec=FractionSum.of(both.matched[junc], both.size_gt[junc]),
        n_anchored=len(j_gt),
        n_junctions=int(np.count_nonzero(gt.junction)),
    )


def frame_counts(pred: LaneGraph, gt: LaneGraph, params: MetricParams) -> dict[str, TopoCounts]:
    """{"directed": ..., "undirected": ...} sums of one frame."""
    dense_pred, dense_gt = densify(pred, params.step), densify(gt, params.step)
    out, last = {}, None
    for mode in ("directed", "undirected"):
        p, g = dense_pred[mode], dense_gt[mode]
        # both modes have the same vertices unless a graph has both u -> v and v -> u
        if last is None or not (np.array_equal(last[0], p.xy) and np.array_equal(last[1], g.xy)):
            cand = candidate_pairs(p.xy, g.xy, params.match_radius)
            last = (p.xy, g.xy, cand, match(cand, p.n, g.n, params.matching))
        out[mode] = mode_counts(p, g, last[2], last[3], params)
    return out


# ---------------------------------------------------------------------------------------------------
# A set of frames


@dataclass
class Totals:
    """Everything summed over the frames scored so far; result() is the JSON body of `cli score`."""

    params: MetricParams = field(default_factory=MetricParams)
    frames: int = 0
    directed: TopoCounts = field(default_factory=TopoCounts)
    undirected: TopoCounts = field(default_factory=TopoCounts)
    iou: IouCounts = field(default_factory=IouCounts)
    rows: list[list[float]] = field(default_factory=list)  # per frame, in order: FRAME_COLUMNS

    def add_frame(self, pred: LaneGraph, gt: LaneGraph) -> None:
        counts = frame_counts(pred, gt, self.params)
        self.directed.add(counts["directed"])
        self.undirected.add(counts["undirected"])
        self.iou.add(iou_counts(pred, gt, self.params))
        self.rows.append(counts["directed"].vector() + counts["undirected"].vector())
        self.frames += 1

    def add(self, other: Totals) -> None:
        self.frames += other.frames
        self.directed.add(other.directed)
        self.undirected.add(other.undirected)
        self.iou.add(other.iou)
        self.rows += other.rows

    def frame_table(self) -> np.ndarray:
        """(frames, len(FRAME_COLUMNS)) float64: each frame's sums, in the order the frames were added."""
        return np.array(self.rows, np.float64).reshape(len(self.rows), len(FRAME_COLUMNS))

    def result(self) -> dict:
        return {
            "frames": self.frames,
            "directed": self.directed.scores(),
            "undirected": self.undirected.scores(),
            "miou": ratio(self.iou.intersection, self.iou.union),
            "metric_params": self.params.as_dict(),
        }


def score_graphs(pairs, params: MetricParams | None = None) -> dict:
    """The scores of (pred, gt) LaneGraph pairs, one per frame, over the set."""
    totals = Totals(params or MetricParams())
    for pred, gt in pairs:
        totals.add_frame(pred, gt)
    return totals.result()
