"""CGNet's GEO / TOPO / JTOPO (XiaoMi/CGNet's topo_eval, as its nuScenes dataset class calls it): one frame's
scores (cgnet_frame, numba kernels) and their averages over frames (cgnet_result), under CGNetParams
(params.py, with CGNET_VERSION: the table of metrics names them without loading this module).

docs/METRICS.md describes the definition and how it differs from ours. In short, for one frame:

1. Input. Our LaneGraph is the graph CGNet's dataset class builds from its lines (`get_graph_gt`, and its
   decoder for predictions): node i at the float32 position (x[i], y[i]) in metres in the BEV frame (x
   right, y forward, as in CGNet's nuScenes frame), an edge per (src, dst), repeats once, as
   `nx.DiGraph(adjacency)`, whose edges run in (src, dst) order, whatever order a prediction lists them in
   (CGNet builds its true and predicted graphs alike from adjacency matrices). Each node is keyed by
   trunc(float64(float32 x) * 10), the same of y: whole decimetres, truncated towards 0 (CGNet's numpy
   1.23 multiplies a float32 scalar by the int 10 in float64). Nodes with one key are one node; a node
   keeps the successor keys of its edges in first-seen order.
2. Interpolation. Keys in dict order, each one's successors in order: an edge whose reverse came first is
   skipped; an edge of L decimetres gets n = max(2, int(L / 2.5) + 1) points i = 0 .. n - 1 at
   x1 * w + x2 * (1 - w), w = 1 - i / (n - 1), in float64; a part (point i - 1 to i) with an end outside
   x in [-150, 150), y in [-300, 300) is dropped. Nodes are the kept parts' ends (exact float pairs) in
   first-seen order, each with its successors in first-seen order.
3. GEO. Pairs (predicted, true) with squared distance r = dx ** 2 + dy ** 2 < 5 ** 2 (libm's pow, as
   Python's `**`), in order of r, then predicted node, then the R-tree's order of the true nodes; kept
   greedily when both ends are free. Precision = matched / predicted nodes, recall = matched / true nodes.
4. TOPO. The matched pairs number k = 0, 1, ... in that order; for k % 10 == 0, each end's reach: the
   depth-first walk of `propagateByDistance` (a stack; a node is marked when popped, expanded when its
   depth is below 80, and pushes its unmarked successors at depth + edge length), listed in the order of
   a CPython set. Their greedy matching (pairs by r, then the true node's place in its list, then the
   R-tree's order of the predicted list) gives m; p = m / |predicted reach|, r = m / |true reach|.
   Precision = GEO precision * mean(p), recall = GEO recall * mean(r).
5. JTOPO: the same over every matched pair whose true node has more than one successor.
6. F1 = 0 when P or R is 0, else 2 * (P * R / (P + R)), per frame; over frames each number is averaged
   with NaN skipped (np.nanmean), F1 included.
"""

from __future__ import annotations

import math

import numpy as np

from benchmark.metric.cgnet_order import rtree_rank, set_order, tuple_hash
from benchmark.metric.params import CGNET_VERSION, CGNetParams
from pipeline.kernels import kernel
from pipeline.lane_graph import LaneGraph

METRICS = ("geo", "topo", "jtopo")
STATS = ("precision", "recall", "f1")
SMALL_TREE = 100  # an R-tree of at most this many entries is one leaf: its order is the insertion order


# ---------------------------------------------------------------------------------------------------
# 1. Input: the key edges in the order the evaluator visits them


def key_edges(graph: LaneGraph, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """(from, to) key positions, (E, 2) float64 each, of the key graph's edges in the evaluator's visiting
    order: keys by first appearance as a source over the (src, dst)-sorted edges, each key's successors
    in first-seen order, an edge whose reverse came earlier left out."""
    n = len(graph.x)
    src, dst = np.asarray(graph.src, np.int64), np.asarray(graph.dst, np.int64)
    if n == 0 or len(src) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    xy = np.stack([np.asarray(graph.x, np.float32), np.asarray(graph.y, np.float32)], axis=1)
    keys = np.trunc(xy.astype(np.float64) * scale)
    low, span = keys.min(0), keys.max(0) - keys.min(0) + 1
    if span[0] * span[1] < 2.0**52:  # one exact number per key: faster than unique rows
        code = (keys[:, 0] - low[0]) * span[1] + (keys[:, 1] - low[1])
        _, first_of, key_of = np.unique(code, return_index=True, return_inverse=True)
        unique_keys = keys[first_of]
    else:
        unique_keys, key_of = np.unique(keys, axis=0, return_inverse=True)
    key_of = key_of.reshape(-1)
    edges = np.unique(src * n + dst)  # (src, dst) order, repeats once
    a, b = key_of[edges // n], key_of[edges % n]
    m = len(unique_keys)
    pair, first = np.unique(a * m + b, return_index=True)
    source_first = np.full(m, len(a))
    np.minimum.at(source_first, a, np.arange(len(a)))
    pa, pb = pair // m, pair % m
    order = np.lexsort((first, source_first[pa]))
    pa, pb = pa[order], pb[order]
    # an edge is left out when its reverse comes earlier in this order
    code, by_code = pa * m + pb, np.argsort(pa * m + pb)
    at = np.minimum(np.searchsorted(code[by_code], pb * m + pa), len(code) - 1)
    reverse_first = (code[by_code[at]] == pb * m + pa) & (by_code[at] < np.arange(len(code))) & (pa != pb)
    return unique_keys[pa[~reverse_first]], unique_keys[pb[~reverse_first]]


# ---------------------------------------------------------------------------------------------------
# 2. Interpolation


@kernel
def _point_ids(px, py):
    """Ids of the points by exact value (-0.0 is 0.0), numbered by first appearance, and their count."""
    n = len(px)
    size = 16
    while size < 2 * n:
        size <<= 1
    slots = np.full(size, -1, np.int64)
    ids, first = np.empty(n, np.int64), np.empty(n, np.int64)
    count = 0
    for k in range(n):
        x, y = px[k] + 0.0, py[k] + 0.0
        h = (tuple_hash(x, y) >> np.uint64(3)) & np.uint64(size - 1)
        i = np.int64(h)
        while True:
            j = slots[i]
            if j < 0:
                slots[i], ids[k], first[count] = count, count, k
                count += 1
                break
            if px[first[j]] + 0.0 == x and py[first[j]] + 0.0 == y:
                ids[k] = j
                break
            i = (i + 1) & (size - 1)
    return ids, first[:count]


@kernel
def _interpolate(ax, ay, bx, by, step, half_width, half_length):
    """The interpolated graph: node positions (x, y) and successor lists (ptr, succ) in CSR form."""
    total = 0
    parts = np.empty(len(ax), np.int64)
    for e in range(len(ax)):
        dx, dy = ax[e] - bx[e], ay[e] - by[e]
        parts[e] = max(2, int(math.sqrt(dx * dx + dy * dy) / step) + 1)
        total += parts[e] - 1
    ends_x, ends_y = np.empty(2 * total), np.empty(2 * total)
    kept = 0
    for e in range(len(ax)):
        x1, y1, x2, y2, m = ax[e], ay[e], bx[e], by[e], parts[e]
        lx, ly = x1, y1
        for i in range(1, m):
            w = 1.0 - float(i) / (m - 1)
            x, y = x1 * w + x2 * (1 - w), y1 * w + y2 * (1 - w)
            if (-half_width <= x < half_width and -half_length <= y < half_length
                    and -half_width <= lx < half_width and -half_length <= ly < half_length):  # fmt: skip
                ends_x[2 * kept], ends_y[2 * kept], ends_x[2 * kept + 1], ends_y[2 * kept + 1] = lx, ly, x, y
                kept += 1
            lx, ly = x, y
    ids, first = _point_ids(ends_x[: 2 * kept], ends_y[: 2 * kept])
    n = len(first)
    u, v = ids[0::2], ids[1::2]
    by_node = np.argsort(u, kind="mergesort")  # each node's parts in the order they came
    ptr = np.zeros(n + 1, np.int64)
    succ = np.empty(kept, np.int64)
    out = 0
    k = 0
    for node in range(n):
        start = out
        while k < kept and u[by_node[k]] == node:
            t = v[by_node[k]]
            seen = False
            for j in range(start, out):
                seen = seen or succ[j] == t
            if not seen:
                succ[out] = t
                out += 1
            k += 1
        ptr[node + 1] = out
    return ends_x[first], ends_y[first], ptr, succ[:out]


# ---------------------------------------------------------------------------------------------------
# 3. Candidate pairs and the frame's matching


@kernel
def _candidates(px, py, gx, gy, radius, two):
    """Pairs (predicted a, true b, r) with r = (gx - px) ** two + (gy - py) ** two < radius ** 2, sorted by
    (r, a, b). `two` is 2.0 passed at run time, so that the square is libm's pow as in Python."""
    limit = radius * radius
    lo_x, lo_y = min(gx.min(), px.min()), min(gy.min(), py.min())
    cols = int((max(gx.max(), px.max()) - lo_x) / radius) + 1
    rows = int((max(gy.max(), py.max()) - lo_y) / radius) + 1
    cell = (np.floor((gx - lo_x) / radius).astype(np.int64) * rows
            + np.floor((gy - lo_y) / radius).astype(np.int64))  # fmt: skip
    order = np.argsort(cell, kind="mergesort")
    start = np.searchsorted(cell[order], np.arange(cols * rows + 1))
    cap = 64
    ca, cb, cr = np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap)
    count = 0
    for a in range(len(px)):
        cx, cy = int((px[a] - lo_x) / radius), int((py[a] - lo_y) / radius)
        begin = count
        for i in range(max(cx - 1, 0), min(cx + 2, cols)):
            for j in range(max(cy - 1, 0), min(cy + 2, rows)):
                for s in range(start[i * rows + j], start[i * rows + j + 1]):
                    b = order[s]
                    dx, dy = gx[b] - px[a], gy[b] - py[a]
                    if dx * dx + dy * dy > limit * 1.000001 + 1e-9:
                        continue
                    r = math.pow(dx, two) + math.pow(dy, two)
                    if r < limit:
                        if count == cap:
                            cap *= 2
                            ca, cb, cr = _grow(ca, cap), _grow(cb, cap), _grow(cr, cap)
                        ca[count], cb[count], cr[count] = a, b, r
                        count += 1
        for i in range(begin + 1, count):  # this node's pairs by true node (few: insertion sort)
            k = i
            while k > begin and cb[k - 1] > cb[k]:
                cb[k - 1], cb[k], cr[k - 1], cr[k] = cb[k], cb[k - 1], cr[k], cr[k - 1]
                k -= 1
    by_r = np.argsort(cr[:count], kind="mergesort")
    return ca[by_r], cb[by_r], cr[by_r]


@kernel
def _grow(values, size):
    out = np.empty(size, values.dtype)
    out[: len(values)] = values
    return out


@kernel
def _greedy(first, second, r, free_first, free_second, rank, ranked):
    """Greedy one-to-one matching of pairs sorted by (r, first): a pair is kept when both ends are free;
    pairs of equal (r, first) go in the order of rank[second], which is read only when two of them are
    free at once: without `ranked` that returns (-1, ...), the caller computes the ranks and comes again.
    Returns (number matched, the kept pairs' positions)."""
    n = len(r)
    kept = np.empty(n, np.int64)
    matched = 0
    k = 0
    while k < n:
        end = k + 1
        while end < n and r[end] == r[k] and first[end] == first[k]:
            end += 1
        if free_first[first[k]]:
            best = -1
            for i in range(k, end):
                if free_second[second[i]]:
                    if best < 0:
                        best = i
                    elif not ranked:
                        return -1, kept[:0]
                    elif rank[second[i]] < rank[second[best]]:
                        best = i
            if best >= 0:
                free_first[first[k]] = False
                free_second[second[best]] = False
                kept[matched] = best
                matched += 1
        k = end
    return matched, kept[:matched]


# ---------------------------------------------------------------------------------------------------
# 4. The walk and the matching of two walks


@kernel
def _walk(ptr, succ, length, start, limit, mark, sid, stack_node, stack_depth, added):
    """propagateByDistance from start: the nodes it marks, in the order first marked, into added."""
    stack_node[0], stack_depth[0] = start, 0.0
    top, count = 1, 0
    while top:
        top -= 1
        v, depth = stack_node[top], stack_depth[top]
        if mark[v] != sid:
            mark[v] = sid
            added[count] = v
            count += 1
        if depth >= limit:
            continue
        for j in range(ptr[v], ptr[v + 1]):
            if mark[succ[j]] != sid:
                stack_node[top], stack_depth[top] = succ[j], depth + length[j]
                top += 1
    return count


@kernel
def _lengths(x, y, ptr, succ, two):
    """Each successor entry's edge length, sqrt((x_v - x_u) ** 2 + (y_v - y_u) ** 2) with libm's pow."""
    out = np.empty(len(succ))
    for v in range(len(ptr) - 1):
        for j in range(ptr[v], ptr[v + 1]):
            out[j] = math.sqrt(math.pow(x[v] - x[succ[j]], two) + math.pow(y[v] - y[succ[j]], two))
    return out


@kernel
def _frame(px, py, pptr, psucc, gx, gy, gptr, gsucc, cand_a, cand_b, cand_r, params, two):
    """Step 3-5 of one frame: (matched, TOPO p, r per scored pair, JTOPO p, r per scored pair)."""
    limit, box, every = params[0], params[1], int(params[2])
    n_p, n_g = len(px), len(gx)
    # 3. the frame's matching; R-tree order of the true nodes only if a tie asks for it
    free_p, free_g = np.ones(n_p, np.bool_), np.ones(n_g, np.bool_)
    matched, kept = _greedy(cand_a, cand_b, cand_r, free_p, free_g, np.empty(0, np.int64), False)
    if matched < 0:
        free_p[:] = True
        free_g[:] = True
        matched, kept = _greedy(cand_a, cand_b, cand_r, free_p, free_g, rtree_rank(gx, gy, box), True)
    # candidates of each true node, for the walks' matchings
    by_g = np.argsort(cand_b, kind="mergesort")
    g_ptr = np.searchsorted(cand_b[by_g], np.arange(n_g + 1))
    # the walks: per side a mark stamp, a stack, the marked nodes, their list order, place in the list
    p_len, g_len = _lengths(px, py, pptr, psucc, two), _lengths(gx, gy, gptr, gsucc, two)
    p_hash, g_hash = np.empty(n_p, np.uint64), np.empty(n_g, np.uint64)
    for v in range(n_p):
        p_hash[v] = tuple_hash(px[v], py[v])
    for v in range(n_g):
        g_hash[v] = tuple_hash(gx[v], gy[v])
    p_mark, g_mark = np.zeros(n_p, np.int64), np.zeros(n_g, np.int64)
    p_stack, p_depth = np.empty(len(psucc) + 1, np.int64), np.empty(len(psucc) + 1)
    g_stack, g_depth = np.empty(len(gsucc) + 1, np.int64), np.empty(len(gsucc) + 1)
    p_added, g_added = np.empty(n_p, np.int64), np.empty(n_g, np.int64)
    p_list, g_list = np.empty(n_p, np.int64), np.empty(n_g, np.int64)
    p_place = np.empty(n_p, np.int64)
    size = 8 * max(n_p, n_g) + 8
    table, spare = np.empty(size, np.int64), np.empty(size, np.int64)
    topo_p, topo_r = np.empty(matched // every + 1), np.empty(matched // every + 1)
    junc_p, junc_r = np.empty(matched), np.empty(matched)
    n_topo, n_junc = 0, 0
    for k in range(matched):
        a, b = cand_a[kept[k]], cand_b[kept[k]]
        junction = gptr[b + 1] - gptr[b] > 1
        if not (junction or k % every == 0):
            continue
        sid = k + 1
        count_p = _walk(pptr, psucc, p_len, a, limit, p_mark, sid, p_stack, p_depth, p_added)
        count_g = _walk(gptr, gsucc, g_len, b, limit, g_mark, sid, g_stack, g_depth, g_added)
        set_order(p_added, count_p, p_hash, table, spare, p_list)
        set_order(g_added, count_g, g_hash, table, spare, g_list)
        for i in range(count_p):
            p_place[p_list[i]] = i
        m = _window(p_list, count_p, p_mark, p_place, g_list, count_g, cand_a, cand_r, by_g, g_ptr, px, py,
                    sid, box)  # fmt: skip
        pre, rec = float(m) / count_p, float(m) / count_g
        if junction:
            junc_p[n_junc], junc_r[n_junc] = pre, rec
            n_junc += 1
        if k % every == 0:
            topo_p[n_topo], topo_r[n_topo] = pre, rec
            n_topo += 1
    return matched, topo_p[:n_topo], topo_r[:n_topo], junc_p[:n_junc], junc_r[:n_junc]


@kernel
def _window(p_list, count_p, p_mark, p_place, g_list, count_g, cand_a, cand_r, by_g, g_ptr, px, py, sid, box):
    """The evaluator's `match` of two walks: pairs (true place i, predicted place n, r) with r < radius ** 2,
    the true list outside, each one's predicted candidates in the R-tree's order of the predicted list,
    sorted stably by r; the greedy matching's size."""
    total = 0
    for i in range(count_g):
        g = g_list[i]
        total += g_ptr[g + 1] - g_ptr[g]
    first, second, r = np.empty(total, np.int64), np.empty(total, np.int64), np.empty(total)
    n = 0
    for i in range(count_g):
        g = g_list[i]
        begin = n
        for s in range(g_ptr[g], g_ptr[g + 1]):
            a = cand_a[by_g[s]]
            if p_mark[a] == sid:
                first[n], second[n], r[n] = i, p_place[a], cand_r[by_g[s]]
                k = n
                while k > begin and second[k - 1] > second[k]:  # by place: the one-leaf R-tree's order
                    second[k - 1], second[k], r[k - 1], r[k] = second[k], second[k - 1], r[k], r[k - 1]
                    k -= 1
                n += 1
    order = np.argsort(r[:n], kind="mergesort")
    first, second, r = first[order], second[order], r[order]
    free_g, free_p = np.ones(count_g, np.bool_), np.ones(count_p, np.bool_)
    small = count_p <= SMALL_TREE
    m, _ = _greedy(first, second, r, free_g, free_p, np.arange(count_p), small)
    if m < 0:
        free_g[:] = True
        free_p[:] = True
        rank = rtree_rank(px[p_list[:count_p]], py[p_list[:count_p]], box)
        m, _ = _greedy(first, second, r, free_g, free_p, rank, True)
    return m


# ---------------------------------------------------------------------------------------------------
# 6. Scores


def _f1(precision: float, recall: float) -> float:
    if precision == 0 or recall == 0:
        return 0.0
    return 2 * ((precision * recall) / (precision + recall))


def _mean(values: np.ndarray) -> float:
    return float(np.mean(values)) if len(values) else math.nan


def interpolated(graph: LaneGraph, params: CGNetParams):
    """Steps 1-2: (x, y, ptr, succ) of the evaluator's interpolated graph of one side."""
    a, b = key_edges(graph, params.scale)
    return _interpolate(a[:, 0].copy(), a[:, 1].copy(), b[:, 0].copy(), b[:, 1].copy(), params.interp_dist,
                        params.half_width, params.half_length)  # fmt: skip


def cgnet_frame(pred: LaneGraph, gt: LaneGraph, params: CGNetParams) -> dict:
    """One frame's {"geo" | "topo" | "jtopo": {"precision", "recall", "f1"}}: the evaluator's numbers (NaN
    where it gives NaN: TOPO and JTOPO with no scored pair; recall with no true node, where the evaluator
    itself divides by zero and stops). A plain dict of floats, for worker processes."""
    px, py, pptr, psucc = interpolated(pred, params)
    gx, gy, gptr, gsucc = interpolated(gt, params)
    if len(px) == 0:  # the evaluator returns zeros before anything else
        return {name: {stat: 0.0 for stat in STATS} for name in METRICS}
    matched, scored = 0, (np.zeros(0),) * 4
    if len(gx):
        two = float(np.float64(2.0))
        cand = _candidates(px, py, gx, gy, params.radius, two)
        numbers = np.array([params.prop_dist, params.box, params.topo_every], np.float64)
        matched, *scored = _frame(px, py, pptr, psucc, gx, gy, gptr, gsucc, *cand, numbers, two)
    geo_p = matched / len(px)
    geo_r = matched / len(gx) if len(gx) else math.nan
    out = {"geo": {"precision": geo_p, "recall": geo_r, "f1": _f1(geo_p, geo_r)}}
    for name, (pre, rec) in (("topo", scored[0:2]), ("jtopo", scored[2:4])):
        p, r = geo_p * _mean(pre), geo_r * _mean(rec)
        out[name] = {"precision": p, "recall": r, "f1": _f1(p, r)}
    return out


def cgnet_result(frames: list[dict], params: CGNetParams | None = None) -> dict:
    """The scores over frames as CGNet reports them: each per-frame number averaged with NaN skipped
    (np.nanmean over frames, F1 too: the mean of the frames' F1, not the F1 of the means). A number with
    no frame to average is None (JSON null)."""
    out: dict = {}
    for name in METRICS:
        out[name] = {}
        for stat in STATS:
            values = np.array([frame[name][stat] for frame in frames], np.float64)
            out[name][stat] = float(np.nanmean(values)) if np.any(~np.isnan(values)) else None
    out["frames"] = len(frames)
    out["params"] = (params or CGNetParams()).to_dict()
    out["version"] = CGNET_VERSION
    return out
