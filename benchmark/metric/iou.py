"""Step 7 of the metric (docs/METRICS.md), mIoU: each graph drawn on the BEV grid, params.miou_line_width
wide (draw), and the cells of the two drawings' intersection and union (IouCounts)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from benchmark.metric.params import EPS, MetricParams
from pipeline.geometry import Range
from pipeline.kernels import kernel
from pipeline.lane_graph import LaneGraph


@kernel
def _draw(xy, src, dst, x_min, y_max, res, rows, cols, half_width):
    """Cells whose centre lies within half_width of a segment src -> dst (src == dst: of a point)."""
    mask = np.zeros((rows, cols), np.bool_)
    for e in range(len(src)):
        ax, ay, bx, by = xy[src[e], 0], xy[src[e], 1], xy[dst[e], 0], xy[dst[e], 1]
        dx, dy = bx - ax, by - ay
        ll = dx * dx + dy * dy
        # only the cells of the segment's bounding box grown by the half width can be in
        c0 = max(0, int(math.floor((min(ax, bx) - half_width - x_min) / res)))
        c1 = min(cols - 1, int(math.floor((max(ax, bx) + half_width - x_min) / res)))
        r0 = max(0, int(math.floor((y_max - max(ay, by) - half_width) / res)))
        r1 = min(rows - 1, int(math.floor((y_max - min(ay, by) + half_width) / res)))
        for r in range(r0, r1 + 1):
            py = y_max - (r + 0.5) * res
            for c in range(c0, c1 + 1):
                px = x_min + (c + 0.5) * res
                t = 0.0 if ll == 0.0 else min(1.0, max(0.0, ((px - ax) * dx + (py - ay) * dy) / ll))
                qx, qy = ax + t * dx - px, ay + t * dy - py
                if qx * qx + qy * qy <= half_width * half_width:
                    mask[r, c] = True
    return mask


def draw(graph: LaneGraph, params: MetricParams) -> np.ndarray:
    """The graph on the BEV grid of docs/guide/prepare.md, params.miou_line_width wide (cells by centre)."""
    crop = Range.parse(params.bev_range)
    res = params.miou_resolution
    rows, cols = round((crop.y_max - crop.y_min) / res), round((crop.x_max - crop.x_min) / res)
    xy = np.stack([np.asarray(graph.x, np.float64), np.asarray(graph.y, np.float64)], axis=1)
    # repeats and both ways draw the same cells; a vertex with no edge is drawn as a dot
    lonely = np.flatnonzero(np.bincount(np.concatenate([graph.src, graph.dst]), minlength=len(xy)) == 0)
    src = np.concatenate([np.asarray(graph.src, np.int64), lonely])
    dst = np.concatenate([np.asarray(graph.dst, np.int64), lonely])
    return _draw(xy, src, dst, crop.x_min, crop.y_max, res, rows, cols, params.miou_line_width / 2 + EPS)


@dataclass
class IouCounts:
    intersection: int = 0
    union: int = 0

    def add(self, other: IouCounts) -> None:
        self.intersection += other.intersection
        self.union += other.union


def iou_counts(pred: LaneGraph, gt: LaneGraph, params: MetricParams) -> IouCounts:
    a, b = draw(pred, params), draw(gt, params)
    return IouCounts(int(np.count_nonzero(a & b)), int(np.count_nonzero(a | b)))
