"""Path2Graph (LaneGAP, Alg. 2): a set of directed paths back to one lane graph.

1. Each path becomes a chain of vertices: its own polyline points, plus the points that split each
   segment into k = ceil(L / step) equal parts, computed by the metric's own densification kernel.
   Paths that share a segment therefore give the very same floats, and so does the ground truth.
2. Points at identical coordinates are one vertex.
3. Vertices of different paths closer than merge_radius and running the same way (their chains'
   directions within MERGE_MAX_ANGLE) are merged, nearest pairs first, into one vertex at their mean
   that inherits all their predecessors and successors; a merged vertex never takes two vertices of
   the same path. Lanes that cross pass within merge_radius too: merging them would join two lanes
   that never meet (docs/EXPERIMENTS.md measures the direction check). "Different paths" means
   different connected pieces after step 2: paths that already share a vertex meet where they truly
   meet, and merging their nearby vertices would only blur a fork or a merge.
4. Self-loops and repeated edges are dropped.
5. With one score per path (`path2graph_scored`), each edge takes the highest score among the paths
   whose chain parts map onto it; `path2graph` is the same graph without the scores.
Coordinates stay float64. docs/METRICS.md explains the round trip of the ground truth (1.000).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from benchmark.metric.candidates import near_pairs, ties_by_key
from benchmark.metric.densify import identical_points, split_into_parts
from benchmark.metric.params import EPS
from pipeline.kernels import kernel
from pipeline.lane_graph import LaneGraph, graph_of_edges

MERGE_MAX_ANGLE = 45.0  # degrees between two vertices' directions for step 3 to merge them


@kernel
def _find(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@kernel
def _cluster(points, vertex, n, chain_src, chain_dst, radius, eps, direction, min_cos):
    """Step 3: the cluster (a step-2 vertex) of each step-2 vertex."""
    # the connected pieces that the chains form over the step-2 vertices
    piece = np.arange(n)
    for e in range(len(chain_src)):
        piece[_find(piece, vertex[chain_src[e]])] = _find(piece, vertex[chain_dst[e]])
    first = np.full(n, -1, np.int64)
    for i in range(len(points) - 1, -1, -1):
        first[vertex[i]] = i
    for v in range(n):
        piece[v] = _find(piece, v)

    cluster = np.arange(n)
    if radius <= 0.0:
        return cluster
    xy = points[first]
    count, pair_b, dist = near_pairs(xy, xy, radius, eps, piece, piece)
    pair_a = np.repeat(np.arange(n), count)
    near = np.flatnonzero(pair_a < pair_b)
    a, b = pair_a[near], pair_b[near]
    same_way = direction[a, 0] * direction[b, 0] + direction[a, 1] * direction[b, 1] > min_cos
    near = near[same_way]
    near = near[ties_by_key(np.argsort(dist[near]), dist[near], pair_a[near] * n + pair_b[near])]
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


@kernel
def _vertices(points, vertex, n, cluster):
    """Output vertex of each step-2 vertex (clusters numbered by first appearance) and the
    coordinates of each: the mean of its step-2 vertices, as first + mean offset, so that a vertex
    of one keeps its floats."""
    first = np.full(n, -1, np.int64)
    for i in range(len(points) - 1, -1, -1):
        first[vertex[i]] = i
    out = np.full(n, -1, np.int64)
    n_out = 0
    for v in range(n):
        if out[cluster[v]] < 0:
            out[cluster[v]] = n_out
            n_out += 1
        out[v] = out[cluster[v]]
    base = np.empty((n_out, 2))
    total = np.zeros((n_out, 2))
    size = np.zeros(n_out)
    for v in range(n):
        o, p = out[v], first[v]
        if size[o] == 0:
            base[o, 0], base[o, 1] = points[p, 0], points[p, 1]
        total[o, 0] += points[p, 0] - base[o, 0]
        total[o, 1] += points[p, 1] - base[o, 1]
        size[o] += 1
    for o in range(n_out):
        base[o, 0] += total[o, 0] / size[o]
        base[o, 1] += total[o, 1] / size[o]
    return out, base


def path2graph(paths: Sequence[np.ndarray], step: float = 0.15, merge_radius: float = 0.15) -> LaneGraph:
    """The lane graph of a set of paths, each an (n, 2) array of points in driving order."""
    return path2graph_scored(paths, None, step, merge_radius)[0]


def path2graph_scored(
    paths: Sequence[np.ndarray], scores=None, step: float = 0.15, merge_radius: float = 0.15
) -> tuple[LaneGraph, np.ndarray]:
    """(path2graph's graph, each of its edges' score): the highest score among the paths whose chain parts
    map onto that edge (`scores`: one per path; None: every score 0.0)."""
    sizes = np.array([len(p) for p in paths], np.int64)
    if sizes.sum() == 0:
        return LaneGraph.empty(), np.zeros(0)
    path_score = np.zeros(len(paths)) if scores is None else np.asarray(scores, np.float64)
    if path_score.shape != (len(paths),):
        raise ValueError(f"scores: one per path ({len(paths)}) is needed, not shape {path_score.shape}")
    xy = np.concatenate([np.asarray(p, np.float64).reshape(-1, 2) for p in paths]) + 0.0  # no -0.0
    path_of = np.repeat(np.arange(len(paths)), sizes)
    segment = np.flatnonzero(path_of[:-1] == path_of[1:])  # segment i: point i -> point i + 1
    points, chain_src, chain_dst, _ = split_into_parts(xy, segment, segment + 1, step, EPS)
    vertex, n = identical_points(points)
    # each step-2 vertex's direction: that of the chain part leaving it, else of the one entering it
    step_xy = points[chain_dst] - points[chain_src]
    unit = step_xy / np.maximum(np.hypot(step_xy[:, 0], step_xy[:, 1]), 1e-12)[:, None]  # 0 on a repeat
    direction = np.zeros((n, 2))
    direction[vertex[chain_dst]] = unit
    direction[vertex[chain_src]] = unit
    min_cos = np.cos(np.radians(MERGE_MAX_ANGLE))
    cluster = _cluster(points, vertex, n, chain_src, chain_dst, merge_radius, EPS, direction, min_cos)
    out, mean = _vertices(points, vertex, n, cluster)
    src, dst = out[vertex[chain_src]], out[vertex[chain_dst]]
    if scores is None:  # LaneGAP's post-processing, a hot path: no score to keep
        graph, _ = graph_of_edges(mean[:, 0], mean[:, 1], src, dst)
        return graph, np.zeros(len(graph.src))
    # each segment's parts are consecutive, and only its last one ends at an input point (< len(xy))
    last = chain_dst < len(xy)
    part_score = path_score[path_of[segment[np.cumsum(last) - last]]]
    return graph_of_edges(mean[:, 0], mean[:, 1], src, dst, part_score)
