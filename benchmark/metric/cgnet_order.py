"""The visiting orders of CGNet's evaluator, replayed in numba: the order in which its R-tree (libspatialindex
1.9.3's R*-tree, as Rtree builds it) returns entries, and the iteration order of a CPython set of positions.

CGNet's greedy matchings take pairs of equal squared distance in the order its R-tree query returns them and
in the order `list(set)` lists its reached positions, so ties follow these two orders. Both are replayed
step by step:

- R*-tree (src/rtree/Node.cc, Index.cc, RTree.cc of libspatialindex 1.9.3, with Rtree's defaults: R* variant,
  capacity 100 for leaves and index nodes, near-minimum-overlap factor 32, reinsert factor 0.3, split
  distribution factor 0.4, tight MBRs): insertion with choose-subtree (least overlap enlargement above
  leaves, else least area enlargement), forced reinsertion once per level and insertion, R* split, and the
  path adjustments. Its sorts are glibc's qsort, a merge sort: stable, so numpy's stable argsort here. A
  range query walks the tree depth-first with a stack (children pushed in order, so popped last first) and
  lists each leaf's entries in order: a query's answer is the whole walk's order restricted to the entries
  found, so `rtree_rank` returns each entry's place in the whole walk.
- CPython sets (Objects/setobject.c since 3.8, checked against 3.11): hash of a tuple of floats (xxHash
  lanes over each float's hash, Python/pyhash.c), open addressing with 9 linear probes then perturbed jumps,
  growth to four times the used entries when 3/5 full; a set lists its table slots in order.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.kernels import kernel

CAPACITY = 100  # entries of a leaf or an index node
NEAR_OVERLAP = 32  # least-overlap choice: only among the 32 least-enlarging children
REINSERTED = 30  # floor((CAPACITY + 1) * 0.3) entries leave an overflowing node to be inserted again
SPLIT_MIN = 40  # floor((CAPACITY + 1) * 0.4): the least entries of a side in a split
SPLIT_CUTS = CAPACITY + 1 - 2 * SPLIT_MIN + 2  # the split positions tried
BIG = np.finfo(np.float64).max
TINY = np.finfo(np.float64).eps
MAX_LEVELS = 64


# ---------------------------------------------------------------------------------------------------
# Regions: lo, hi are (2,) arrays


@kernel(inline="always")
def _area(lo0, lo1, hi0, hi1):
    return (hi0 - lo0) * (hi1 - lo1)


@kernel(inline="always")
def _margin(lo0, lo1, hi0, hi1):
    return (0.0 + (hi0 - lo0) * 2.0) + (hi1 - lo1) * 2.0


@kernel(inline="always")
def _overlap(alo0, alo1, ahi0, ahi1, blo0, blo1, bhi0, bhi1):
    """The area two regions share (0 when apart; touching regions share 0 too)."""
    if alo0 > bhi0 or ahi0 < blo0 or alo1 > bhi1 or ahi1 < blo1:
        return 0.0
    return (min(ahi0, bhi0) - max(alo0, blo0)) * (min(ahi1, bhi1) - max(alo1, blo1))


@kernel(inline="always")
def _contains(alo, ahi, blo, bhi):
    return not (alo[0] > blo[0] or ahi[0] < bhi[0] or alo[1] > blo[1] or ahi[1] < bhi[1])


@kernel(inline="always")
def _touches(alo, ahi, blo, bhi):
    for d in range(2):
        if (blo[d] - TINY <= alo[d] <= blo[d] + TINY) or (bhi[d] - TINY <= ahi[d] <= bhi[d] + TINY):
            return True
    return False


# ---------------------------------------------------------------------------------------------------
# The R*-tree. Node k: lev[k], cnt[k], its region nlo[k], nhi[k], its entries' regions lo[k, e], hi[k, e]
# and ids ref[k, e] (a child node, or an inserted entry in a leaf). Slot CAPACITY holds an overflowing entry.


@kernel
def _refit(nlo, nhi, lo, hi, cnt, k):
    nlo[k, 0], nlo[k, 1], nhi[k, 0], nhi[k, 1] = BIG, BIG, -BIG, -BIG
    for e in range(cnt[k]):
        for d in range(2):
            nlo[k, d] = min(nlo[k, d], lo[k, e, d])
            nhi[k, d] = max(nhi[k, d], hi[k, e, d])


@kernel
def _append(nlo, nhi, lo, hi, ref, cnt, k, elo, ehi, eref):
    e = cnt[k]
    lo[k, e, 0], lo[k, e, 1], hi[k, e, 0], hi[k, e, 1], ref[k, e] = elo[0], elo[1], ehi[0], ehi[1], eref
    cnt[k] += 1
    for d in range(2):
        nlo[k, d] = min(nlo[k, d], elo[d])
        nhi[k, d] = max(nhi[k, d], ehi[d])


@kernel(inline="always")
def _put(lo, hi, e, elo, ehi):
    lo[e, 0], lo[e, 1], hi[e, 0], hi[e, 1] = elo[0], elo[1], ehi[0], ehi[1]


@kernel
def _fill(tree, k, group, old_lo, old_hi, old_ref):
    """Node k emptied, then the entries `group` of old_* appended in order."""
    nlo, nhi, lo, hi, ref, cnt, lev = tree
    cnt[k] = 0
    nlo[k, 0], nlo[k, 1], nhi[k, 0], nhi[k, 1] = BIG, BIG, -BIG, -BIG
    for e in group:
        _append(nlo, nhi, lo, hi, ref, cnt, k, old_lo[e], old_hi[e], old_ref[e])


@kernel
def _least_enlargement(lo, hi, cnt, k, elo, ehi):
    best, least = -1, np.inf
    for c in range(cnt[k]):
        a = _area(lo[k, c, 0], lo[k, c, 1], hi[k, c, 0], hi[k, c, 1])
        grown = _area(min(lo[k, c, 0], elo[0]), min(lo[k, c, 1], elo[1]),
                      max(hi[k, c, 0], ehi[0]), max(hi[k, c, 1], ehi[1]))  # fmt: skip
        enl = grown - a
        if enl < least:
            least, best = enl, c
        elif enl == least:
            if enl == np.inf or a < _area(lo[k, best, 0], lo[k, best, 1], hi[k, best, 0], hi[k, best, 1]):
                best = c
    return best


@kernel
def _least_overlap(lo, hi, cnt, k, elo, ehi):
    n = cnt[k]
    clo, chi = np.empty((n, 2)), np.empty((n, 2))
    original, enl = np.empty(n), np.empty(n)
    best, least_enl = -1, BIG
    for c in range(n):
        for d in range(2):
            clo[c, d], chi[c, d] = min(lo[k, c, d], elo[d]), max(hi[k, c, d], ehi[d])
        original[c] = _area(lo[k, c, 0], lo[k, c, 1], hi[k, c, 0], hi[k, c, 1])
        enl[c] = _area(clo[c, 0], clo[c, 1], chi[c, 0], chi[c, 1]) - original[c]
        if enl[c] < least_enl:
            least_enl, best = enl[c], c
        elif enl[c] == least_enl and original[c] < original[best]:
            best = c
    if -TINY <= least_enl <= TINY:
        return best
    if n > NEAR_OVERLAP:
        order, tries = np.argsort(enl, kind="mergesort"), NEAR_OVERLAP
    else:
        order, tries = np.arange(n), n
    least = BIG
    for t in range(tries):
        e = order[t]
        dif = 0.0
        for c in range(n):
            if c != e:
                f = _overlap(clo[e, 0], clo[e, 1], chi[e, 0], chi[e, 1],
                             lo[k, c, 0], lo[k, c, 1], hi[k, c, 0], hi[k, c, 1])  # fmt: skip
                if f != 0.0:
                    dif += f - _overlap(lo[k, e, 0], lo[k, e, 1], hi[k, e, 0], hi[k, e, 1],
                                        lo[k, c, 0], lo[k, c, 1], hi[k, c, 0], hi[k, c, 1])  # fmt: skip
        if dif < least:
            least, best = dif, e
        elif dif == least:
            if enl[e] == enl[best]:
                if original[e] < original[best]:
                    best = e
            elif enl[e] < enl[best]:
                best = e
    return best


@kernel
def _spans(lo, hi, order):
    """Prefix and suffix bounding boxes of the entries in `order`: (lo0, lo1, hi0, hi1) each."""
    n = len(order)
    pre, suf = np.empty((n, 4)), np.empty((n, 4))
    acc = np.array([BIG, BIG, -BIG, -BIG])
    for i in range(n):
        e = order[i]
        acc[0], acc[1] = min(acc[0], lo[e, 0]), min(acc[1], lo[e, 1])
        acc[2], acc[3] = max(acc[2], hi[e, 0]), max(acc[3], hi[e, 1])
        pre[i] = acc
    acc = np.array([BIG, BIG, -BIG, -BIG])
    for i in range(n - 1, -1, -1):
        e = order[i]
        acc[0], acc[1] = min(acc[0], lo[e, 0]), min(acc[1], lo[e, 1])
        acc[2], acc[3] = max(acc[2], hi[e, 0]), max(acc[3], hi[e, 1])
        suf[i] = acc
    return pre, suf


@kernel
def _split(lo, hi):
    """R* split of CAPACITY + 1 entries: (first group, second group), each in its sorted order."""
    by_low, by_high = np.arange(CAPACITY + 1), np.arange(CAPACITY + 1)
    least_margin, axis, use_high = BIG, -1, False
    for d in range(2):
        # each sort starts from the order the previous axis left (glibc's merge sort is stable)
        by_low = by_low[np.argsort(lo[by_low, d], kind="mergesort")]
        by_high = by_high[np.argsort(hi[by_high, d], kind="mergesort")]
        sum_low, sum_high = 0.0, 0.0
        pre_l, suf_l = _spans(lo, hi, by_low)
        pre_h, suf_h = _spans(lo, hi, by_high)
        for u in range(1, SPLIT_CUTS + 1):
            cut = SPLIT_MIN - 1 + u
            a, b = pre_l[cut - 1], suf_l[cut]
            sum_low += _margin(a[0], a[1], a[2], a[3]) + _margin(b[0], b[1], b[2], b[3])
            a, b = pre_h[cut - 1], suf_h[cut]
            sum_high += _margin(a[0], a[1], a[2], a[3]) + _margin(b[0], b[1], b[2], b[3])
        m = sum_high if sum_high < sum_low else sum_low
        if m < least_margin:
            least_margin, axis, use_high = m, d, not (sum_low < sum_high)
    keys = hi[by_low, axis] if use_high else lo[by_low, axis]
    order = by_low[np.argsort(keys, kind="mergesort")]
    pre, suf = _spans(lo, hi, order)
    least_overlap, least_area, best = BIG, BIG, -1
    for u in range(1, SPLIT_CUTS + 1):
        cut = SPLIT_MIN - 1 + u
        a, b = pre[cut - 1], suf[cut]
        o = _overlap(a[0], a[1], a[2], a[3], b[0], b[1], b[2], b[3])
        if o < least_overlap:
            best, least_overlap = u, o
            least_area = _area(a[0], a[1], a[2], a[3]) + _area(b[0], b[1], b[2], b[3])
        elif o == least_overlap:
            s = _area(a[0], a[1], a[2], a[3]) + _area(b[0], b[1], b[2], b[3])
            if s < least_area:
                best, least_area = u, s
    cut = SPLIT_MIN - 1 + best
    return order[:cut], order[cut:]


@kernel
def _adjust(tree, k, parent, path, depth, force):
    """Index::adjustTree(node): the parent's entry for k takes k's region, and refits go up while needed."""
    nlo, nhi, lo, hi, ref, cnt, lev = tree
    while True:
        child = 0
        while ref[parent, child] != k:
            child += 1
        contained = _contains(nlo[parent], nhi[parent], nlo[k], nhi[k])
        touching = _touches(nlo[parent], nhi[parent], lo[parent, child], hi[parent, child])
        recompute = not contained or touching
        _put(lo[parent], hi[parent], child, nlo[k], nhi[k])
        if recompute or force:
            _refit(nlo, nhi, lo, hi, cnt, parent)
        if not ((recompute or force) and depth > 0):
            return depth
        k, parent, depth = parent, path[depth - 1], depth - 1


@kernel
def _insert(
    tree, n_nodes, elo, ehi, eref, level, overflow, tasks_lo, tasks_hi, tasks_ref, tasks_lev, n_tasks
):
    """RTree::insertData_impl of one entry at `level`; forced reinsertions are pushed on the task stack.
    Returns (node count, task count)."""
    nlo, nhi, lo, hi, ref, cnt, lev = tree
    path = np.empty(MAX_LEVELS, np.int64)
    depth, k = 0, 0
    while lev[k] != level:  # choose subtree
        path[depth] = k
        depth += 1
        c = (
            _least_overlap(lo, hi, cnt, k, elo, ehi)
            if lev[k] == 1
            else _least_enlargement(lo, hi, cnt, k, elo, ehi)
        )
        k = ref[k, c]
    cur_lo, cur_hi, cur_ref = elo.copy(), ehi.copy(), eref
    pending, pending_recompute = False, False  # inserting a split's new half into the parent
    while True:
        if cnt[k] < CAPACITY:
            inside = _contains(nlo[k], nhi[k], cur_lo, cur_hi)
            _append(nlo, nhi, lo, hi, ref, cnt, k, cur_lo, cur_hi, cur_ref)
            if not inside and depth > 0:
                _adjust(tree, k, path[depth - 1], path, depth - 1, False)
            elif pending and pending_recompute and depth > 0:
                _adjust(tree, k, path[depth - 1], path, depth - 1, False)
            return n_nodes, n_tasks
        _put(lo[k], hi[k], CAPACITY, cur_lo, cur_hi)
        ref[k, CAPACITY] = cur_ref
        if depth > 0 and overflow[lev[k]] == 0:  # forced reinsertion
            overflow[lev[k]] = 1
            dist = np.empty(CAPACITY + 1)
            c0, c1 = (nlo[k, 0] + nhi[k, 0]) / 2.0, (nlo[k, 1] + nhi[k, 1]) / 2.0
            for e in range(CAPACITY + 1):
                d0 = c0 - (lo[k, e, 0] + hi[k, e, 0]) / 2.0
                d1 = c1 - (lo[k, e, 1] + hi[k, e, 1]) / 2.0
                dist[e] = (0.0 + d0 * d0) + d1 * d1
            order = np.argsort(dist, kind="mergesort")
            keep = CAPACITY + 1 - REINSERTED
            old_lo, old_hi, old_ref = lo[k].copy(), hi[k].copy(), ref[k].copy()
            for i in range(keep):
                _put(lo[k], hi[k], i, old_lo[order[i]], old_hi[order[i]])
                ref[k, i] = old_ref[order[i]]
            cnt[k] = keep
            _refit(nlo, nhi, lo, hi, cnt, k)
            _adjust(tree, k, path[depth - 1], path, depth - 1, True)
            for i in range(CAPACITY, keep - 1, -1):  # pushed last first: inserted nearest first
                e = order[i]
                _put(tasks_lo, tasks_hi, n_tasks, old_lo[e], old_hi[e])
                tasks_ref[n_tasks], tasks_lev[n_tasks] = old_ref[e], lev[k]
                n_tasks += 1
            return n_nodes, n_tasks
        first, second = _split(lo[k], hi[k])
        old_lo, old_hi, old_ref = lo[k].copy(), hi[k].copy(), ref[k].copy()
        if depth == 0:  # the root splits: two new nodes under it
            a, b = n_nodes, n_nodes + 1
            n_nodes += 2
            lev[a], lev[b] = lev[k], lev[k]
            _fill(tree, a, first, old_lo, old_hi, old_ref)
            _fill(tree, b, second, old_lo, old_hi, old_ref)
            lev[k] += 1
            _fill(tree, k, first[:0], old_lo, old_hi, old_ref)
            _append(nlo, nhi, lo, hi, ref, cnt, k, nlo[a].copy(), nhi[a].copy(), a)
            _append(nlo, nhi, lo, hi, ref, cnt, k, nlo[b].copy(), nhi[b].copy(), b)
            return n_nodes, n_tasks
        b = n_nodes
        n_nodes += 1
        lev[b] = lev[k]
        _fill(tree, k, first, old_lo, old_hi, old_ref)
        _fill(tree, b, second, old_lo, old_hi, old_ref)
        parent = path[depth - 1]
        depth -= 1
        child = 0
        while ref[parent, child] != k:
            child += 1
        contained = _contains(nlo[parent], nhi[parent], nlo[k], nhi[k]) and _contains(
            nlo[parent], nhi[parent], nlo[b], nhi[b]
        )
        touching = _touches(nlo[parent], nhi[parent], lo[parent, child], hi[parent, child])
        pending_recompute = not contained or touching
        _put(lo[parent], hi[parent], child, nlo[k], nhi[k])
        if pending_recompute:
            _refit(nlo, nhi, lo, hi, cnt, parent)
        pending = True
        cur_lo, cur_hi, cur_ref = nlo[b].copy(), nhi[b].copy(), b
        k = parent


@kernel
def rtree_rank(x: np.ndarray, y: np.ndarray, half: float) -> np.ndarray:
    """Entry i is the box (x[i] - half, y[i] - half, x[i] + half, y[i] + half), inserted in order i = 0..n-1
    into an empty R*-tree: each entry's place in the order a range query lists it."""
    n = len(x)
    m = n // 30 + 8
    nlo, nhi = np.full((m, 2), BIG), np.full((m, 2), -BIG)
    lo, hi = np.empty((m, CAPACITY + 1, 2)), np.empty((m, CAPACITY + 1, 2))
    ref, cnt, lev = np.empty((m, CAPACITY + 1), np.int64), np.zeros(m, np.int64), np.zeros(m, np.int64)
    tree = (nlo, nhi, lo, hi, ref, cnt, lev)
    size = REINSERTED * MAX_LEVELS + 1
    tasks_lo, tasks_hi = np.empty((size, 2)), np.empty((size, 2))
    tasks_ref, tasks_lev = np.empty(size, np.int64), np.empty(size, np.int64)
    n_nodes = 1
    elo, ehi = np.empty(2), np.empty(2)
    for i in range(n):
        overflow = np.zeros(MAX_LEVELS, np.int64)
        elo[0], elo[1], ehi[0], ehi[1] = x[i] - half, y[i] - half, x[i] + half, y[i] + half
        n_nodes, n_tasks = _insert(tree, n_nodes, elo, ehi, i, 0, overflow,
                                   tasks_lo, tasks_hi, tasks_ref, tasks_lev, 0)  # fmt: skip
        while n_tasks:
            n_tasks -= 1
            n_nodes, n_tasks = _insert(tree, n_nodes, tasks_lo[n_tasks].copy(), tasks_hi[n_tasks].copy(),
                                       tasks_ref[n_tasks], tasks_lev[n_tasks], overflow,
                                       tasks_lo, tasks_hi, tasks_ref, tasks_lev, n_tasks)  # fmt: skip
    rank = np.empty(n, np.int64)
    stack = np.empty(m, np.int64)
    top, seen = 0, 0
    if cnt[0] > 0:
        stack[0], top = 0, 1
    while top:
        top -= 1
        k = stack[top]
        if lev[k] == 0:
            for e in range(cnt[k]):
                rank[ref[k, e]] = seen
                seen += 1
        else:
            for e in range(cnt[k]):
                stack[top] = ref[k, e]
                top += 1
    return rank


# ---------------------------------------------------------------------------------------------------
# CPython sets of (x, y) tuples

HASH_BITS = 61
HASH_MODULUS = (1 << HASH_BITS) - 1
XXPRIME_1 = np.uint64(11400714785074694791)
XXPRIME_2 = np.uint64(14029467366897019727)
XXPRIME_5 = np.uint64(2870177450012600261)
LINEAR_PROBES = 9
PERTURB_SHIFT = 5


@kernel
def _float_hash(v: float) -> np.uint64:
    """hash(v) of a finite float (equal to hash(int(v)) when v is whole), as an unsigned 64-bit word."""
    m, e = math.frexp(v)
    negative = m < 0
    if negative:
        m = -m
    x = np.uint64(0)
    modulus = np.uint64(HASH_MODULUS)
    while m:
        x = ((x << np.uint64(28)) & modulus) | (x >> np.uint64(HASH_BITS - 28))
        m *= 268435456.0
        e -= 28
        y = np.uint64(m)
        m -= y
        x += y
        if x >= modulus:
            x -= modulus
    e = e % HASH_BITS if e >= 0 else HASH_BITS - 1 - ((-1 - e) % HASH_BITS)
    x = ((x << np.uint64(e)) & modulus) | (x >> np.uint64(HASH_BITS - e))
    if negative:
        x = np.uint64(0) - x
    if x == np.uint64(0xFFFFFFFFFFFFFFFF):
        x = np.uint64(0xFFFFFFFFFFFFFFFE)
    return x


@kernel
def tuple_hash(x: float, y: float) -> np.uint64:
    """hash((x, y)) of two finite floats (or whole numbers), as an unsigned 64-bit word."""
    acc = XXPRIME_5
    for lane in (_float_hash(x), _float_hash(y)):
        acc += lane * XXPRIME_2
        acc = (acc << np.uint64(31)) | (acc >> np.uint64(33))
        acc *= XXPRIME_1
    acc += np.uint64(2) ^ (XXPRIME_5 ^ np.uint64(3527539))
    if acc == np.uint64(0xFFFFFFFFFFFFFFFF):
        return np.uint64(1546275796)
    return acc


@kernel
def _slot(table, size_mask, h):
    """set_insert_clean: the first empty slot on h's probe sequence."""
    mask = np.uint64(size_mask)
    perturb = h
    i = h & mask
    while True:
        if table[i] < 0:
            return np.int64(i)
        if i + np.uint64(LINEAR_PROBES) <= mask:
            for j in range(1, LINEAR_PROBES + 1):
                if table[i + np.uint64(j)] < 0:
                    return np.int64(i + np.uint64(j))
        perturb >>= np.uint64(PERTURB_SHIFT)
        i = (i * np.uint64(5) + np.uint64(1) + perturb) & mask


@kernel
def set_order(items, count, hashes, table, spare, out):
    """`list(s)` after s.add(item) for the first `count` items (distinct; hashes[item] their hashes): the
    items in table order, written to out. table and spare are work buffers of at least 8 * count + 8 slots.
    No item is ever removed, so a set's fill equals its used count."""
    mask = 7
    table[:8] = -1
    for k in range(count):
        table[_slot(table, mask, hashes[items[k]])] = items[k]
        used = k + 1
        if used * 5 < mask * 3:
            continue
        size = 8
        while size <= used * 4:  # sets under 50,000 items grow to four times their items
            size <<= 1
        spare[:size] = -1
        for i in range(mask + 1):
            if table[i] >= 0:
                spare[_slot(spare, size - 1, hashes[table[i]])] = table[i]
        table, spare, mask = spare, table, size - 1
    n = 0
    for i in range(mask + 1):
        if table[i] >= 0:
            out[n] = table[i]
            n += 1
    return n
