"""TOPO / Junction TOPO / mIoU (docs/METRICS.md): hand-computed cases, properties, and agreement with
a straightforward networkx reading of the definition, which this file keeps as the reference."""

from __future__ import annotations

import math
from fractions import Fraction

import networkx as nx
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from benchmark.metric.candidates import candidate_pairs, near_pairs
from benchmark.metric.densify import densify, identical_points
from benchmark.metric.params import EPS, MetricParams
from benchmark.metric.totals import FractionSum, TopoCounts, frame_counts, score_graphs
from pipeline.lane_graph import LaneGraph

# ---------------------------------------------------------------------------------------------------
# The reference: the definition read literally, plain Python and networkx, slow.


def ref_dense(graph: LaneGraph, step: float, directed: bool):
    """(points, networkx graph with weights, junctions) of the densified graph."""
    xy = [(x + 0.0, y + 0.0) for x, y in zip(graph.x.tolist(), graph.y.tolist())]
    edges = sorted({(int(s), int(d)) for s, d in zip(graph.src, graph.dst) if s != d})
    if not directed:  # one undirected edge per pair, in the orientation that comes first
        seen: set = set()
        kept = []
        for u, v in edges:
            if (min(u, v), max(u, v)) not in seen:
                seen.add((min(u, v), max(u, v)))
                kept.append((u, v))
        edges = kept
    chains = [[xy[u]] for u in range(len(xy))]  # lone vertices are points too
    for u, v in edges:
        (ax, ay), (bx, by) = xy[u], xy[v]
        length = math.sqrt((bx - ax) * (bx - ax) + (by - ay) * (by - ay))
        k = max(1, math.ceil(length / step - EPS))
        inner = [(ax + (bx - ax) * (i / k), ay + (by - ay) * (i / k)) for i in range(1, k)]
        chains.append([xy[u], *inner, xy[v], length / k])
    # points at identical coordinates are one vertex, numbered by first appearance
    vertex: dict = {}
    for point in xy:
        vertex.setdefault(point, len(vertex))
    for chain in chains[len(xy) :]:
        for point in chain[1:-2]:
            vertex.setdefault(point, len(vertex))
    g = nx.DiGraph() if directed else nx.Graph()
    g.add_nodes_from(range(len(vertex)))
    for chain in chains[len(xy) :]:
        weight = chain[-1]
        for a, b in zip(chain[:-2], chain[1:-1]):
            s, d = vertex[a], vertex[b]
            if s != d and (not g.has_edge(s, d) or g[s][d]["weight"] > weight):
                g.add_edge(s, d, weight=weight)
    if directed:
        junctions = {v for v in g if g.in_degree(v) >= 2 or g.out_degree(v) >= 2}
    else:
        junctions = {v for v in g if g.degree(v) >= 3}
    return list(vertex), g, junctions


def ref_candidates(pa, pb, sa, sb, radius):
    out = []
    for a in sa:
        for b in sb:
            dx, dy = pa[a][0] - pb[b][0], pa[a][1] - pb[b][1]
            d = math.sqrt(dx * dx + dy * dy)
            if d < radius - EPS:
                out.append((d, a, b))
    return sorted(out)


def ref_greedy(pa, pb, sa, sb, radius):
    taken_a, taken_b, pairs = set(), set(), []
    for _, a, b in ref_candidates(pa, pb, sa, sb, radius):
        if a not in taken_a and b not in taken_b:
            taken_a.add(a)
            taken_b.add(b)
            pairs.append((a, b))
    return pairs


def ref_reach(g, v, radius):
    dist = nx.single_source_dijkstra_path_length(g, v, weight="weight")
    return [u for u, d in dist.items() if d < radius - EPS]


def ref_pair(pa, ga, pb, gb, p, g, params):
    """(m, |S_p|, |S_g|) of a pair."""
    s_p, s_g = ref_reach(ga, p, params.reach_radius), ref_reach(gb, g, params.reach_radius)
    return len(ref_greedy(pa, pb, s_p, s_g, params.match_radius)), len(s_p), len(s_g)


def fractions(counts, which):
    """sum of m / |S| over the pairs, which = 1: |S_p|, 2: |S_g|."""
    return FractionSum.of(
        np.array([c[0] for c in counts], np.int64), np.array([c[which] for c in counts], np.int64)
    )


def ref_counts(pred: LaneGraph, gt: LaneGraph, params: MetricParams) -> dict[str, TopoCounts]:
    out = {}
    for mode, directed in (("directed", True), ("undirected", False)):
        pa, ga, _ = ref_dense(pred, params.step, directed)
        pb, gb, junctions = ref_dense(gt, params.step, directed)
        pairs = ref_greedy(pa, pb, range(len(pa)), range(len(pb)), params.match_radius)
        scores = [ref_pair(pa, ga, pb, gb, p, g, params) for p, g in pairs]
        paired = {g: p for p, g in pairs}
        j_scores = []
        for j in sorted(junctions):
            near = ref_candidates(pa, pb, range(len(pa)), [j], params.match_radius)
            anchor = paired.get(j, near[0][1] if near else None)
            if anchor is not None:
                j_scores.append(ref_pair(pa, ga, pb, gb, anchor, j, params))
        out[mode] = TopoCounts(
            pre=fractions(scores, 1),
            rec=fractions(scores, 2),
            n_pred=len(pa),
            n_gt=len(pb),
            junction_pre=fractions(j_scores, 1),
            junction_rec=fractions(j_scores, 2),
            n_anchored=len(j_scores),
            n_junctions=len(junctions),
        )
    return out


# ---------------------------------------------------------------------------------------------------
# Graph builders


def graph(points, edges, dtype=np.float32) -> LaneGraph:
    xy = np.asarray(points, np.float64).reshape(-1, 2).astype(dtype)
    e = np.asarray(edges, np.int32).reshape(-1, 2)
    return LaneGraph(xy[:, 0], xy[:, 1], e[:, 0], e[:, 1])


def scores(pred: LaneGraph, gt: LaneGraph, **params) -> dict:
    return score_graphs([(pred, gt)], MetricParams(**params))


def assert_scores(result: dict, mode: str, metric: str, precision, recall) -> None:
    """Exact expected fractions; the tolerance only absorbs the final float rounding."""
    p, r = Fraction(precision), Fraction(recall)
    f1 = 2 * p * r / (p + r) if p + r else Fraction(0)
    expected = {"precision": float(p), "recall": float(r), "f1": float(f1)}
    assert result[mode][metric] == pytest.approx(expected, rel=1e-12, abs=1e-15)


LANE = graph([(0, 0), (0, 3)], [(0, 1)])  # 3 m straight up: 20 parts, 21 vertices
# a Y: a 3 m trunk up to (0, 3), then 3 m straight on to (0, 6) and 3.75 m right to (2.25, 6):
# 20 + 20 + 25 parts, 66 vertices (coordinates exact in float32, so the counts are too)
FORK = graph([(0, 0), (0, 3), (0, 6), (2.25, 6)], [(0, 1), (1, 2), (1, 3)])


# ---------------------------------------------------------------------------------------------------
# Hand-computed cases


def test_straight_lane_against_itself_is_perfect():
    long_lane = graph([(0, 0), (0, 9)], [(0, 1)])  # 60 parts: reach sets are cut at 7.5 m
    result = scores(long_lane, long_lane)
    for mode in ("directed", "undirected"):
        assert_scores(result, mode, "topo", 1, 1)
        assert_scores(result, mode, "junction_topo", 0, 0)  # no junction: 0 / 0 reads 0
    assert result["miou"] == 1.0


def test_half_lane():
    """Prediction: the first 1.5 m of the lane (11 vertices). Pair i (i = 0..10) sees the 11 - i
    predicted and 21 - i true vertices ahead (all under 7.5 m), 11 - i of them matched."""
    half = graph([(0, 0), (0, 1.5)], [(0, 1)])
    result = scores(half, LANE)
    recall = sum(Fraction(11 - i, 21 - i) for i in range(11)) / 21
    assert_scores(result, "directed", "topo", 1, recall)
    # undirected, every vertex reaches its whole lane
    assert_scores(result, "undirected", "topo", 1, Fraction(11 * 11, 21 * 21))


def test_fork_against_itself_is_perfect():
    result = scores(FORK, FORK)
    for mode in ("directed", "undirected"):
        assert_scores(result, mode, "topo", 1, 1)
        assert_scores(result, mode, "junction_topo", 1, 1)  # the fork vertex
    assert result["miou"] == 1.0


def test_fork_with_a_dropped_branch():
    """Prediction: trunk and straight branch only (41 of the 66 vertices, all matched exactly).
    Directed: a trunk pair j = 0..20 sees 41 - j predicted and 66 - j true vertices ahead; a branch
    pair sees the same vertices on both sides. Undirected: every vertex reaches all (<= 6.75 m)."""
    pred = graph([(0, 0), (0, 3), (0, 6)], [(0, 1), (1, 2)])
    result = scores(pred, FORK)
    recall = (sum(Fraction(41 - j, 66 - j) for j in range(21)) + 20) / 66
    assert_scores(result, "directed", "topo", 1, recall)
    assert_scores(result, "directed", "junction_topo", 1, Fraction(21, 46))
    assert_scores(result, "undirected", "topo", 1, Fraction(41 * 41, 66 * 66))
    assert_scores(result, "undirected", "junction_topo", 1, Fraction(41, 66))


def test_reversed_prediction_collapses_directed_scores_only():
    """Pair j sees predicted vertices 0..j and true vertices j..20; within 0.45 m of each other
    only (j, j) and (j - 1, j + 1) stay matched: m = 2, or 1 at either end."""
    reverse = graph([(0, 0), (0, 3)], [(1, 0)])
    result = scores(reverse, LANE)
    m = [1] + [2] * 19 + [1]
    precision = sum(Fraction(m[j], j + 1) for j in range(21)) / 21
    recall = sum(Fraction(m[j], 21 - j) for j in range(21)) / 21
    assert precision == recall < Fraction(3, 10)
    assert_scores(result, "directed", "topo", precision, recall)
    assert_scores(result, "undirected", "topo", 1, 1)
    assert result["miou"] == 1.0


def test_shifted_prediction():
    """0.3 m to the side: every vertex still pairs with its neighbour, TOPO stays 1. One raster column
    (0.15 m) to the side: the lane covers 6 columns (24, 24, 24, 24 and, exactly at the half width,
    20 and 20 cells), the shifted copy shares 112 of its 136 cells: IoU 112 / 160."""
    for mode in ("directed", "undirected"):
        assert_scores(scores(graph([(0.3, 0), (0.3, 3)], [(0, 1)]), LANE), mode, "topo", 1, 1)
    assert_scores(scores(graph([(0.5, 0), (0.5, 3)], [(0, 1)]), LANE), "directed", "topo", 0, 0)
    lane64 = graph([(0, 0), (0, 3)], [(0, 1)], np.float64)
    shifted = graph([(0.15, 0), (0.15, 3)], [(0, 1)], np.float64)
    assert scores(shifted, lane64)["miou"] == 112 / 160


def test_empty_prediction_and_empty_ground_truth():
    for pred, gt in (
        (LaneGraph.empty(), FORK),
        (FORK, LaneGraph.empty()),
        (LaneGraph.empty(), LaneGraph.empty()),
    ):
        result = scores(pred, gt)
        for mode in ("directed", "undirected"):
            for metric in ("topo", "junction_topo"):
                assert_scores(result, mode, metric, 0, 0)
        assert result["miou"] == 0.0


def test_junction_anchor_falls_back_to_the_nearest_predicted_vertex():
    """A fork J = (0, 0.3) with branches to A = (0.3, 0.3) and B = (0, 0.36); one predicted vertex
    p = (0, 0.35). p pairs with B (0.01 m), so J has no pair; its anchor is p, the nearest (0.05 m).
    Junction pair (p, J): S_p = {p}, S_J = {J, A, B}, m = 1. TOPO pair (p, B): 1 / 1 and 1 / 1."""
    gt = graph([(0, 0), (0, 0.3), (0.3, 0.3), (0, 0.36)], [(0, 1), (1, 2), (1, 3)])
    result = scores(graph([(0, 0.35)], []), gt, step=1.0)
    assert_scores(result, "directed", "junction_topo", 1, Fraction(1, 3))
    assert_scores(result, "directed", "topo", 1, Fraction(1, 4))
    # no predicted vertex within 0.45 m of J: the junction is unanchored
    far = scores(graph([(0, 0.8)], []), gt, step=1.0)
    assert_scores(far, "directed", "junction_topo", 0, 0)


def test_params_are_recorded_and_checked():
    result = scores(LANE, LANE, reach_radius=5.0)
    assert result["metric_params"]["reach_radius"] == 5.0
    assert set(result["metric_params"]) >= {"step", "match_radius", "reach_radius", "matching"}
    with pytest.raises(ValueError, match="matching"):
        MetricParams(matching="hungarian")
    with pytest.raises(ValueError, match="step"):
        MetricParams(step=0)


def test_optimal_matching_option():
    """True vertices at x = 0 and 0.4, predicted at 0.21 and 0.6. Greedy takes (0.21, 0.4) first
    (0.19 m); then (0.6, 0.4) and (0.21, 0) find an end taken: one pair. A maximum matching has two."""
    gt = graph([(0, 0), (0.4, 0)], [])
    pred = graph([(0.21, 0), (0.6, 0)], [])
    assert_scores(scores(pred, gt), "directed", "topo", Fraction(1, 2), Fraction(1, 2))
    optimal = scores(pred, gt, matching="optimal")
    assert_scores(optimal, "directed", "topo", 1, 1)
    assert optimal["metric_params"]["matching"] == "optimal"


# ---------------------------------------------------------------------------------------------------
# Properties


@st.composite
def random_graphs(draw, max_vertices: int = 7, grid: bool = True):
    """Vertices in a 3 m box, on a 5 cm grid (exact ties, exact multiples of the step) or, with
    grid=False, at distinct x and distinct y (ties left to chance); random edges, with repeats and
    self-loops."""
    n = draw(st.integers(0, max_vertices))
    if grid:
        coord = st.integers(-30, 30).map(lambda v: v * 0.05)
        points = [(draw(coord), draw(coord)) for _ in range(n)]
    else:
        coord = st.lists(st.integers(-15000, 15000), min_size=n, max_size=n, unique=True)
        points = [(x * 1.003e-4, y * 0.997e-4) for x, y in zip(draw(coord), draw(coord))]
    pairs = st.tuples(st.integers(0, n - 1), st.integers(0, n - 1))
    edges = draw(st.lists(pairs, max_size=2 * n)) if n else []
    return graph(points, edges)


def all_values(result: dict) -> list[float]:
    return [v for mode in ("directed", "undirected") for m in result[mode].values() for v in m.values()]


small = MetricParams(reach_radius=1.0)  # reach sets with borders inside a 3 m box


@settings(max_examples=200, deadline=None)
@given(random_graphs(), random_graphs())
def test_scores_are_between_0_and_1(pred, gt):
    result = score_graphs([(pred, gt)], small)
    assert all(0.0 <= v <= 1.0 for v in [*all_values(result), result["miou"]])


@settings(max_examples=200, deadline=None)
@given(random_graphs())
def test_a_graph_against_itself_scores_1(g):
    assume(len(g.x) > 0)
    result = score_graphs([(g, g)], small)
    has_junctions = frame_counts(g, g, small)
    for mode in ("directed", "undirected"):
        assert result[mode]["topo"] == {"precision": 1.0, "recall": 1.0, "f1": 1.0}
        expected = 1.0 if has_junctions[mode].n_junctions else 0.0
        assert set(result[mode]["junction_topo"].values()) == {expected}
    assert result["miou"] == 1.0


def tie_free(pred: LaneGraph, gt: LaneGraph) -> bool:
    """No two candidate pairs at the same distance: ties are broken by index, which permutes."""
    for mode in ("directed", "undirected"):
        dist = candidate_pairs(densify(pred, 0.15)[mode].xy, densify(gt, 0.15)[mode].xy, 0.45).dist
        if len(np.unique(dist)) < len(dist):
            return False
    return True


def permuted(g: LaneGraph, order: np.ndarray) -> LaneGraph:
    new = np.empty_like(order)
    new[order] = np.arange(len(order))
    return LaneGraph(
        g.x[order], g.y[order], new[g.src].astype(np.int32)[::-1], new[g.dst].astype(np.int32)[::-1]
    )


@settings(max_examples=100, deadline=None)
@given(random_graphs(grid=False), random_graphs(grid=False), st.randoms(use_true_random=False))
def test_invariant_to_vertex_and_edge_order(pred, gt, rnd):
    assume(tie_free(pred, gt))
    shuffled = [permuted(g, np.array(rnd.sample(range(len(g.x)), len(g.x)), np.int64)) for g in (pred, gt)]
    assert score_graphs([tuple(shuffled)], small) == score_graphs([(pred, gt)], small)


def with_long_edge(g: LaneGraph, a: tuple[float, float], b: tuple[float, float]) -> LaneGraph:
    """g plus two new vertices a, b and the edge a -> b."""
    n = len(g.x)
    x, y = np.append(g.x, [a[0], b[0]]).astype(np.float32), np.append(g.y, [a[1], b[1]]).astype(np.float32)
    return LaneGraph(x, y, np.append(g.src, n).astype(np.int32), np.append(g.dst, n + 1).astype(np.int32))


def split_last_edge(g: LaneGraph, at: int) -> LaneGraph:
    """The last edge u -> v cut in two at its at-th densification point (0 < at < k)."""
    u, v = int(g.src[-1]), int(g.dst[-1])
    a = np.array([g.x[u], g.y[u]], np.float64)
    b = np.array([g.x[v], g.y[v]], np.float64)
    k = max(1, math.ceil(math.sqrt(((b - a) ** 2).sum()) / 0.15 - EPS))
    w = a + (b - a) * (min(at, k - 1) / k)
    n = len(g.x)
    x, y = np.append(g.x.astype(np.float64), w[0]), np.append(g.y.astype(np.float64), w[1])
    src = np.concatenate([g.src[:-1], [u, n]]).astype(np.int32)
    dst = np.concatenate([g.dst[:-1], [n, v]]).astype(np.int32)
    return LaneGraph(x, y, src, dst)


point = st.tuples(st.floats(-1.5, 1.5), st.floats(-1.5, 1.5))


@settings(max_examples=100, deadline=None)
@given(random_graphs(grid=False), random_graphs(grid=False), point, point, st.integers(1, 100), st.booleans())
def test_invariant_to_splitting_an_edge_at_one_of_its_points(pred, gt, a, offset, at, in_pred):
    """Cutting u -> v at its j-th densification point densifies into the same points and weights
    (up to float rounding, far below every threshold)."""
    b = (a[0] + 0.5 + abs(offset[0]), a[1] + offset[1])  # >= 0.5 m: at least 4 parts
    if in_pred:
        pred = with_long_edge(pred, a, b)
    else:
        gt = with_long_edge(gt, a, b)
    assume(tie_free(pred, gt))
    before = score_graphs([(pred, gt)], small)
    after = score_graphs(
        [(split_last_edge(pred, at), gt) if in_pred else (pred, split_last_edge(gt, at))], small
    )
    assert after == before


# ---------------------------------------------------------------------------------------------------
# The fast implementation against the reference


@settings(max_examples=300, deadline=None)
@given(random_graphs(), random_graphs())
def test_fast_equals_reference_on_random_graphs(pred, gt):
    assert frame_counts(pred, gt, small) == ref_counts(pred, gt, small)


@settings(max_examples=100, deadline=None)
@given(random_graphs(), st.floats(-0.5, 0.5), st.floats(-0.5, 0.5))
def test_fast_equals_reference_on_noisy_copies(gt, dx, dy):
    pred = LaneGraph(gt.x + np.float32(dx), gt.y + np.float32(dy), gt.src[::-1], gt.dst[::-1])
    assert frame_counts(pred, gt, small) == ref_counts(pred, gt, small)


def window(g: LaneGraph, x_min, x_max, y_min, y_max) -> LaneGraph:
    """The vertices inside a box and the edges between them."""
    inside = (g.x >= x_min) & (g.x <= x_max) & (g.y >= y_min) & (g.y <= y_max)
    index = np.cumsum(inside) - 1
    keep = inside[g.src] & inside[g.dst]
    return LaneGraph(
        g.x[inside], g.y[inside], index[g.src[keep]].astype(np.int32), index[g.dst[keep]].astype(np.int32)
    )


def test_fast_equals_reference_on_real_av2_frames(prepared_av2):
    """Real ground truth against a noisy, thinned copy of itself, in a 20 x 25 m window (the
    reference needs tens of seconds per full frame), with the default parameters."""
    from benchmark.graph_table import graphs_from_table
    from pipeline.io import read_table

    graphs = graphs_from_table(read_table(prepared_av2, "graphs"), prepared_av2)
    rng = np.random.default_rng(0)
    frames = sorted(graphs)
    for frame_id in (frames[0], frames[-1]):  # one per log
        gt = window(graphs[frame_id], -10, 10, -5, 20)
        keep = rng.random(len(gt.src)) < 0.9
        noise = rng.normal(0, 0.15, (2, len(gt.x))).astype(np.float32)
        pred = LaneGraph(gt.x + noise[0], gt.y + noise[1], gt.src[keep], gt.dst[keep])
        assert densify(gt, 0.15)["directed"].n > 250
        assert frame_counts(pred, gt, MetricParams()) == ref_counts(pred, gt, MetricParams())


# ---------------------------------------------------------------------------------------------------
# The spatial kernels against brute force

coords = st.integers(-40, 40).map(lambda v: v * 0.05)  # exact ties and points on cell borders
point_sets = st.lists(st.tuples(coords, coords, st.integers(0, 2)), max_size=30)


@settings(max_examples=300, deadline=None)
@given(point_sets, point_sets, st.sampled_from([0.1, 0.15, 0.45, 1.0]), st.booleans())
def test_near_pairs_equal_brute_force(a, b, radius, self_join):
    b = list(a) if self_join else b  # a self-join takes a shortcut (Path2Graph's case)
    a_xy, b_xy = np.array([p[:2] for p in a]).reshape(-1, 2), np.array([p[:2] for p in b]).reshape(-1, 2)
    group_a, group_b = np.array([p[2] for p in a], np.int64), np.array([p[2] for p in b], np.int64)
    count, pair_b, dist = near_pairs(a_xy, b_xy, radius, EPS, group_a, group_b)
    pair_a = np.repeat(np.arange(len(a)), count)
    found = sorted(zip(pair_a.tolist(), pair_b.tolist(), dist.tolist()))
    expected = sorted(
        (i, j, math.dist(a_xy[i], b_xy[j]))
        for i in range(len(a))
        for j in range(len(b))
        if group_a[i] != group_b[j] and math.dist(a_xy[i], b_xy[j]) < radius - EPS
    )
    assert [f[:2] for f in found] == [e[:2] for e in expected]
    assert np.allclose([f[2] for f in found], [e[2] for e in expected], rtol=0, atol=1e-12)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 3), st.integers(0, 3)), max_size=40))
def test_identical_points_number_each_distinct_point_by_first_appearance(points):
    xy = np.array(points, np.float64).reshape(-1, 2) * 0.15
    vertex, n = identical_points(xy)
    first_seen = list(dict.fromkeys(points))
    assert n == len(first_seen)
    assert vertex.tolist() == [first_seen.index(p) for p in points]
