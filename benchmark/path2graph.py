"""Path2Graph (LaneGAP, Alg. 2): a set of directed paths back to one lane graph.

1. Each path becomes a chain of vertices: its own polyline points, plus the points that split each
   segment into k = ceil(L / step) equal parts, computed by the metric's own densification
   (benchmark.metrics.split_points). Paths that share a segment therefore give the very same floats.
2. Points at identical coordinates are one vertex.
3. Vertices of different paths closer than merge_radius are merged, nearest pairs first, into one
   vertex at their mean that inherits all their predecessors and successors; a merged vertex never
   takes two vertices of the same path. "Different paths" means different connected pieces after
   step 2: paths that already share a vertex are joined where they truly meet, and merging their
   nearby vertices would only blur a fork or a merge (ground-truth paths share every vertex they
   have in common, so they are rebuilt exactly).
4. Self-loops and repeated edges are dropped.
docs/METRICS.md explains why this makes the ground truth round-trip to 1.000 by construction.
"""

from __future__ import annotations

from collections.abc import Sequence

import numba
import numpy as np

from benchmark.metrics import EPS, identical_points, near_pairs, split_counts, split_points
from pipeline.lane_graph import LaneGraph


def chains(paths: Sequence[np.ndarray], step: float) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 2) float64, path index of each point): every path's points with its segments
    split every <= step, path after path."""
    sizes = np.array([len(p) for p in paths], np.int64)
    if sizes.sum() == 0:
        return np.zeros((0, 2)), np.zeros(0, np.int64)
    points = np.concatenate([np.asarray(p, np.float64).reshape(-1, 2) for p in paths])
    path_of = np.repeat(np.arange(len(paths)), sizes)
    has_next = np.zeros(len(points), bool)
    has_next[:-1] = path_of[:-1] == path_of[1:]
    starts = np.flatnonzero(has_next)
    d = points[starts + 1] - points[starts]
    k = split_counts(np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]), step)
    inner = split_points(points[starts], points[starts + 1], k)
    # each original point moves up by the inner points inserted before it
    inserted_after = np.zeros(len(points), np.int64)
    inserted_after[starts] = k - 1
    position = np.arange(len(points)) + np.cumsum(inserted_after) - inserted_after
    out = np.empty((len(points) + len(inner), 2))
    is_original = np.zeros(len(out), bool)
    is_original[position] = True
    out[position] = points
    out[~is_original] = inner
    out_path = np.empty(len(out), np.int64)
    out_path[position] = path_of
    out_path[~is_original] = np.repeat(path_of[starts], k - 1)
    return out, out_path


@numba.njit(cache=True)
def _find(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@numba.njit(cache=True)
def _cluster(xy, vertex, n, chain_next, radius, eps):
    """Step 3: the cluster of each step-2 vertex. xy are the points, vertex their step-2 vertex."""
    # the connected pieces that the chains form over the step-2 vertices
    piece = np.arange(n)
    for i in range(len(xy)):
        if chain_next[i] >= 0:
            piece[_find(piece, vertex[i])] = _find(piece, vertex[chain_next[i]])
    first = np.full(n, -1, np.int64)
    for i in range(len(xy) - 1, -1, -1):
        first[vertex[i]] = i
    points = xy[first]
    for v in range(n):
        piece[v] = _find(piece, v)

    cluster = np.arange(n)
    if radius <= 0.0:
        return cluster
    count, pair_b, dist = near_pairs(points, points, radius, eps)
    pair_a = np.repeat(np.arange(n), count)
    near = np.flatnonzero((pair_a < pair_b) & (piece[pair_a] != piece[pair_b]))
    near = near[np.argsort(dist[near], kind="mergesort")]  # stable: ties stay in (a, b) order
    # nearest pairs first; a cluster's members form a linked list from its root, to check that no
    # cluster ever holds two vertices of one piece
    next_member = np.full(n, -1, np.int64)
    last_member = np.arange(n)
    for p in near:
        u, v = _find(cluster, pair_a[p]), _find(cluster, pair_b[p])
        if u == v:
            continue
        clash = False
        i = u
        while i >= 0 and not clash:
            j = v
            while j >= 0 and not clash:
                clash = piece[i] == piece[j]
                j = next_member[j]
            i = next_member[i]
        if not clash:
            cluster[v] = u
            next_member[last_member[u]] = v
            last_member[u] = last_member[v]
    for v in range(n):
        cluster[v] = _find(cluster, v)
    return cluster


def path2graph(paths: Sequence[np.ndarray], step: float = 0.15, merge_radius: float = 0.15) -> LaneGraph:
    """The lane graph of a set of paths, each an (n, 2) array of points in driving order.

    Coordinates stay float64: the chain points are then exactly the metric's densified points.
    """
    xy, path_of = chains(paths, step)
    if len(xy) == 0:
        return LaneGraph.empty()
    chain_next = np.arange(1, len(xy) + 1)
    chain_next[np.append(path_of[1:] != path_of[:-1], True)] = -1
    vertex, n = identical_points(xy)
    cluster = _cluster(xy, vertex, n, chain_next, merge_radius, EPS)

    # one output vertex per cluster, numbered by first appearance, at the mean of its step-2 vertices
    first = np.full(n, len(xy))
    np.minimum.at(first, vertex, np.arange(len(xy)))
    points = xy[first]
    roots, root_first, out_of_vertex = np.unique(cluster, return_index=True, return_inverse=True)
    rank = np.empty(len(roots), np.int64)
    rank[np.argsort(root_first)] = np.arange(len(roots))
    out_of_vertex = rank[out_of_vertex.ravel()]
    n_out = len(roots)
    first_vertex = np.full(n_out, n)
    np.minimum.at(first_vertex, out_of_vertex, np.arange(n))
    base = points[first_vertex]
    offset = points - base[out_of_vertex]  # first + mean offset: a cluster of one keeps its floats
    size = np.bincount(out_of_vertex, minlength=n_out)[:, None]
    mean = base + np.stack([np.bincount(out_of_vertex, offset[:, i], n_out) for i in (0, 1)], axis=1) / size

    linked = np.flatnonzero(chain_next >= 0)
    src, dst = out_of_vertex[vertex[linked]], out_of_vertex[vertex[chain_next[linked]]]
    key = np.unique((src * n_out + dst)[src != dst])
    return LaneGraph(mean[:, 0], mean[:, 1], (key // n_out).astype(np.int32), (key % n_out).astype(np.int32))
