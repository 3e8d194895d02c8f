"""Pixel2Graph (HDMapNet-style post-processing): a lane mask and a direction map to a directed graph.

1. Thinning: the mask's skeleton (scikit-image, Zhang's method), one pixel wide.
2. Pixel graph: skeleton pixels are joined to their 4-neighbours, and to a diagonal neighbour only
   when no skeleton pixel is a 4-neighbour of both (m-adjacency), so that an L-shaped corner is a
   chain and not a triangle.
3. Nodes: pixels with other than two neighbours (ends, junctions); touching junction pixels form one
   node at their mean. A closed loop without any gets its first pixel as a node.
4. Tracing: from every node, each way out is followed through two-neighbour pixels to the next node,
   giving one polyline per skeleton branch; spurs (a branch from a junction to a dead end) shorter
   than min_spur pixels are dropped, the thinning's usual artefacts at the ends of a wide line.
5. Orientation: along each polyline, the direction bins under its pixels (bin b: travel direction
   (b - 0.5) * 360 / bins degrees, 0 = +x, counter-clockwise; 0 = no direction) are compared with the
   polyline's own direction of tracing; the polyline is reversed when they disagree on the whole.
6. Simplification: Douglas-Peucker with a tolerance of `tolerance` metres (skimage
   approximate_polygon); the ends stay, so branches still meet at their nodes.
Pixel (r, c) has its centre at x = x_min + (c + 0.5) * res, y = y_max - (r + 0.5) * res (docs/DATA.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from skimage.measure import approximate_polygon
from skimage.morphology import skeletonize

from pipeline.lane_graph import LaneGraph
from pipeline.raster import direction_vectors

NEIGHBOURS = [(-1, 0), (0, -1), (0, 1), (1, 0), (-1, -1), (-1, 1), (1, -1), (1, 1)]  # 4-neighbours first


@dataclass(frozen=True)
class RasterGrid:
    x_min: float = -15.0
    y_max: float = 30.0
    resolution: float = 0.15
    direction_bins: int = 36


def skeleton_adjacency(skeleton: np.ndarray) -> tuple[np.ndarray, list[list[int]]]:
    """(pixels (P, 2) as (row, col), neighbours of each pixel) under m-adjacency."""
    rows, cols = skeleton.shape
    pixels = np.argwhere(skeleton)
    index = np.full((rows + 2, cols + 2), -1, np.int64)
    index[1:-1, 1:-1][skeleton] = np.arange(len(pixels))
    on = index >= 0
    r, c = pixels[:, 0] + 1, pixels[:, 1] + 1
    src, dst = [], []
    for dr, dc in NEIGHBOURS:
        other = index[r + dr, c + dc]
        ok = other >= 0
        if dr and dc:  # diagonal: only when the two pixels share no 4-neighbour on the skeleton
            ok &= ~on[r + dr, c] & ~on[r, c + dc]
        src.append(np.flatnonzero(ok))
        dst.append(other[ok])
    src, dst = np.concatenate(src), np.concatenate(dst)
    neighbours: list[list[int]] = [[] for _ in range(len(pixels))]
    for p, q in zip(src.tolist(), dst.tolist()):
        neighbours[p].append(q)
    return pixels, neighbours


def trace(neighbours: list[list[int]]) -> tuple[np.ndarray, list[list[int]]]:
    """(node of each pixel, -1 for chain pixels; branches as pixel lists from node to node)."""
    degree = np.array([len(n) for n in neighbours], np.int64)
    node = np.where(degree != 2, 0, -1)
    # touching node pixels form one node
    is_node = np.flatnonzero(node >= 0)
    pairs = [(p, q) for p in is_node.tolist() for q in neighbours[p] if degree[q] != 2]
    pairs = np.array(pairs, np.int64).reshape(-1, 2)
    n = len(neighbours)
    _, label = connected_components(
        coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    )
    node[is_node] = label[is_node]

    branches: list[list[int]] = []
    done = np.zeros(n, bool)  # chain pixels already traced

    def follow(start: int, first: int) -> list[int]:
        branch, prev, cur = [start, first], start, first
        while node[cur] < 0:
            done[cur] = True
            step = neighbours[cur][0] if neighbours[cur][0] != prev else neighbours[cur][1]
            prev, cur = cur, step
            branch.append(cur)
            if cur == start:  # a loop closed on its own start
                break
        return branch

    for p in is_node.tolist():
        for q in neighbours[p]:
            if node[q] < 0 and not done[q]:
                branches.append(follow(p, q))
    for p in range(n):  # closed loops with no node: their first pixel becomes one
        if node[p] < 0 and not done[p]:
            node[p] = label.max() + 1 + p
            done[p] = True
            branches.append(follow(p, neighbours[p][0]))
    return node, branches


def pixel2graph(
    mask: np.ndarray,
    direction: np.ndarray,
    grid: RasterGrid = RasterGrid(),
    tolerance: float = 0.15,
    min_spur: int = 5,
) -> LaneGraph:
    skeleton = skeletonize(np.asarray(mask) > 0)
    pixels, neighbours = skeleton_adjacency(skeleton)
    if len(pixels) == 0:
        return LaneGraph.empty()
    node, branches = trace(neighbours)
    res = grid.resolution
    xy = np.stack([grid.x_min + (pixels[:, 1] + 0.5) * res, grid.y_max - (pixels[:, 0] + 0.5) * res], axis=1)
    pixel_vector = direction_vectors(grid.direction_bins)[np.asarray(direction)[pixels[:, 0], pixels[:, 1]]]

    # nodes: one vertex each, at the mean of its pixels
    node_ids, node_of = np.unique(node[node >= 0], return_inverse=True)
    node_xy = np.stack([np.bincount(node_of, xy[node >= 0, i]) for i in (0, 1)], axis=1)
    node_xy /= np.bincount(node_of)[:, None]
    vertex_of_node = dict(zip(node_ids.tolist(), range(len(node_ids))))
    degree = np.zeros(len(node_ids), np.int64)
    for b in branches:
        degree[vertex_of_node[node[b[0]]]] += 1
        degree[vertex_of_node[node[b[-1]]]] += 1

    points: list[np.ndarray] = [node_xy]
    edges: list[tuple[int, int]] = []
    n_vertices = len(node_xy)
    for b in branches:
        ends = (vertex_of_node[node[b[0]]], vertex_of_node[node[b[-1]]])
        low, high = sorted(degree[list(ends)])
        if len(b) < min_spur and low == 1 and high > 2:
            continue  # a short spur off a junction
        line = xy[b].copy()
        line[0], line[-1] = node_xy[ends[0]], node_xy[ends[-1]]
        tangent = np.gradient(line, axis=0) if len(line) > 1 else np.zeros_like(line)
        if np.sum(tangent * pixel_vector[b]) < 0:  # the direction map says the other way
            line, ends = line[::-1], ends[::-1]
        inner = approximate_polygon(line, tolerance)[1:-1] if len(line) > 2 else line[:0]
        chain = [ends[0], *range(n_vertices, n_vertices + len(inner)), ends[1]]
        points.append(inner)
        n_vertices += len(inner)
        edges += zip(chain[:-1], chain[1:])
    xy_out = np.concatenate(points)
    e = np.array(edges, np.int64).reshape(-1, 2)
    e = np.unique(e[e[:, 0] != e[:, 1]], axis=0)
    return LaneGraph(xy_out[:, 0], xy_out[:, 1], e[:, 0].astype(np.int32), e[:, 1].astype(np.int32))
