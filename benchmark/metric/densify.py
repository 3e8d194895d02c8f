"""Step 1 of the metric (docs/METRICS.md): densify a lane graph, every edge split into equal parts of at
most `step` and identical points made one vertex (Dense), renumbered chain-major for the Reach kernels.

Path2Graph (benchmark/graphs/path2graph.py) splits and merges its paths with the same kernels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from benchmark.metric.candidates import _rows
from benchmark.metric.params import EPS
from pipeline.kernels import kernel
from pipeline.lane_graph import LaneGraph


def identical_points(xy: np.ndarray) -> tuple[np.ndarray, int]:
    """(vertex of each point, number of vertices): points at identical coordinates are one vertex,
    numbered 0.. in the order of their first appearance."""
    return _identical_points(xy, np.argsort(xy[:, 0]))  # numpy's sort is the faster one


@kernel
def _identical_points(xy, order):
    same = np.arange(len(xy))  # a point with the same coordinates met before in the sort, or itself
    s = 0
    while s < len(order):  # equal x sit together in the sort: sort each such run by y
        t = s + 1
        while t < len(order) and xy[order[t], 0] == xy[order[s], 0]:
            t += 1
        if t - s > 16:
            run = order[s:t].copy()
            order[s:t] = run[np.argsort(xy[run, 1])]
        else:  # most runs are a handful of points: sort them in place, without allocating
            for r in range(s + 1, t):
                i, q = order[r], r
                while q > s and xy[order[q - 1], 1] > xy[i, 1]:
                    order[q] = order[q - 1]
                    q -= 1
                order[q] = i
        for r in range(s + 1, t):
            if xy[order[r], 1] == xy[order[r - 1], 1]:
                same[order[r]] = same[order[r - 1]]
        s = t
    vertex = np.full(len(xy), -1, np.int64)
    n = 0
    for i in range(len(xy)):
        if vertex[same[i]] < 0:
            vertex[same[i]] = n
            n += 1
        vertex[i] = vertex[same[i]]
    return vertex, n


@kernel
def _unique_edges(src, dst, n, directed):
    keep = np.flatnonzero(src != dst)
    key = src[keep] * n + dst[keep]
    key = np.unique(key)  # sorted by (src, dst)
    if directed:
        return key // n, key % n
    # undirected: the first of u -> v and v -> u in that order stands for both
    lo, hi = np.minimum(key // n, key % n), np.maximum(key // n, key % n)
    order = np.argsort(lo * n + hi, kind="mergesort")
    first = np.ones(len(key), np.bool_)
    for i in range(1, len(order)):
        first[order[i]] = lo[order[i]] != lo[order[i - 1]] or hi[order[i]] != hi[order[i - 1]]
    return key[first] // n, key[first] % n


def unique_edges(graph: LaneGraph, directed: bool) -> np.ndarray:
    """(E, 2) int64 edges without self-loops or repeats, sorted by (src, dst).

    Undirected: u -> v and v -> u are one edge, kept in the orientation that comes first in that
    order, so that it densifies into the same points as in directed mode.
    """
    src, dst = np.asarray(graph.src, np.int64), np.asarray(graph.dst, np.int64)
    return np.stack(_unique_edges(src, dst, max(len(graph.x), 1), directed), axis=1)


@dataclass
class Dense:
    """A densified graph in one mode. xy and junction are in the definition's vertex numbering; the
    kernels work in a chain-major numbering (see _chain_order): order[new] = vertex, new_of[vertex]."""

    xy: np.ndarray  # (n, 2) float64
    junction: np.ndarray  # (n,) bool
    order: np.ndarray
    new_of: np.ndarray
    chains: tuple  # the edges that Reach follows, in the chain-major numbering (see _chain_order)

    @property
    def n(self) -> int:
        return len(self.xy)


@kernel
def split_into_parts(xy, src, dst, step, eps):
    """Edges src -> dst split into k = max(1, ceil(L / step - eps)) equal parts. Returns the points
    (xy, then each edge's inner points xy[src] + (xy[dst] - xy[src]) * (i / k)) and the sub-edges
    (src, dst, length L / k). An edge at most eps steps over a multiple of the step is not split
    further. Path2Graph splits its paths with this same kernel: same segment, same floats."""
    length = np.empty(len(src))
    k = np.empty(len(src), np.int64)
    for e in range(len(src)):
        dx, dy = xy[dst[e], 0] - xy[src[e], 0], xy[dst[e], 1] - xy[src[e], 1]
        length[e] = np.sqrt(dx * dx + dy * dy)
        k[e] = max(1, np.int64(np.ceil(length[e] / step - eps)))
    points = np.empty((len(xy) + k.sum() - len(k), 2))
    points[: len(xy)] = xy
    sub_src, sub_dst = np.empty(k.sum(), np.int64), np.empty(k.sum(), np.int64)
    sub_w = np.empty(k.sum())
    at, s = len(xy), 0
    for e in range(len(src)):
        ax, ay, bx, by = xy[src[e], 0], xy[src[e], 1], xy[dst[e], 0], xy[dst[e], 1]
        prev = src[e]
        for i in range(1, k[e]):
            t = i / k[e]
            points[at, 0], points[at, 1] = ax + (bx - ax) * t, ay + (by - ay) * t
            sub_src[s], sub_dst[s], sub_w[s] = prev, at, length[e] / k[e]
            prev, at, s = at, at + 1, s + 1
        sub_src[s], sub_dst[s], sub_w[s] = prev, dst[e], length[e] / k[e]
        s += 1
    return points, sub_src, sub_dst, sub_w


@kernel
def _adjacency(vertex, n, sub_src, sub_dst, sub_w, directed):
    """CSR (indptr, nbr, weight) and junction flags over the vertices (identical points made one):
    one edge per (src, dst), the shortest, no self-loops; both ways when undirected."""
    m = len(sub_src)
    if directed and n == len(vertex):  # nothing was merged: the sub-edges are distinct already
        indptr, rows = _rows(sub_src, n)
        in_degree = np.bincount(sub_dst, minlength=n)
        out_degree = indptr[1:] - indptr[:-1]
        return indptr, sub_dst[rows], sub_w[rows], (in_degree >= 2) | (out_degree >= 2)
    both = 1 if directed else 2
    src, dst, w = np.empty(both * m, np.int64), np.empty(both * m, np.int64), np.empty(both * m)
    for i in range(m):
        src[i], dst[i], w[i] = vertex[sub_src[i]], vertex[sub_dst[i]], sub_w[i]
        if not directed:
            src[m + i], dst[m + i], w[m + i] = dst[i], src[i], sub_w[i]
    if n == len(vertex):  # nothing was merged: both ways of distinct sub-edges are distinct
        indptr, rows = _rows(src, n)
        out_degree = indptr[1:] - indptr[:-1]
        return indptr, dst[rows], w[rows], out_degree >= 3
    order = np.argsort(src * n + dst)
    keep = np.zeros(len(src), np.bool_)
    last = -1
    for r in range(len(order)):
        i = order[r]
        if src[i] == dst[i]:
            continue
        if last >= 0 and src[last] == src[i] and dst[last] == dst[i]:
            if w[i] < w[last]:  # a shorter copy of the same edge
                keep[last], keep[i], last = False, True, i
            continue
        keep[i], last = True, i
    kept = np.flatnonzero(keep)
    indptr, rows = _rows(src[kept], n)
    in_degree = np.bincount(dst[kept], minlength=n)
    out_degree = indptr[1:] - indptr[:-1]
    junction = (in_degree >= 2) | (out_degree >= 2) if directed else out_degree >= 3
    return indptr, dst[kept][rows], w[kept][rows], junction


def densify(graph: LaneGraph, step: float) -> dict[str, Dense]:
    """{"directed": ..., "undirected": ...}: every edge split into equal parts, then points at
    identical coordinates made one vertex. Junctions: in- or out-degree >= 2 (directed), >= 3
    distinct neighbours (undirected)."""
    xy = np.stack([np.asarray(graph.x, np.float64), np.asarray(graph.y, np.float64)], axis=1) + 0.0  # no -0.0
    out, last = {}, None
    for mode in ("directed", "undirected"):
        edges = unique_edges(graph, mode == "directed")
        if last is None or len(edges) != len(last[0]):  # the same edges unless u -> v and v -> u
            points, sub_src, sub_dst, sub_w = split_into_parts(xy, edges[:, 0], edges[:, 1], step, EPS)
            vertex, n = identical_points(points)
            first = np.full(n, len(points))
            np.minimum.at(first, vertex, np.arange(len(points)))
            last = (edges, points[first], vertex, n, sub_src, sub_dst, sub_w)
        edges, xy_out, vertex, n, sub_src, sub_dst, sub_w = last
        directed = mode == "directed"
        indptr, nbr, weight, junction = _adjacency(vertex, n, sub_src, sub_dst, sub_w, directed)
        order, new_of, chains = _chain_order(indptr, nbr, weight, directed)
        out[mode] = Dense(xy_out, junction, order, new_of, chains)
    return out


@kernel
def _chain_order(indptr, nbr, weight, directed):
    """A lane graph densified at 0.15 m is mostly chains: runs of vertices with one way in and one way
    on (directed) or two neighbours (undirected). The other vertices are hubs; a closed run without
    one gets its first vertex as hub. Renumbered hubs first, then chain after chain in driving order,
    a walk along a chain is a walk along consecutive numbers, and Reach can run it in a tight loop.

    Returns (order: new -> old, new_of: old -> new, chains), chains in the new numbering:
    (indptr, nbr, weight: the CSR; is_hub; first, last: the ends of each vertex's chain; w_in[v]: the
    weight of the edge into v from the vertex before it (the entry hub for a chain's first);
    w_exit[v], exit_hub[v] at a chain's last vertex: the edge on to the hub after it;
    entry_hub[v] at a chain's first vertex; directed)."""
    n = len(indptr) - 1
    out_degree = indptr[1:] - indptr[:-1]
    in_degree = np.zeros(n, np.int64)
    for e in range(len(nbr)):
        in_degree[nbr[e]] += 1
    hub = out_degree != 2
    if directed:
        hub = (in_degree != 1) | (out_degree != 1)
    new_of = np.full(n, -1, np.int64)
    order = np.empty(n, np.int64)
    is_hub = np.zeros(n, np.bool_)
    first, last = np.zeros(n, np.int64), np.zeros(n, np.int64)
    w_in, w_exit = np.zeros(n), np.zeros(n)
    entry_hub, exit_hub = np.full(n, -1, np.int64), np.full(n, -1, np.int64)
    count = 0
    for v in range(n):
        if hub[v]:
            new_of[v], order[count], is_hub[count] = count, v, True
            count += 1
    done, unseen = 0, 0  # order[:done] have had their chains followed; vertices < unseen are placed
    while True:
        while done < count:
            h = order[done]
            done += 1
            if not hub[h]:
                continue
            for e in range(indptr[h], indptr[h + 1]):
                v = nbr[e]
                if hub[v] or new_of[v] >= 0:
                    continue
                chain_first, prev, w = count, h, weight[e]
                while True:  # follow the chain from v to the next hub
                    new_of[v], order[count], w_in[count] = count, v, w
                    count += 1
                    nxt = -1
                    for e2 in range(indptr[v], indptr[v + 1]):
                        if directed or nbr[e2] != prev:
                            nxt, w = nbr[e2], weight[e2]
                            break
                    if hub[nxt] or new_of[nxt] >= 0:
                        break
                    prev, v = v, nxt
                first[chain_first:count], last[chain_first:count] = chain_first, count - 1
                entry_hub[chain_first] = new_of[h]
                w_exit[count - 1], exit_hub[count - 1] = w, nxt  # old numbering, mapped below
        while unseen < n and new_of[unseen] >= 0:
            unseen += 1
        if unseen == n:
            break
        hub[unseen] = True  # a closed run without a hub: its first vertex becomes one
        new_of[unseen], order[count], is_hub[count] = count, unseen, True
        count += 1
    for i in range(n):
        if exit_hub[i] >= 0:
            exit_hub[i] = new_of[exit_hub[i]]
    new_indptr = np.zeros(n + 1, np.int64)
    for u in range(n):
        new_indptr[u + 1] = new_indptr[u] + out_degree[order[u]]
    new_nbr, new_weight = np.empty(len(nbr), np.int64), np.empty(len(nbr))
    for u in range(n):
        old = order[u]
        at = new_indptr[u]
        for e in range(indptr[old], indptr[old + 1]):
            new_nbr[at], new_weight[at] = new_of[nbr[e]], weight[e]
            at += 1
    chains = (new_indptr, new_nbr, new_weight, is_hub, first, last, w_in, w_exit, entry_hub, exit_hub)
    return order, new_of, (*chains, directed)
