"""TOPO, Junction TOPO and mIoU of a predicted lane graph against the ground truth.

docs/METRICS.md is the definition; this module implements it step by step:
densify -> candidate pairs -> matching P -> for each pair: Reach sets and their matching -> sums.

The per-pair work (two shortest-path searches and one matching for each of ~3,000 pairs per frame)
is the hot path, so it runs in numba kernels over flat arrays. tests/test_metrics.py keeps a plain
networkx reading of the definition and checks that both agree exactly, pair by pair.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numba
import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import maximum_bipartite_matching

from pipeline.geometry import Range
from pipeline.lane_graph import LaneGraph

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


# ---------------------------------------------------------------------------------------------------
# Step 1: densify


def identical_points(xy: np.ndarray) -> tuple[np.ndarray, int]:
    """(vertex of each point, number of vertices): points at identical coordinates are one vertex,
    numbered 0.. in the order of their first appearance."""
    return _identical_points(xy, np.argsort(xy[:, 0]))  # numpy's sort is the faster one


@numba.njit(cache=True)
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


@numba.njit(cache=True)
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


@numba.njit(cache=True)
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


@numba.njit(cache=True)
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


# ---------------------------------------------------------------------------------------------------
# Step 2: candidate pairs and the matching M(V_pred, V_gt)


@dataclass
class Candidates:
    """Pairs (a, b) closer than the match radius. Rank r is the r-th pair in matching order,
    ascending (distance, a, b); a_ptr/a_rank list each a's pairs by rank (CSR), b_ptr/b_rank each b's."""

    a: np.ndarray  # (C,) int64 vertex of A, by rank
    b: np.ndarray  # (C,) int64 vertex of B, by rank
    dist: np.ndarray  # (C,) float64, by rank
    a_ptr: np.ndarray  # (n_a + 1,)
    a_rank: np.ndarray  # (C,)
    b_ptr: np.ndarray  # (n_b + 1,)
    b_rank: np.ndarray  # (C,)


@numba.njit(cache=True)
def _rows(keys, n):
    """CSR of the ranks 0..len(keys)-1 grouped by key, ascending within each row."""
    ptr = np.zeros(n + 1, np.int64)
    for key in keys:
        ptr[key + 1] += 1
    ptr = np.cumsum(ptr)
    fill = ptr[:-1].copy()
    ranks = np.empty(len(keys), np.int64)
    for r in range(len(keys)):
        ranks[fill[keys[r]]] = r
        fill[keys[r]] += 1
    return ptr, ranks


@numba.njit(cache=True)
def _cell_search(
    a_xy, b_xy, limit, group_a, group_b, a_cell, a_order, b_cell, b_order, column, pair_a, pair_b, pair_d
):
    """near_pairs' search: the number of pairs found; those that fit in the buffers are written."""
    near2 = (limit * 1.000001) ** 2  # a cheap first test, looser than the exact one
    cursor = np.zeros(3, np.int64)
    at = 0
    for i in a_order:
        if a_cell[i] < 0:
            continue
        for c in range(3):
            first = a_cell[i] + (c - 1) * column - 1  # the run of cells (x - 1 + c, y - 1 .. y + 1)
            while cursor[c] < len(b_cell) and b_cell[cursor[c]] < first:
                cursor[c] += 1
            s = cursor[c]
            while s < len(b_cell) and b_cell[s] <= first + 2:
                j = b_order[s]
                s += 1
                if group_a[i] == group_b[j]:
                    continue
                dx, dy = a_xy[i, 0] - b_xy[j, 0], a_xy[i, 1] - b_xy[j, 1]
                if dx * dx + dy * dy > near2:
                    continue
                d = np.sqrt(dx * dx + dy * dy)
                if d < limit:
                    if at < len(pair_a):
                        pair_a[at], pair_b[at], pair_d[at] = i, j, d
                    at += 1
    return at


@numba.njit(cache=True)
def near_pairs(a_xy, b_xy, radius, eps, group_a, group_b):
    """(count per a, b, distance) of the pairs closer than radius - eps, grouped by a (b in no
    particular order), leaving out pairs in the same group (group_a[i] == group_b[j]).

    Both sets are sorted by the square cell of side radius they fall in, numbered column by column,
    so that the 3 x 3 cells around a point are three runs of three consecutive cell numbers, and
    walking A in cell order moves three cursors over B only forward. A dense grid of 0.15 m cells
    would cost more to clear than the search itself, and cKDTree is several times slower at this
    size, mostly in building its trees and its result lists."""
    if len(a_xy) == 0 or len(b_xy) == 0:
        return np.zeros(len(a_xy), np.int64), np.empty(0, np.int64), np.empty(0)
    bx = np.floor(b_xy[:, 0] / radius).astype(np.int64)
    by = np.floor(b_xy[:, 1] / radius).astype(np.int64)
    x0, y0, x1, y1 = bx.min() - 1, by.min() - 1, bx.max() + 1, by.max() + 1
    column = y1 - y0 + 2  # one unused cell number between columns: runs never spill into the next
    b_cell = (bx - x0) * column + (by - y0)
    b_order = np.argsort(b_cell)
    b_cell = b_cell[b_order]
    if a_xy.shape == b_xy.shape and np.all(a_xy == b_xy):  # a self-join (Path2Graph): B's sort serves
        a_order, a_cell = b_order, np.empty(len(a_xy), np.int64)
        a_cell[b_order] = b_cell
    else:
        ax = np.floor(a_xy[:, 0] / radius).astype(np.int64)
        ay = np.floor(a_xy[:, 1] / radius).astype(np.int64)
        inside = (ax >= x0) & (ax <= x1) & (ay >= y0) & (ay <= y1)  # the others have no neighbour
        a_cell = np.where(inside, (ax - x0) * column + (ay - y0), -1)
        a_order = np.argsort(a_cell)

    # buffers for ~16 pairs per point (0.45 m around points 0.15 m apart: ~9): reallocating them inside
    # the search loop would slow it down 4x in numba, so a search that overflows runs again
    size = 16 * len(a_xy) + 64
    while True:
        pair_a, pair_b, pair_d = np.empty(size, np.int64), np.empty(size, np.int64), np.empty(size)
        at = _cell_search(
            a_xy,
            b_xy,
            radius - eps,
            group_a,
            group_b,
            a_cell,
            a_order,
            b_cell,
            b_order,
            column,
            pair_a,
            pair_b,
            pair_d,
        )
        if at <= size:
            break
        size = at
    count = np.bincount(pair_a[:at], minlength=len(a_xy))
    _, rows = _rows(pair_a[:at], len(a_xy))  # grouped by a
    return count, pair_b[rows], pair_d[rows]


@numba.njit(cache=True)
def ties_by_key(order, dist, key):
    """Sort each run of equal distances of an (unstable) argsort by key, i.e. by (a, b)."""
    s = 0
    while s < len(order):
        t = s + 1
        while t < len(order) and dist[order[t]] == dist[order[s]]:
            t += 1
        if t - s > 1:
            run = order[s:t].copy()
            order[s:t] = run[np.argsort(key[run])]
        s = t
    return order


@numba.njit(cache=True)
def _ranked(count, pair_b, dist, order, n_a, n_b):
    """The pairs in matching order (order: an unstable argsort of dist), and their rows by a and b."""
    pair_a = np.repeat(np.arange(n_a), count)
    order = ties_by_key(order, dist, pair_a * n_b + pair_b)
    a, b = pair_a[order], pair_b[order]
    a_ptr, a_rank = _rows(a, n_a)
    b_ptr, b_rank = _rows(b, n_b)
    return a, b, dist[order], a_ptr, a_rank, b_ptr, b_rank


def candidate_pairs(a_xy: np.ndarray, b_xy: np.ndarray, radius: float) -> Candidates:
    if len(a_xy) and len(b_xy):
        no_group_a, no_group_b = np.full(len(a_xy), -1), np.full(len(b_xy), -2)
        count, pair_b, dist = near_pairs(a_xy, b_xy, radius, EPS, no_group_a, no_group_b)
    else:
        count, pair_b, dist = np.zeros(len(a_xy), np.int64), np.zeros(0, np.int64), np.zeros(0)
    # numpy's unstable sort is several times faster than a stable one; ties are rare and fixed after
    return Candidates(*_ranked(count, pair_b, dist, np.argsort(dist), len(a_xy), len(b_xy)))


@numba.njit(cache=True)
def _greedy(cand_a, cand_b, n_a, n_b):
    """Take the pairs in rank order, keeping one when neither end is taken yet.
    Returns each vertex's partner (-1: none) and the rank of its pair."""
    partner_a, partner_b = np.full(n_a, -1, np.int64), np.full(n_b, -1, np.int64)
    rank_a, rank_b = np.full(n_a, len(cand_a), np.int64), np.full(n_b, len(cand_a), np.int64)
    for r in range(len(cand_a)):
        a, b = cand_a[r], cand_b[r]
        if partner_a[a] < 0 and partner_b[b] < 0:
            partner_a[a], partner_b[b] = b, a
            rank_a[a], rank_b[b] = r, r
    return partner_a, partner_b, rank_a, rank_b


@dataclass
class Matching:
    """M(A, B) over all vertices: partner_a[a] = b (-1: unmatched), rank_a[a] the rank of that pair."""

    partner_a: np.ndarray
    partner_b: np.ndarray
    rank_a: np.ndarray
    rank_b: np.ndarray

    @property
    def pairs(self) -> tuple[np.ndarray, np.ndarray]:
        a = np.flatnonzero(self.partner_a >= 0)
        return a, self.partner_a[a]


def optimal_partners(cand_a: np.ndarray, cand_b: np.ndarray, n_a: int, n_b: int) -> np.ndarray:
    """Partner of each a (-1: none) in a maximum-cardinality matching (Hopcroft-Karp)."""
    graph = csr_matrix((np.ones(len(cand_a)), (cand_a, cand_b)), shape=(n_a, n_b))
    return np.asarray(maximum_bipartite_matching(graph, perm_type="column"), np.int64)


def match(cand: Candidates, n_a: int, n_b: int, matching: str) -> Matching:
    if matching == "greedy":
        return Matching(*_greedy(cand.a, cand.b, n_a, n_b))
    partner_a = optimal_partners(cand.a, cand.b, n_a, n_b)
    partner_b = np.full(n_b, -1, np.int64)
    paired = np.flatnonzero(partner_a >= 0)
    partner_b[partner_a[paired]] = paired
    none = np.full(max(n_a, n_b), len(cand.a), np.int64)  # ranks only serve the greedy kernel
    return Matching(partner_a, partner_b, none[:n_a], none[:n_b])


# ---------------------------------------------------------------------------------------------------
# Steps 3-4: Reach, and the counts of each pair (the hot path)


@numba.njit(cache=True)
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


@numba.njit(cache=True, inline="always")
def _walk(first, last, w_in, w_exit, entry_hub, exit_hub, v, d, forward, limit, stamp, sid, out, count):
    """From chain vertex v, at distance d < limit, along its chain: marks (stamp == sid, appended to
    out) the vertices closer than limit; returns (count, the hub at the chain's end, or -1 when that
    is out of reach, and its distance)."""
    if stamp[v] != sid:
        stamp[v], out[count], count = sid, v, count + 1
    if forward:
        while v != last[v]:
            d += w_in[v + 1]
            if d >= limit:
                return count, -1, 0.0
            v += 1
            if stamp[v] != sid:
                stamp[v], out[count], count = sid, v, count + 1
        return count, exit_hub[v], d + w_exit[v]
    while v != first[v]:
        d += w_in[v]
        if d >= limit:
            return count, -1, 0.0
        v -= 1
        if stamp[v] != sid:
            stamp[v], out[count], count = sid, v, count + 1
    return count, entry_hub[v], d + w_in[v]


@numba.njit(cache=True, inline="always")
def _reach(
    indptr, nbr, weight, is_hub, first, last, w_in, w_exit, entry_hub, exit_hub, directed,
    source, limit, hub_dist, stamp, queued, queue, sid, out,
):  # fmt: skip
    """Reach(source) in the chain-major numbering: chains are walked in tight loops; between hubs,
    labels are corrected with a FIFO queue until no edge improves one.

    Writes the vertices to out (returns how many) and marks them stamp == sid; hub_dist, stamp,
    queued and queue are work arrays reused across calls. Distances are summed from the source along
    each path, so the labels are the very floats Dijkstra computes (the minimum over paths).
    """
    count, head, tail, size = 0, 0, 0, len(queue)
    hub_a, dist_a, hub_b, dist_b = -1, 0.0, -1, 0.0  # the hubs the source reaches first
    if is_hub[source]:
        hub_a = source
    else:
        count, hub_a, dist_a = _walk(
            first, last, w_in, w_exit, entry_hub, exit_hub, source, 0.0, True, limit, stamp, sid, out, count
        )
        if not directed:
            count, hub_b, dist_b = _walk(
                first,
                last,
                w_in,
                w_exit,
                entry_hub,
                exit_hub,
                source,
                0.0,
                False,
                limit,
                stamp,
                sid,
                out,
                count,
            )
    for h, d in ((hub_a, dist_a), (hub_b, dist_b)):
        if h >= 0 and d < limit and (stamp[h] != sid or d < hub_dist[h]):
            if stamp[h] != sid:
                stamp[h], out[count], count = sid, h, count + 1
            hub_dist[h] = d
            if queued[h] != sid:
                queued[h], queue[tail] = sid, h
                tail = tail + 1 if tail + 1 < size else 0
    while head != tail:
        u = queue[head]
        head = head + 1 if head + 1 < size else 0
        queued[u] = 0
        for e in range(indptr[u], indptr[u + 1]):
            v, d = nbr[e], hub_dist[u] + weight[e]
            if d >= limit:
                continue
            if not is_hub[v]:  # into a chain at one of its ends, walking away from u
                forward = directed or (first[v] == v and entry_hub[v] == u)
                count, v, d = _walk(
                    first,
                    last,
                    w_in,
                    w_exit,
                    entry_hub,
                    exit_hub,
                    v,
                    d,
                    forward,
                    limit,
                    stamp,
                    sid,
                    out,
                    count,
                )
                if v < 0 or d >= limit:
                    continue
            if stamp[v] != sid or d < hub_dist[v]:
                if stamp[v] != sid:
                    stamp[v], out[count], count = sid, v, count + 1
                hub_dist[v] = d
                if queued[v] != sid:
                    queued[v], queue[tail] = sid, v
                    tail = tail + 1 if tail + 1 < size else 0
    return count


@numba.njit(cache=True, inline="always")
def _heap_push(keys, vals, size, key, val):
    i = size
    while i > 0 and keys[(i - 1) // 2] > key:
        keys[i], vals[i] = keys[(i - 1) // 2], vals[(i - 1) // 2]
        i = (i - 1) // 2
    keys[i], vals[i] = key, val
    return size + 1


@numba.njit(cache=True, inline="always")
def _heap_pop(keys, vals, size):
    top_key, top_val = keys[0], vals[0]
    size -= 1
    key, val = keys[size], vals[size]
    i = 0
    while 2 * i + 1 < size:
        child = 2 * i + 1
        if child + 1 < size and keys[child + 1] < keys[child]:
            child += 1
        if keys[child] >= key:
            break
        keys[i], vals[i] = keys[child], vals[child]
        i = child
    keys[i], vals[i] = key, val
    return top_key, top_val, size


@numba.njit(cache=True, inline="always")
def _next_pair(ptr, ranks, other_end, other_stamp, sid, v, after):
    """The first pair of v ranked after `after` whose other end is in the other Reach set, or -1."""
    for i in range(ptr[v], ptr[v + 1]):
        r = ranks[i]
        if r > after and other_stamp[other_end[r]] == sid:
            return r
    return -1


@numba.njit(cache=True)
def _pair_counts(
    pair_a, pair_b, limit, cand_a, cand_b, a_ptr, a_rank, b_ptr, b_rank, partner_a, partner_b, rank_a, rank_b,
    a_indptr, a_nbr, a_weight, a_is_hub, a_first, a_last, a_w_in, a_w_exit, a_entry, a_exit, directed,
    b_indptr, b_nbr, b_weight, b_is_hub, b_first, b_last, b_w_in, b_w_exit, b_entry, b_exit, _,
):  # fmt: skip
    """For each pair (p, g): |S_p|, |S_g| and |M(S_p, S_g)|, S = Reach, M the greedy matching.

    The greedy matching restricted to S_p x S_g is the global one except near the border of the
    window, so it is computed as a repair of the global one: every pair of the global matching inside
    the window stands, until a vertex whose global partner lies outside is freed; then, in rank
    order (an event heap), each freed vertex takes its next pair whose other end is still free at
    that rank, which may free that end's later partner in turn. This replays the greedy exactly,
    touching the window's vertices once and only the few pairs whose decision changes.
    """
    n_a, n_b, n_cand = len(a_indptr) - 1, len(b_indptr) - 1, len(cand_a)
    size_a, size_b, matched = np.zeros((3, len(pair_a)), np.int64)
    dist_a, stamp_a, queued_a = np.empty(n_a), np.zeros(n_a, np.int64), np.zeros(n_a, np.int64)
    dist_b, stamp_b, queued_b = np.empty(n_b), np.zeros(n_b, np.int64), np.zeros(n_b, np.int64)
    reach_a, queue_a = np.empty(n_a, np.int64), np.empty(n_a + 1, np.int64)
    reach_b, queue_b = np.empty(n_b, np.int64), np.empty(n_b + 1, np.int64)
    # the matching inside the window: the rank at which each vertex is taken (n_cand: never), by whom
    taken_a, with_a = np.empty(n_a, np.int64), np.empty(n_a, np.int64)
    taken_b, with_b = np.empty(n_b, np.int64), np.empty(n_b, np.int64)
    heap_keys = np.empty(2 * n_cand + n_a + n_b + 1, np.int64)  # a pair enters at most once per end
    heap_vals = np.empty(2 * n_cand + n_a + n_b + 1, np.int64)  # 2 * vertex + (0: of A, 1: of B)
    for k in range(len(pair_a)):
        sid = k + 1
        count_a = _reach(
            a_indptr, a_nbr, a_weight, a_is_hub, a_first, a_last, a_w_in, a_w_exit, a_entry, a_exit, directed,
            pair_a[k], limit, dist_a, stamp_a, queued_a, queue_a, sid, reach_a,
        )  # fmt: skip
        count_b = _reach(
            b_indptr, b_nbr, b_weight, b_is_hub, b_first, b_last, b_w_in, b_w_exit, b_entry, b_exit, directed,
            pair_b[k], limit, dist_b, stamp_b, queued_b, queue_b, sid, reach_b,
        )  # fmt: skip
        m, heap = 0, 0
        for i in range(count_a):
            a = reach_a[i]
            b = partner_a[a]
            if b >= 0 and stamp_b[b] == sid:
                taken_a[a], with_a[a] = rank_a[a], b
                m += 1
            else:
                taken_a[a], with_a[a] = n_cand, -1
                if b >= 0:
                    r = _next_pair(a_ptr, a_rank, cand_b, stamp_b, sid, a, rank_a[a])
                    if r >= 0:
                        heap = _heap_push(heap_keys, heap_vals, heap, r, 2 * a)
        for i in range(count_b):
            b = reach_b[i]
            a = partner_b[b]
            if a >= 0 and stamp_a[a] == sid:
                taken_b[b], with_b[b] = rank_b[b], a
            else:
                taken_b[b], with_b[b] = n_cand, -1
                if a >= 0:
                    r = _next_pair(b_ptr, b_rank, cand_a, stamp_a, sid, b, rank_b[b])
                    if r >= 0:
                        heap = _heap_push(heap_keys, heap_vals, heap, r, 2 * b + 1)
        while heap:
            r, code, heap = _heap_pop(heap_keys, heap_vals, heap)
            a, b, of_b = cand_a[r], cand_b[r], code & 1
            if (taken_b[b] if of_b else taken_a[a]) <= r:
                continue  # the freed vertex was taken again meanwhile
            if taken_a[a] > r and taken_b[b] > r:  # both free at rank r: the window keeps (a, b)
                m += 1
                loser_a, loser_b, lost_at = -1, -1, n_cand
                if of_b:  # a gives up the pair it would take later
                    loser_b, lost_at = with_a[a], taken_a[a]
                else:
                    loser_a, lost_at = with_b[b], taken_b[b]
                taken_a[a], with_a[a], taken_b[b], with_b[b] = r, b, r, a
                if loser_a >= 0:
                    m -= 1
                    taken_a[loser_a], with_a[loser_a] = n_cand, -1
                    r2 = _next_pair(a_ptr, a_rank, cand_b, stamp_b, sid, loser_a, lost_at)
                    if r2 >= 0:
                        heap = _heap_push(heap_keys, heap_vals, heap, r2, 2 * loser_a)
                if loser_b >= 0:
                    m -= 1
                    taken_b[loser_b], with_b[loser_b] = n_cand, -1
                    r2 = _next_pair(b_ptr, b_rank, cand_a, stamp_a, sid, loser_b, lost_at)
                    if r2 >= 0:
                        heap = _heap_push(heap_keys, heap_vals, heap, r2, 2 * loser_b + 1)
            else:  # the other end is taken: the freed vertex tries its next pair
                if of_b:
                    r2 = _next_pair(b_ptr, b_rank, cand_a, stamp_a, sid, b, r)
                else:
                    r2 = _next_pair(a_ptr, a_rank, cand_b, stamp_b, sid, a, r)
                if r2 >= 0:
                    heap = _heap_push(heap_keys, heap_vals, heap, r2, code)
        size_a[k], size_b[k], matched[k] = count_a, count_b, m
    return size_a, size_b, matched


def reach(graph: Dense, source: int, radius: float) -> np.ndarray:
    """Reach(G, v): the sorted vertices closer than radius to source along the edges."""
    n = graph.n
    out, queue = np.empty(n, np.int64), np.empty(n + 1, np.int64)
    hub_dist, stamp, queued = np.empty(n), np.zeros(n, np.int64), np.zeros(n, np.int64)
    work = (hub_dist, stamp, queued, queue, 1, out)
    count = _reach(*graph.chains, graph.new_of[source], radius - EPS, *work)
    return np.sort(graph.order[out[:count]])


@dataclass
class PairCounts:
    """Step 4 of one frame in one mode, per pair."""

    pred: np.ndarray  # (P,) paired predicted vertex
    gt: np.ndarray  # (P,) paired ground-truth vertex
    size_pred: np.ndarray  # |S_p|
    size_gt: np.ndarray  # |S_g|
    matched: np.ndarray  # |M(S_p, S_g)|


@numba.njit(cache=True)
def _renumbered(cand_a, cand_b, partner_a, partner_b, rank_a, rank_b, new_of_a, order_a, new_of_b, order_b):
    """The candidates and the matching in the kernels' chain-major numbering (ranks keep their order)."""
    cand_a, cand_b = new_of_a[cand_a], new_of_b[cand_b]
    new_partner_a, new_partner_b = np.full(len(order_a), -1, np.int64), np.full(len(order_b), -1, np.int64)
    for new in range(len(order_a)):
        if partner_a[order_a[new]] >= 0:
            new_partner_a[new] = new_of_b[partner_a[order_a[new]]]
    for new in range(len(order_b)):
        if partner_b[order_b[new]] >= 0:
            new_partner_b[new] = new_of_a[partner_b[order_b[new]]]
    a_ptr, a_rank = _rows(cand_a, len(order_a))
    b_ptr, b_rank = _rows(cand_b, len(order_b))
    matching = (new_partner_a, new_partner_b, rank_a[order_a], rank_b[order_b])
    return cand_a, cand_b, a_ptr, a_rank, b_ptr, b_rank, *matching


def pair_counts(pred: Dense, gt: Dense, pair_p, pair_g, cand: Candidates, m: Matching, params: MetricParams):
    pair_p, pair_g = np.asarray(pair_p, np.int64), np.asarray(pair_g, np.int64)
    if params.matching == "greedy":
        matching = (m.partner_a, m.partner_b, m.rank_a, m.rank_b)
        renumbered = _renumbered(cand.a, cand.b, *matching, pred.new_of, pred.order, gt.new_of, gt.order)
        limit = params.reach_radius - EPS
        pairs = (pred.new_of[pair_p], gt.new_of[pair_g])
        sizes = _pair_counts(*pairs, limit, *renumbered, *pred.chains, *gt.chains)
    else:  # a maximum-cardinality matching for each pair: slow, an option off by default
        sizes = tuple(np.zeros(len(pair_p), np.int64) for _ in range(3))
        for k, (p, g) in enumerate(zip(pair_p.tolist(), pair_g.tolist())):
            s_p, s_g = reach(pred, p, params.reach_radius), reach(gt, g, params.reach_radius)
            inside = np.isin(cand.a, s_p) & np.isin(cand.b, s_g)
            partner = optimal_partners(cand.a[inside], cand.b[inside], pred.n, gt.n)
            sizes[0][k], sizes[1][k], sizes[2][k] = len(s_p), len(s_g), np.count_nonzero(partner >= 0)
    return PairCounts(pair_p, pair_g, *sizes)


# ---------------------------------------------------------------------------------------------------
# Steps 4-5: one frame's sums, and the scores over a set of frames


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
# Step 7: mIoU


@numba.njit(cache=True)
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
    """The graph on the BEV grid of docs/DATA.md, params.miou_line_width wide (cells by centre)."""
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
