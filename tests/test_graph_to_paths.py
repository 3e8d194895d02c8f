"""Graph2Piece and Graph2Path on random graphs, cycles included, and on hand-made cases."""

from __future__ import annotations

import networkx as nx
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.lane_graph import LaneGraph
from pipeline.paths import pieces_to_paths
from pipeline.pieces import graph_to_pieces


def make_graph(n: int, edges: list[tuple[int, int]]) -> LaneGraph:
    edges = sorted({(a, b) for a, b in edges if a != b})
    e = np.array(edges, np.int32).reshape(-1, 2)
    return LaneGraph(np.arange(n, dtype=np.float32), np.zeros(n, np.float32), e[:, 0], e[:, 1])


def enumerate_paths(graph: LaneGraph, max_paths: int = 10_000):
    pieces = graph_to_pieces(graph)
    return pieces, pieces_to_paths(pieces, len(graph.x), max_paths)


random_graph = st.integers(2, 12).flatmap(
    lambda n: st.tuples(
        st.just(n), st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)), max_size=24)
    )
)


@settings(max_examples=400, deadline=None)
@given(random_graph)
def test_paths_cover_every_edge_and_are_simple(case):
    n, edges = case
    graph = make_graph(n, edges)
    pieces, paths = enumerate_paths(graph)
    assert not paths.cap_hit
    edge_set = set(zip(graph.src.tolist(), graph.dst.tolist()))
    covered = set()
    for ids in paths.vertex_ids:
        ids = ids.tolist()
        assert len(set(ids)) == len(ids) or (ids[0] == ids[-1] and len(set(ids)) == len(ids) - 1)
        steps = set(zip(ids[:-1], ids[1:]))
        assert steps <= edge_set
        covered |= steps
    assert covered == edge_set
    # pieces partition the edges, and every root starts some path
    piece_edges = [e for c in pieces.chains for e in zip(c[:-1].tolist(), c[1:].tolist())]
    assert sorted(piece_edges) == sorted(edge_set)
    g = nx.DiGraph(list(edge_set))
    roots = {v for v in g if g.in_degree(v) == 0}
    assert roots <= {int(ids[0]) for ids in paths.vertex_ids}
    # deterministic
    again = enumerate_paths(graph)[1]
    assert [p.tolist() for p in again.vertex_ids] == [p.tolist() for p in paths.vertex_ids]


@settings(max_examples=200, deadline=None)
@given(random_graph)
def test_acyclic_paths_are_all_root_to_leaf_paths(case):
    """Without cycles, Graph2Path is exactly the set of all root-to-leaf simple paths."""
    n, edges = case
    graph = make_graph(n, [(min(a, b), max(a, b)) for a, b in edges])
    _, paths = enumerate_paths(graph)
    g = nx.DiGraph()
    g.add_edges_from(zip(graph.src.tolist(), graph.dst.tolist()))
    roots = [v for v in g if g.in_degree(v) == 0]
    leaves = [v for v in g if g.out_degree(v) == 0]
    expected = {tuple(p) for r in roots for p in nx.all_simple_paths(g, r, leaves)}
    assert {tuple(p.tolist()) for p in paths.vertex_ids} == expected


def test_roundabout_without_entries_keeps_every_edge():
    ring = [(i, (i + 1) % 8) for i in range(8)]
    pieces, paths = enumerate_paths(make_graph(8, ring))
    assert len(pieces.chains) == 1 and pieces.chains[0].tolist() == [0, 1, 2, 3, 4, 5, 6, 7, 0]
    assert [p.tolist() for p in paths.vertex_ids] == [[0, 1, 2, 3, 4, 5, 6, 7, 0]]


def test_roundabout_with_entry_and_exit():
    ring = [(i, (i + 1) % 8) for i in range(8)]
    graph = make_graph(10, ring + [(8, 2), (6, 9)])
    _, paths = enumerate_paths(graph)
    got = [p.tolist() for p in paths.vertex_ids]
    # root 8 enters at 2 and leaves at 6 (going on round the ring would revisit 2); the rest of the
    # ring, which no root-to-leaf path can take, gets a path of its own
    assert got == [[8, 2, 3, 4, 5, 6, 9], [6, 7, 0, 1, 2]]
    covered = {e for p in got for e in zip(p[:-1], p[1:])}
    assert covered == set(ring) | {(8, 2), (6, 9)}


def test_path_explosion_is_capped():
    # 24 diamonds in a row: 2**24 root-to-leaf paths
    edges = []
    for k in range(24):
        a, b, c, d = 3 * k, 3 * k + 1, 3 * k + 2, 3 * k + 3
        edges += [(a, b), (a, c), (b, d), (c, d)]
    _, paths = enumerate_paths(make_graph(3 * 24 + 1, edges), max_paths=256)
    assert paths.cap_hit and len(paths.vertex_ids) == 256


def test_fork_and_merge():
    fork = make_graph(4, [(0, 1), (1, 2), (1, 3)])
    pieces, paths = enumerate_paths(fork)
    assert [c.tolist() for c in pieces.chains] == [[0, 1], [1, 2], [1, 3]]
    assert list(zip(pieces.link_src.tolist(), pieces.link_dst.tolist())) == [(0, 1), (0, 2)]
    assert [p.tolist() for p in paths.vertex_ids] == [[0, 1, 2], [0, 1, 3]]
