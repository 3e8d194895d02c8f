"""Step 2 of the metric (docs/METRICS.md): the candidate pairs, vertices closer than the match radius,
in matching order (Candidates), found by a cell search (near_pairs) that Path2Graph shares."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from benchmark.metric.params import EPS
from pipeline.kernels import kernel


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


@kernel
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


@kernel
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


@kernel
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


@kernel
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


@kernel
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
