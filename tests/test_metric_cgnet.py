"""CGNet's GEO / TOPO / JTOPO (benchmark/metric/cgnet.py): a plain, slow reading of its evaluator in this
file, against the numba module on hand-made and generated graphs, pair orders and ties included."""

from __future__ import annotations

import hashlib
import json
import math
import pickle
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest

from benchmark.graph_table import graphs_from_table, read_graph_table
from benchmark.metric.cgnet import _candidates, cgnet_frame, cgnet_result, interpolated, key_edges
from benchmark.metric.cgnet_order import rtree_rank, set_order, tuple_hash
from benchmark.metric.params import CGNET_VERSION, CGNetParams
from pipeline.lane_graph import LaneGraph

# ---------------------------------------------------------------------------------------------------
# The plain reading: the evaluator as CGNet's nuScenes dataset class calls it, in plain Python dicts,
# lists and sets, visiting everything in the same order. Positions are whole decimetres.

NAN = float("nan")


def plain_input(graph: LaneGraph, listed_order: bool = False) -> dict:
    """{key: [successor keys]}: each vertex keyed by its float32 coordinates times 10 in float64, truncated;
    the edges in (src, dst) order (networkx's order for CGNet's graphs, made from an adjacency matrix),
    repeats once. With `listed_order`, each vertex's edges in the order the graph lists them instead: what
    networkx gives when the edges are added one by one, which CGNet never does."""
    x32, y32 = graph.x.astype(np.float32).tolist(), graph.y.astype(np.float32).tolist()
    key = [(int(x * 10), int(y * 10)) for x, y in zip(x32, y32)]
    out: dict = {}
    edges = list(dict.fromkeys((int(s), int(d)) for s, d in zip(graph.src, graph.dst)))
    for s, d in sorted(edges, key=lambda e: e[0]) if listed_order else sorted(edges):
        successors = out.setdefault(key[s], [])
        if key[d] not in successors:
            successors.append(key[d])
    return out


def inside(point, p: CGNetParams) -> bool:
    x, y = point
    return -p.half_width <= x < p.half_width and -p.half_length <= y < p.half_length


def plain_interpolate(keyed: dict, p: CGNetParams) -> dict:
    """{node: [successors]}: each key edge cut into equal parts no longer than interp_dist (an edge whose
    reverse came first is skipped); a part with an end outside the box is left out."""
    out: dict = {}
    done: set = set()
    for a, successors in keyed.items():
        for b in successors:
            if (a, b) in done or (b, a) in done:
                continue
            done.add((a, b))
            (x1, y1), (x2, y2) = a, b
            parts = max(2, int(math.sqrt((x1 - x2) ** 2 + (y1 - y2) ** 2) / p.interp_dist) + 1)
            last = a
            for i in range(1, parts):
                w = 1.0 - float(i) / (parts - 1)
                point = (x1 * w + x2 * (1 - w), y1 * w + y2 * (1 - w))
                if inside(point, p) and inside(last, p):
                    successors_of_last = out.setdefault(last, [])
                    if point not in successors_of_last:
                        successors_of_last.append(point)
                    out.setdefault(point, [])
                last = point
    return out


def plain_reach(graph: dict, start, limit: float) -> list:
    """The depth-first walk: a stack of (node, depth); a node is marked when popped, expanded when its
    depth is below the limit, and pushes each successor not marked yet. The marked set as a list."""
    marked: set = set()
    stack = [(start, 0)]
    while stack:
        node, depth = stack.pop()
        marked.add(node)
        if depth >= limit:
            continue
        for nxt in graph[node]:
            if nxt not in marked:
                stack.append((nxt, depth + math.sqrt((node[0] - nxt[0]) ** 2 + (node[1] - nxt[1]) ** 2)))
    return list(marked)


def plain_pairs(outer: list, inner: list, radius: float) -> list:
    """(outer index, inner index, r) with r = (x_in - x_out) ** 2 + (y_in - y_out) ** 2 < radius ** 2: the
    outer nodes in order, each one's inner nodes in the order the R-tree over `inner` (its nodes inserted in
    order as squares of half-side 1) answers a query, which is cgnet_order.rtree_rank's order (pinned to
    the real library below); then stably by r."""
    tree = rtree_rank(np.array([x for x, _ in inner], float), np.array([y for _, y in inner], float), 1.0)
    cells: dict = {}
    for n, (x, y) in enumerate(inner):
        cells.setdefault((math.floor(x / radius), math.floor(y / radius)), []).append(n)
    pairs = []
    for i, (x, y) in enumerate(outer):
        cx, cy = math.floor(x / radius), math.floor(y / radius)
        near = [n for dx in (-1, 0, 1) for dy in (-1, 0, 1) for n in cells.get((cx + dx, cy + dy), [])]
        for n in sorted(near, key=lambda n: tree[n]):
            x2, y2 = inner[n]
            r = (x2 - x) ** 2 + (y2 - y) ** 2
            if r < radius * radius:
                pairs.append((i, n, r))
    return sorted(pairs, key=lambda pair: pair[2])


def plain_greedy(pairs: list, ties: dict | None = None, key: str = "") -> list:
    """The greedy matching; `ties` counts under `key` the pairs kept while a later pair of the same
    (first end, r) had a free second end too: pairs that the visiting order decided."""
    taken_a, taken_b, kept = set(), set(), []
    for k, (a, b, r) in enumerate(pairs):
        if a not in taken_a and b not in taken_b:
            taken_a.add(a)
            taken_b.add(b)
            kept.append((a, b))
            if ties is not None:
                rest = (b2 for a2, b2, r2 in pairs[k + 1 : k + 50] if a2 == a and r2 == r)
                ties[key] = ties.get(key, 0) + any(b2 not in taken_b for b2 in rest)
    return kept


def plain_window(pred: dict, gt: dict, p_node, g_node, p: CGNetParams, ties: dict | None = None):
    s_p = plain_reach(pred, p_node, p.prop_dist)
    s_g = plain_reach(gt, g_node, p.prop_dist)
    key = "large window" if len(s_p) > 100 else "window"
    m = len(plain_greedy(plain_pairs(s_g, s_p, p.radius), ties, key))
    return m / len(s_p), m / len(s_g)


def plain_f1(precision: float, recall: float) -> float:
    if precision == 0 or recall == 0:
        return 0.0
    return 2 * ((precision * recall) / (precision + recall))


def plain_mean(values: list) -> float:
    return float(np.mean(values)) if values else NAN


def plain_frame(
    pred: LaneGraph, gt: LaneGraph, p: CGNetParams | None = None, ties: dict | None = None, listed_order=False
):
    p = p or CGNetParams()
    pred_graph = plain_interpolate(plain_input(pred, listed_order), p)
    gt_graph = plain_interpolate(plain_input(gt, listed_order), p)
    pred_nodes, gt_nodes = list(pred_graph), list(gt_graph)
    if not pred_nodes:
        zero = {"precision": 0.0, "recall": 0.0, "f1": 0.0}
        return {"geo": dict(zero), "topo": dict(zero), "jtopo": dict(zero)}
    matched, ps, rs, jps, jrs = 0, [], [], [], []
    for a, b in plain_greedy(plain_pairs(pred_nodes, gt_nodes, p.radius), ties, "frame"):
        if len(gt_graph[gt_nodes[b]]) > 1:
            pre, rec = plain_window(pred_graph, gt_graph, pred_nodes[a], gt_nodes[b], p, ties)
            jps.append(pre)
            jrs.append(rec)
        if matched % p.topo_every == 0:
            pre, rec = plain_window(pred_graph, gt_graph, pred_nodes[a], gt_nodes[b], p, ties)
            ps.append(pre)
            rs.append(rec)
        matched += 1
    geo_p = matched / len(pred_nodes)
    geo_r = matched / len(gt_nodes) if gt_nodes else NAN
    out = {}
    for name, (pre, rec) in {"geo": (1.0, 1.0), "topo": (ps, rs), "jtopo": (jps, jrs)}.items():
        precision = geo_p if name == "geo" else geo_p * plain_mean(pre)
        recall = geo_r if name == "geo" else geo_r * plain_mean(rec)
        out[name] = {"precision": precision, "recall": recall, "f1": plain_f1(precision, recall)}
    return out


# ---------------------------------------------------------------------------------------------------
# Helpers

P = CGNetParams()


def graph(points, edges) -> LaneGraph:
    xy = np.asarray(points, np.float64).reshape(-1, 2).astype(np.float32)
    e = np.asarray(edges, np.int32).reshape(-1, 2)
    return LaneGraph(xy[:, 0], xy[:, 1], e[:, 0], e[:, 1])


def chain(points) -> LaneGraph:
    return graph(points, [(i, i + 1) for i in range(len(points) - 1)])


def assert_same(fast: dict, plain: dict) -> None:
    for name in ("geo", "topo", "jtopo"):
        for stat in ("precision", "recall", "f1"):
            a, b = fast[name][stat], plain[name][stat]
            assert (math.isnan(a) and math.isnan(b)) or abs(a - b) <= 1e-9, (name, stat, a, b)


def check(pred: LaneGraph, gt: LaneGraph, ties: dict | None = None) -> dict:
    fast = cgnet_frame(pred, gt, P)
    assert_same(fast, plain_frame(pred, gt, P, ties))
    return fast


LANE = chain([(0, -10), (0, 10)])  # 20 m straight ahead
# a Y: a 6 m trunk, then straight on and off to the right
FORK = graph([(0, 0), (0, 6), (0, 12), (3, 12)], [(0, 1), (1, 2), (1, 3)])
NAN3 = {"precision": math.nan, "recall": math.nan, "f1": math.nan}


def perturb(g: LaneGraph, rng, sigma: float, drop: float, shift=(0.0, 0.0)) -> LaneGraph:
    keep = rng.random(len(g.src)) >= drop
    x = (g.x + rng.normal(0, sigma, len(g.x)) + shift[0]).astype(np.float32)
    y = (g.y + rng.normal(0, sigma, len(g.y)) + shift[1]).astype(np.float32)
    return LaneGraph(x, y, g.src[keep], g.dst[keep])


# ---------------------------------------------------------------------------------------------------
# Hand-made frames


def test_a_graph_against_itself_scores_one():
    result = check(FORK, FORK)
    for name in ("geo", "topo", "jtopo"):
        assert result[name] == {"precision": 1.0, "recall": 1.0, "f1": 1.0}


def test_a_frame_with_no_true_junction_has_no_jtopo():
    result = check(LANE, LANE)
    assert result["geo"] == result["topo"] == {"precision": 1.0, "recall": 1.0, "f1": 1.0}
    assert all(math.isnan(v) for v in result["jtopo"].values())


def test_an_empty_prediction_scores_zero_even_on_an_empty_frame():
    zero = {"precision": 0.0, "recall": 0.0, "f1": 0.0}
    for gt in (FORK, LaneGraph.empty()):
        assert check(LaneGraph.empty(), gt) == {"geo": zero, "topo": zero, "jtopo": zero}
    # vertices without edges are no graph to the evaluator
    assert check(graph([(0, 0), (1, 1)], []), FORK) == {"geo": zero, "topo": zero, "jtopo": zero}


def test_an_empty_ground_truth_leaves_recall_undefined():
    """The evaluator divides by the true node count there (CGNet never feeds it an empty frame)."""
    result = check(FORK, LaneGraph.empty())
    assert result["geo"]["precision"] == 0.0 and result["geo"]["f1"] == 0.0
    assert math.isnan(result["geo"]["recall"])
    assert all(math.isnan(v) for v in (*result["topo"].values(), *result["jtopo"].values()))


def test_no_pair_within_the_radius():
    far = chain([(5, -10), (5, 10)])
    result = check(far, LANE)
    assert result["geo"] == {"precision": 0.0, "recall": 0.0, "f1": 0.0}
    assert all(math.isnan(v) for v in result["topo"].values())


def test_keys_are_float32_times_ten_in_float64_truncated():
    # float32(0.7) * 10 in float64 is 6.99999988: key 6, where float32 arithmetic would give 7
    a, b = key_edges(graph([(0.7, 0.7), (-0.05, -0.19), (0.2, 3.0)], [(0, 1), (1, 2)]), 10.0)
    assert a.tolist() == [[6, 6], [0, -1]] and b.tolist() == [[0, -1], [2, 30]]
    # vertices in one decimetre cell are one key: the edge between them is a self-loop, kept
    a, b = key_edges(graph([(0.01, 0.0), (0.05, 0.0), (0.01, 1.0)], [(0, 1), (1, 2)]), 10.0)
    assert a.tolist() == [[0, 0], [0, 0]] and b.tolist() == [[0, 0], [0, 10]]


def test_an_edge_whose_reverse_came_first_is_skipped():
    two_way = graph([(0, 0), (0, 5), (3, 5)], [(1, 0), (0, 1), (1, 2)])
    a, b = key_edges(two_way, 10.0)
    assert a.tolist() == [[0, 0], [0, 50]] and b.tolist() == [[0, 50], [30, 50]]
    check(two_way, FORK)
    check(FORK, two_way)


def test_parts_at_the_range_border():
    """Nodes are kept in [-150, 150) x [-300, 300) decimetres: a lane ending at x = 15 m loses its last part,
    one ending at x = -15 m keeps it; a part with an end outside is dropped, the rest of the lane stays."""
    right = chain([(14, 0), (15, 0)])  # 4 parts of 2.5 dm; the point at 150 is out
    left = chain([(-14, 0), (-15, 0)])
    across = chain([(0, 29), (0, 31)])  # 8 parts: nodes at 290 .. 297.5 stay, from 300 on out
    assert len(interpolated(right, P)[0]) == 4
    assert len(interpolated(left, P)[0]) == 5
    assert len(interpolated(across, P)[0]) == 4
    outside = chain([(20, 0), (30, 0)])
    assert len(interpolated(outside, P)[0]) == 0
    check(right, left)
    check(right, chain([(13, 0), (15, 0)]))
    check(across, chain([(0.1, 25), (0.1, 31)]))
    check(chain([(14, -31), (14, 31), (16, 31)]), chain([(14.2, -30), (14.2, 30)]))


def test_cycles_and_merges():
    loop = graph([(0, 0), (0, 4), (4, 4), (4, 0)], [(0, 1), (1, 2), (2, 3), (3, 0)])
    merge = graph([(-2, 0), (2, 0), (0, 4), (0, 10)], [(0, 2), (1, 2), (2, 3)])
    figure_eight = graph(
        [(0, 0), (0, 3), (3, 3), (3, 0), (0, -3), (-3, -3), (-3, 0)],
        [(0, 1), (1, 2), (2, 3), (3, 0), (0, 4), (4, 5), (5, 6), (6, 0)],
    )
    for pred in (loop, merge, figure_eight):
        for gt in (loop, merge, figure_eight, FORK):
            check(pred, gt)
    rng = np.random.default_rng(7)
    check(perturb(figure_eight, rng, 0.1, 0.0), figure_eight)


def lanes(dx: float = 0.0, split: bool = False) -> LaneGraph:
    """Five lanes 3 m apart, 24 m ahead, with lane changes every 4 m: reaches of over 100 nodes. With
    `split`, each lane between two changes runs as two paths 0.1 m either side of it."""
    xs, ys = (-6, -3, 0, 3, 6), (-12, -8, -4, 0, 4, 8, 12)
    points = [(x + dx, y) for y in ys for x in xs]
    edges = []
    for j in range(len(ys) - 1):
        for i in range(len(xs)):
            a = j * len(xs) + i
            edges += [(a, a + len(xs) + d) for d in (-1, 1) if 0 <= i + d < len(xs)]
            if not split:
                edges.append((a, a + len(xs)))
                continue
            for side in (-0.1, 0.1):
                points += [(xs[i] + dx + side, ys[j] + 0.5), (xs[i] + dx + side, ys[j] + 3.5)]
                edges += [(a, len(points) - 2), (len(points) - 2, len(points) - 1), (len(points) - 1, a + 5)]
    return graph(points, edges)


def test_ties_of_equal_distance_follow_the_evaluators_orders():
    """Lanes 1 dm from two true lanes, or true lanes 1 dm from two predicted paths: pairs of equal
    distance everywhere, and the visiting orders pick the winners."""
    ties: dict = {}
    one, two = lanes(0.1), lanes()
    two = LaneGraph(*(np.concatenate([u, v]) for u, v in zip(vars(two).values(), vars(lanes(0.2)).values())))
    two.src[len(two.src) // 2 :] += len(two.x) // 2
    two.dst[len(two.dst) // 2 :] += len(two.x) // 2
    result = check(one, two, ties)
    assert result["geo"] == {"precision": 1.0, "recall": 0.5, "f1": 2 / 3}
    assert ties.get("frame", 0) > 0  # pairs decided by the frame's R-tree order
    check(lanes(split=True), lanes(), ties)
    assert ties.get("large window", 0) > 0  # by the R-tree of a walk of over 100 nodes
    assert ties.get("window", 0) > 0  # by the order of a CPython set (a one-leaf R-tree)
    check(lanes(), lanes(split=True))


# ---------------------------------------------------------------------------------------------------
# The visiting orders against the real things

# (seed, count, kind) -> the first 16 hex digits of the sha256 of the order in which Rtree 1.0.1
# (libspatialindex 1.9.3, default properties) answers a query over all the squares, recorded with it.
RTREE_ORDERS = {
    (1, 99, "float"): "06af2b323658babc",
    (2, 101, "lattice"): "1b1d2ac5808c0942",
    (3, 700, "float"): "36b9ab496272c1ff",
    (4, 1500, "lattice"): "2cc612d870f6a989",
    (5, 3000, "lane"): "54152bff3cf3d554",
    (6, 8000, "lane"): "b9e9969cf7f989af",
}


def tree_points(seed: int, n: int, kind: str) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    if kind == "float":
        return rng.uniform(-150, 150, n), rng.uniform(-300, 300, n)
    if kind == "lattice":  # many equal coordinates: every sort meets ties
        return rng.integers(-40, 40, n) * 2.5, rng.integers(-80, 80, n) * 1.25
    turn = np.repeat(rng.uniform(0, 2 * np.pi, n // 40 + 1), 40)[:n] + np.cumsum(rng.normal(0, 0.05, n))
    return np.cumsum(2.5 * np.cos(turn)) % 300 - 150, np.cumsum(2.5 * np.sin(turn)) % 600 - 300


@pytest.mark.parametrize("case", sorted(RTREE_ORDERS))
def test_rtree_order_is_libspatialindexs(case):
    x, y = tree_points(*case)
    order = np.argsort(rtree_rank(x, y, 1.0)).astype(np.int64)
    assert hashlib.sha256(order.tobytes()).hexdigest()[:16] == RTREE_ORDERS[case]
    if case[1] <= 100:  # one leaf: the insertion order
        assert order.tolist() == list(range(case[1]))


def test_set_order_is_cpythons():
    rng = np.random.default_rng(3)
    for n in (1, 5, 6, 21, 100, 700):
        points = list(dict.fromkeys(
            (float(x) * 0.25 - 1, float(y) * 0.125)
            for x, y in zip(rng.integers(-600, 600, n), rng.integers(-2400, 2400, n))
        ))  # fmt: skip
        points += [(0, 0), (-1, -1), (-2.0, 5), (0.1, 0.2)]
        hashes = np.array([tuple_hash(float(x), float(y)) for x, y in points], np.uint64)
        assert hashes.tolist() == [hash(p) % 2**64 for p in points]
        added = rng.permutation(len(points)).astype(np.int64)
        real = set()
        for i in added:
            real.add(points[i])
        out = np.empty(len(points), np.int64)
        work = 8 * len(points) + 8
        count = set_order(added, len(points), hashes, np.empty(work, np.int64), np.empty(work, np.int64), out)
        assert [points[i] for i in out[:count]] == list(real)


def test_squared_distances_are_pythons_pow():
    """`d ** 2` on a Python float is libm's pow, which differs from d * d in about 1 case in 1,000."""
    rng = np.random.default_rng(5)
    px, py = rng.uniform(-20, 20, 300), rng.uniform(-20, 20, 300)
    gx, gy = px + rng.uniform(-5, 5, 300), py + rng.uniform(-5, 5, 300)
    a, b, r = _candidates(px, py, gx, gy, 5.0, 2.0)
    expected = sorted(
        ((gx[j] - px[i]) ** 2 + (gy[j] - py[i]) ** 2, i, j)
        for i in range(300) for j in range(300)
        if (gx[j] - px[i]) ** 2 + (gy[j] - py[i]) ** 2 < 25
    )  # fmt: skip
    assert list(zip(r.tolist(), a.tolist(), b.tolist())) == expected
    differences = (gx[None, :] - px[:, None]).ravel().tolist()
    assert any(d**2 != d * d for d in differences)  # the case this guards against occurs here


# ---------------------------------------------------------------------------------------------------
# Generated frames: synthetic worlds prepared by `cli prepare`, and perturbed predictions


def reverse(g: LaneGraph, rng, share: float) -> LaneGraph:
    """A share of the edges turned round, each where the graph lists it (so no longer in (src, dst) order)."""
    flip = rng.random(len(g.src)) < share
    return LaneGraph(g.x, g.y, np.where(flip, g.dst, g.src), np.where(flip, g.src, g.dst))


def with_false_lanes(g: LaneGraph, rng, count: int = 3) -> LaneGraph:
    """The graph and `count` false lanes of eight vertices 2 m apart, anywhere in the 30 x 60 m range."""
    parts = [(g.x, g.y, g.src, g.dst)]
    n = len(g.x)
    for _ in range(count):
        start, heading = rng.uniform((-15, -30), (15, 30)), rng.uniform(0, 2 * np.pi)
        turn = heading + np.cumsum(rng.normal(0, 0.1, 8))
        xy = (start + np.cumsum(2.0 * np.stack([np.cos(turn), np.sin(turn)], 1), 0)).astype(np.float32)
        src = np.arange(n, n + 7, dtype=np.int32)
        parts.append((xy[:, 0], xy[:, 1], src, src + 1))
        n += 8
    return LaneGraph(*(np.concatenate(column) for column in zip(*parts)))


KINDS = ("itself", "noise", "dropped edges", "reversed edges", "shifted", "false lanes", "empty")


def prediction(gt: LaneGraph, rng, kind: str) -> LaneGraph:
    """A kind of prediction of a frame: the ground truth itself, 0.1 m noise on every vertex, 20 % of the
    edges dropped, 30 % reversed, an exact shift, three false lanes added, or nothing."""
    return {
        "itself": lambda: gt,
        "noise": lambda: perturb(gt, rng, 0.1, 0.0),
        "dropped edges": lambda: perturb(gt, rng, 0.0, 0.2),
        "reversed edges": lambda: reverse(gt, rng, 0.3),
        "shifted": lambda: perturb(gt, rng, 0.0, 0.0, shift=(0.125, -0.2)),
        "false lanes": lambda: with_false_lanes(gt, rng),
        "empty": LaneGraph.empty,
    }[kind]()


def match_plain_reading(path, per_kind: int, seed: int) -> dict:
    """`per_kind` frames drawn for each kind of prediction, each scored by both readings."""
    rng = np.random.default_rng(seed)
    graphs = graphs_from_table(read_graph_table(path), path)
    ties: dict = {}
    frames = rng.choice(sorted(graphs), per_kind * len(KINDS), replace=False)
    for k, frame in enumerate(frames):
        check(prediction(graphs[frame], rng, KINDS[k % len(KINDS)]), graphs[frame], ties)
    return ties


def test_prepared_frames_match_the_plain_reading(synth_prepared):
    for name in ("av2", "nuscenes"):
        ties = match_plain_reading(synth_prepared[name], 2, 53)
        assert ties.get("frame", 0) > 0 and ties.get("window", 0) > 0


def test_real_av2_frames_match_the_plain_reading(prepared_av2):
    match_plain_reading(prepared_av2, 3, 54)


def test_the_order_a_prediction_lists_its_edges_in_changes_nothing(prepared_av2):
    """CGNet builds every graph as nx.DiGraph(adjacency), so its evaluator meets each vertex's edges in
    (src, dst) order. Fed the edges one by one in a reversed prediction's own order, the same evaluator picks
    other pairs for TOPO (its dicts' orders change the pairs' order, hence which tenth is scored): the score
    follows the adjacency's order, whatever order the prediction lists its edges in."""
    rng = np.random.default_rng(59)
    graphs = graphs_from_table(read_graph_table(prepared_av2), prepared_av2)
    differ = 0
    for frame in sorted(graphs)[::40]:
        gt = graphs[frame]
        pred = reverse(gt, rng, 0.3)
        shuffled = rng.permutation(len(pred.src))
        again = cgnet_frame(LaneGraph(pred.x, pred.y, pred.src[shuffled], pred.dst[shuffled]), gt, P)
        assert_same(again, check(pred, gt))
        listed = plain_frame(pred, gt, P, listed_order=True)
        assert_same({**again, "topo": listed["topo"]}, listed)  # GEO and JTOPO: the same pairs
        differ += abs(listed["topo"]["precision"] - again["topo"]["precision"]) > 1e-6
    assert differ >= 4  # of the 8 frames: the order is the one that matters, and it is the adjacency's


# ---------------------------------------------------------------------------------------------------
# Averages and the result


def test_result_averages_each_number_with_nan_skipped():
    frames = [
        {"geo": {"precision": 1.0, "recall": 0.5, "f1": 2 / 3}, "topo": dict(NAN3), "jtopo": dict(NAN3)},
        {"geo": {"precision": 0.5, "recall": 0.5, "f1": 0.5}, "topo": {"precision": 0.25, "recall": 1.0,
         "f1": 0.4}, "jtopo": dict(NAN3)},
        {"geo": {"precision": 0.0, "recall": math.nan, "f1": 0.0}, "topo": dict(NAN3), "jtopo": dict(NAN3)},
    ]  # fmt: skip
    result = cgnet_result(frames)
    assert result["geo"] == {"precision": 0.5, "recall": 0.5, "f1": (2 / 3 + 0.5 + 0.0) / 3}
    assert result["topo"] == {"precision": 0.25, "recall": 1.0, "f1": 0.4}  # F1: the frames' mean
    assert result["jtopo"] == {"precision": None, "recall": None, "f1": None}
    assert result["frames"] == 3 and result["version"] == CGNET_VERSION
    assert result["params"] == P.to_dict() == {
        "radius": 5.0, "interp_dist": 2.5, "prop_dist": 80.0, "scale": 10.0, "half_width": 150.0,
        "half_length": 300.0, "topo_every": 10, "box": 1.0,
    }  # fmt: skip
    json.dumps(result, allow_nan=False)


def test_frames_are_scored_in_worker_processes():
    rng = np.random.default_rng(11)
    pairs = [(perturb(FORK, rng, 0.2, 0.0), FORK), (LANE, FORK), (LaneGraph.empty(), LANE)]
    here = [cgnet_frame(pred, gt, P) for pred, gt in pairs]
    assert pickle.loads(pickle.dumps(here)) == here
    with ProcessPoolExecutor(1) as pool:
        there = list(pool.map(cgnet_frame, *zip(*pairs), [P] * len(pairs)))
    for a, b in zip(here, there):
        assert_same(a, b)
    result = cgnet_result(there)
    assert result["geo"]["precision"] == np.mean([f["geo"]["precision"] for f in here])
