"""Steps 3-4 of the metric (docs/METRICS.md), the hot path: Reach sets, and for each pair |S_p|, |S_g| and
|M(S_p, S_g)| (PairCounts), in numba kernels over densify.py's chain-major numbering.

Two shortest-path searches and one matching for each of ~3,000 pairs per frame: the kernels work on flat
arrays, and the window's greedy matching is a repair of the global one (see _pair_counts).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from benchmark.metric.candidates import Candidates, _rows
from benchmark.metric.densify import Dense
from benchmark.metric.matching import Matching, optimal_partners
from benchmark.metric.params import EPS, MetricParams
from pipeline.kernels import kernel


@kernel(inline="always")
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


@kernel(inline="always")
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


@kernel(inline="always")
def _heap_push(keys, vals, size, key, val):
    i = size
    while i > 0 and keys[(i - 1) // 2] > key:
        keys[i], vals[i] = keys[(i - 1) // 2], vals[(i - 1) // 2]
        i = (i - 1) // 2
    keys[i], vals[i] = key, val
    return size + 1


@kernel(inline="always")
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


@kernel(inline="always")
def _next_pair(ptr, ranks, other_end, other_stamp, sid, v, after):
    """The first pair of v ranked after `after` whose other end is in the other Reach set, or -1."""
    for i in range(ptr[v], ptr[v + 1]):
        r = ranks[i]
        if r > after and other_stamp[other_end[r]] == sid:
            return r
    return -1


@kernel
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


@kernel
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
