"""TOPO / Junction TOPO / mIoU (docs/METRICS.md): hand-computed cases, properties, and agreement with
a straightforward networkx reading of the definition, which this file keeps as the reference."""

from __future__ import annotations

import math

import networkx as nx
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from benchmark.metrics import EPS, FractionSum, MetricParams, TopoCounts, frame_counts
from pipeline.lane_graph import LaneGraph

# ---------------------------------------------------------------------------------------------------
# The reference: the definition read literally, plain Python and networkx, slow.


def ref_dense(graph: LaneGraph, step: float, directed: bool):
    """(points, networkx graph with weights, junctions) of the densified graph."""
    points = [(float(x), float(y)) for x, y in zip(graph.x, graph.y)]
    n = len(points)
    edges = sorted({(int(s), int(d)) for s, d in zip(graph.src, graph.dst) if s != d})
    if not directed:  # one undirected edge per pair, in the orientation that comes first
        seen: set = set()
        edges = [
            (u, v)
            for u, v in edges
            if not ((min(u, v), max(u, v)) in seen or seen.add((min(u, v), max(u, v))))
        ]
    g = nx.DiGraph() if directed else nx.Graph()
    g.add_nodes_from(range(n))
    for u, v in edges:
        (ax, ay), (bx, by) = points[u], points[v]
        length = math.sqrt((bx - ax) * (bx - ax) + (by - ay) * (by - ay))
        k = max(1, math.ceil(length / step - EPS))
        chain = [u]
        for i in range(1, k):
            points.append((ax + (bx - ax) * (i / k), ay + (by - ay) * (i / k)))
            g.add_node(len(points) - 1)
            chain.append(len(points) - 1)
        chain.append(v)
        for s, d in zip(chain, chain[1:]):
            g.add_edge(s, d, weight=length / k)
    if directed:
        junctions = {v for v in range(n) if g.in_degree(v) >= 2 or g.out_degree(v) >= 2}
    else:
        junctions = {v for v in range(n) if g.degree(v) >= 3}
    return points, g, junctions


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


def graph(points, edges) -> LaneGraph:
    xy = np.asarray(points, np.float64).reshape(-1, 2)
    e = np.asarray(edges, np.int64).reshape(-1, 2)
    return LaneGraph(
        xy[:, 0].astype(np.float32),
        xy[:, 1].astype(np.float32),
        e[:, 0].astype(np.int32),
        e[:, 1].astype(np.int32),
    )


@st.composite
def random_graphs(draw, max_vertices: int = 7):
    """Vertices on a 5 cm grid in a 3 m box (exact ties, exact multiples of the step), random edges."""
    n = draw(st.integers(0, max_vertices))
    coord = st.integers(-30, 30).map(lambda v: v * 0.05)
    points = [(draw(coord), draw(coord)) for _ in range(n)]
    edges = (
        draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)), max_size=2 * n)) if n else []
    )
    return graph(points, edges)


small = MetricParams(reach_radius=1.0)  # reach sets with borders inside a 3 m box


@settings(max_examples=300, deadline=None)
@given(random_graphs(), random_graphs())
def test_fast_equals_reference_on_random_graphs(pred, gt):
    assert frame_counts(pred, gt, small) == ref_counts(pred, gt, small)


@settings(max_examples=100, deadline=None)
@given(random_graphs(), st.floats(-0.5, 0.5), st.floats(-0.5, 0.5))
def test_fast_equals_reference_on_noisy_copies(gt, dx, dy):
    pred = LaneGraph(gt.x + np.float32(dx), gt.y + np.float32(dy), gt.src[::-1], gt.dst[::-1])
    assert frame_counts(pred, gt, small) == ref_counts(pred, gt, small)
