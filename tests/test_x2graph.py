"""Path2Graph, Piece2Graph, Pixel2Graph, and the ground truth's round trips through them."""

from __future__ import annotations

import networkx as nx
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from benchmark.graphs.path2graph import path2graph
from benchmark.graphs.piece2graph import piece2graph, suppress_duplicates
from benchmark.graphs.pixel2graph import pixel2graph
from benchmark.metric.densify import densify
from benchmark.metric.params import MetricParams
from benchmark.metric.totals import score_graphs
from benchmark.roundtrip import roundtrip
from pipeline.geometry import Range
from pipeline.lane_graph import LaneGraph
from pipeline.raster import Grid, rasterize

TRUNK = np.array([(0, 0), (0, 3)], np.float32)
FORK = LaneGraph(
    np.array([0, 0, 0, 2.25], np.float32),
    np.array([0, 3, 6, 6], np.float32),
    np.array([0, 1, 1], np.int32),
    np.array([1, 2, 3], np.int32),
)  # 3 m trunk, 3 m straight on, 3.75 m to the right: 66 densified vertices


def degrees(g: LaneGraph) -> tuple[np.ndarray, np.ndarray]:
    return np.bincount(g.src, minlength=len(g.x)), np.bincount(g.dst, minlength=len(g.x))


def same_points(a: np.ndarray, b: np.ndarray) -> bool:
    return np.array_equal(np.unique(a, axis=0), np.unique(b, axis=0))


# ---------------------------------------------------------------------------------------------------
# Path2Graph


def test_paths_sharing_a_trunk_rebuild_the_fork_exactly():
    paths = [np.array([(0, 0), (0, 3), (0, 6)]), np.array([(0, 0), (0, 3), (2.25, 6)])]
    for merge_radius in (0.0, 0.15):  # shared vertices are identical: nothing else to merge
        g = path2graph(paths, merge_radius=merge_radius)
        assert len(g.x) == 66 and len(g.src) == 65
        assert same_points(np.stack([g.x, g.y], 1), densify(FORK, 0.15)["directed"].xy)
        out_degree, _ = degrees(g)
        assert np.flatnonzero(out_degree == 2).tolist() == [int(np.flatnonzero((g.x == 0) & (g.y == 3))[0])]


def test_near_duplicate_paths_merge_into_one_chain_at_their_mean():
    g = path2graph([TRUNK, TRUNK + [0.05, 0]])
    assert len(g.x) == 21 and len(g.src) == 20
    np.testing.assert_allclose(g.x, 0.025)
    out_degree, in_degree = degrees(g)
    assert out_degree.max() == in_degree.max() == 1
    # with merge_radius 0 the two stay apart
    assert len(path2graph([TRUNK, TRUNK + [0.05, 0]], merge_radius=0.0).x) == 42


def test_noisy_fork_merges_its_trunk_and_splits_where_branches_part():
    paths = [np.array([(0, 0), (0, 3), (0, 6)]), np.array([(0.04, 0), (0.04, 3), (2.3, 6)])]
    g = path2graph(paths)
    out_degree, in_degree = degrees(g)
    assert (out_degree == 2).sum() == 1 and in_degree.max() == 1
    fork = np.flatnonzero(out_degree == 2)[0]
    assert 2.9 < g.y[fork] < 3.3


def test_crossing_lanes_do_not_merge_where_they_cross():
    # two paths of different pieces crossing at right angles: their vertices at the crossing are within
    # merge_radius, but they run different ways (a junction's crossing lanes never meet)
    across = np.array([(-3.0, 1.52), (3.0, 1.52)])  # 0.02 m from the trunk's vertex at y = 1.5
    g = path2graph([TRUNK, across])
    separate = path2graph([TRUNK, across], merge_radius=0.0)
    assert len(g.x) == len(separate.x) == 21 + 41 and len(g.src) == 20 + 40
    out_degree, in_degree = degrees(g)
    assert out_degree.max() == in_degree.max() == 1
    # the same two lanes nearly parallel (10 degrees apart) do merge where they are close
    assert len(path2graph([TRUNK, np.array([(0.05, 0.0), (0.05 + 3 * np.tan(np.radians(10)), 3.0)])]).x) < 42


def test_a_path_never_merges_with_itself_and_no_self_loops():
    u_turn = np.array([(0, 0), (0, 3), (0.1, 3), (0.1, 0)])  # its two sides 0.1 m apart
    g = path2graph([u_turn])
    d = np.diff(u_turn, axis=0)
    assert len(g.x) == 1 + sum(int(np.ceil(np.hypot(*s) / 0.15 - 1e-9)) for s in d)
    assert np.all(g.src != g.dst)
    assert len(path2graph([]).x) == 0
    one = path2graph([np.array([(1.0, 2.0)])])
    assert (len(one.x), len(one.src)) == (1, 0)


# ---------------------------------------------------------------------------------------------------
# Piece2Graph


def test_linked_pieces_join_at_the_mean_of_their_ends():
    pieces = [np.array([(0, 0), (0, 3)]), np.array([(0.1, 3), (0, 6)]), np.array([(-0.1, 3), (2, 6)])]
    g = piece2graph(pieces, np.array([(0, 1), (0, 2)]))
    assert len(g.x) == 4 and len(g.src) == 3
    joint = np.flatnonzero(np.bincount(g.src, minlength=4) == 2)[0]
    assert (g.x[joint], g.y[joint]) == pytest.approx((0, 3))


def test_piece_and_link_thresholds():
    pieces = [np.array([(0, 0), (0, 3)]), np.array([(0.1, 3), (0, 6)]), np.array([(-0.1, 3), (2, 6)])]
    links = np.array([(0, 1), (0, 2)])
    low_link = piece2graph(pieces, links, link_scores=np.array([0.9, 0.2]), link_threshold=0.5)
    assert len(low_link.x) == 5  # piece 2 keeps its own start
    low_piece = piece2graph(pieces, links, piece_scores=np.array([1.0, 1.0, 0.1]), piece_threshold=0.5)
    assert (len(low_piece.x), len(low_piece.src)) == (3, 2)
    assert len(piece2graph(pieces, links, piece_scores=np.zeros(3)).x) == 0


LANE = np.stack([np.zeros(21), np.linspace(-20.0, 20.0, 21)], 1)  # 40 m along y, a point every 2 m


def test_duplicates_either_way_round_give_way_to_the_higher_score():
    reversed_copy = LANE[::-1] + [0.5, 0]  # the same lane driven the wrong way, 0.5 m off
    next_lane = LANE + [3.5, 0]  # a lane width away
    tail = LANE[15:] - [1.0, 0]  # a quarter of the lane's length, lying on it
    pieces, scores = [tail, reversed_copy, LANE, next_lane], np.array([0.95, 0.8, 0.9, 0.7])
    assert suppress_duplicates(pieces, scores, 3.0, 0.5).tolist() == [0, 2, 3]
    # 7 of the lane's 21 points lie within 3 m of the tail: under the overlap, both stay
    assert suppress_duplicates([tail, LANE], np.array([0.95, 0.9]), 3.0, 0.5).tolist() == [0, 1]
    assert suppress_duplicates([tail, LANE], np.array([0.95, 0.9]), 3.0, 0.25).tolist() == [0]
    assert suppress_duplicates(pieces, scores, 4.0, 0.5).tolist() == [0, 2]  # the next lane too
    assert suppress_duplicates(pieces, scores, 0.0, 0.5).tolist() == [0, 1, 2, 3]  # off


def test_duplicate_suppression_edge_cases():
    assert suppress_duplicates([], np.zeros(0), 3.0, 0.5).tolist() == []
    assert suppress_duplicates([LANE, np.zeros((0, 2))], np.array([0.5, 0.9]), 3.0, 0.5).tolist() == [0]
    # equal scores: the first piece stays
    assert suppress_duplicates([LANE, LANE.copy()], np.array([0.5, 0.5]), 3.0, 0.5).tolist() == [0]


# ---------------------------------------------------------------------------------------------------
# Pixel2Graph


def raster(graph: LaneGraph) -> tuple[np.ndarray, np.ndarray]:
    return rasterize(graph, Grid(Range()))


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 399), st.integers(0, 199), st.sampled_from([0.15, 0.3, 0.6]))
def test_pixel_centres_are_where_to_pixels_puts_them(row, col, resolution):
    # one grid object places pixels both ways: Pixel2Graph's vertices, the rasters' drawing
    grid = Grid(Range(-15.0, 15.0, -30.0, 30.0), resolution)
    xy = grid.pixel_centres(np.array([row]), np.array([col]))
    np.testing.assert_allclose(grid.to_pixels(xy[:, 0], xy[:, 1]), [[col + 0.5, row + 0.5]], atol=1e-9)


def test_a_drawn_lane_comes_back_pointing_the_way_of_the_direction_map():
    lane = LaneGraph(
        np.array([0, 0], np.float32), np.array([-10, 10], np.float32), np.array([0]), np.array([1])
    )
    mask, direction = raster(lane)
    g = pixel2graph(mask, direction, Grid(Range()))
    dy = g.y[g.dst] - g.y[g.src]
    assert len(g.src) >= 1 and np.all(dy > 0)
    assert g.y.min() == pytest.approx(-10, abs=0.5) and g.y.max() == pytest.approx(10, abs=0.5)
    np.testing.assert_allclose(g.x, 0, atol=0.3)  # the thinning may end a pixel or two aside
    # the same mask with the direction map turned around
    flipped = np.where(direction > 0, (direction - 1 + 18) % 36 + 1, 0).astype(np.uint8)
    back = pixel2graph(mask, flipped, Grid(Range()))
    assert np.all(back.y[back.dst] < back.y[back.src])


def test_a_drawn_fork_comes_back_as_a_fork():
    mask, direction = raster(FORK)
    g = pixel2graph(mask, direction, Grid(Range()))
    out_degree, in_degree = degrees(g)
    assert (out_degree == 2).sum() == 1 and in_degree.max() == 1
    fork = np.flatnonzero(out_degree == 2)[0]
    assert np.hypot(g.x[fork], g.y[fork] - 3) < 1.5  # where the two 0.75 m wide strokes part
    result = score_graphs([(g, FORK)], MetricParams())
    assert result["directed"]["topo"]["f1"] > 0.8
    assert len(pixel2graph(np.zeros_like(mask), direction, Grid(Range())).x) == 0


def lanes(*polylines: np.ndarray) -> LaneGraph:
    """Each polyline a lane of its own (no shared vertices)."""
    xy = np.concatenate(polylines).astype(np.float32)
    starts = np.cumsum([0] + [len(p) for p in polylines])
    src = np.concatenate([np.arange(a, b - 1) for a, b in zip(starts[:-1], starts[1:])]).astype(np.int32)
    return LaneGraph(xy[:, 0], xy[:, 1], src, src + 1)


def reaches(g: LaneGraph, a, b) -> bool:
    """Whether the vertex nearest a leads to the vertex nearest b."""
    nearest = [int(np.argmin(np.hypot(g.x - p[0], g.y - p[1]))) for p in (a, b)]
    return nx.has_path(nx.DiGraph(list(zip(g.src.tolist(), g.dst.tolist()))), *nearest)


@settings(max_examples=25, deadline=None)
@given(
    angle=st.floats(60, 120),
    cx=st.floats(-3, 3),
    cy=st.floats(-10, 10),
)
def test_lanes_crossing_in_a_junction_do_not_join(angle, cx, cy):
    # one skeleton junction (or two joined by a short piece, at shallow angles) where they cross;
    # each lane goes on straight across it and never onto the other
    centre = np.array([cx, cy])
    along = 8 * np.array([np.cos(np.radians(angle)), np.sin(np.radians(angle))])
    a, b = np.array([centre - [8, 0], centre + [8, 0]]), np.array([centre - along, centre + along])
    g = pixel2graph(*raster(lanes(a, b)), Grid(Range()))
    assert reaches(g, a[0], a[1]) and reaches(g, b[0], b[1])
    assert not reaches(g, a[0], b[1]) and not reaches(g, b[0], a[1])


@settings(max_examples=25, deadline=None)
@given(x=st.floats(-5, 5), spread=st.floats(2, 5), below=st.floats(0.6, 1.2))
def test_lanes_forking_just_outside_the_grid_both_point_their_own_way(x, spread, below):
    # both lanes run up the grid from a fork below its edge; their lines touch on the edge, so the
    # skeleton makes one branch that goes down one lane and up the other
    fork = np.array([x, -30 - below])
    left = np.array([fork, fork + [-spread, 8], fork + [-spread, 28]])
    right = np.array([fork, fork + [spread, 8], fork + [spread, 28]])
    g = pixel2graph(*raster(lanes(left, right)), Grid(Range()))
    dy = g.y[g.dst] - g.y[g.src]
    assert np.hypot(g.x[g.dst] - g.x[g.src], dy).sum() > 2 * 25  # both lanes are there
    assert -dy[dy < 0].sum() < 0.5  # and no part of either points down


# ---------------------------------------------------------------------------------------------------
# Round trips of the prepared ground truth (Tab. 10)


def perfect(result: dict) -> bool:
    values = [v for mode in ("directed", "undirected") for m in result[mode].values() for v in m.values()]
    return values == [1.0] * 12 and result["miou"] == 1.0


def test_round_trips_on_real_av2(prepared_av2, tmp_path):
    """Every 8th of the 313 frames, to keep the test short (docs/METRICS.md has all of them)."""
    assert perfect(roundtrip(prepared_av2, "path", tmp_path / "path.json", frame_stride=8))
    assert perfect(roundtrip(prepared_av2, "piece", frame_stride=8))
    pixel = roundtrip(prepared_av2, "pixel", frame_stride=8)
    assert 0.5 < pixel["directed"]["topo"]["f1"] < 1 and 0.5 < pixel["miou"] < 1
    assert (tmp_path / "path.json").is_file()


def test_round_trips_on_synthetic_data(synth_prepared):
    for data in synth_prepared.values():  # AV2 and nuScenes formats, every 2nd frame
        assert perfect(roundtrip(data, "path", frame_stride=2))
        assert perfect(roundtrip(data, "piece", frame_stride=2))


def test_roundtrip_rejects_an_unknown_representation(prepared_av2):
    with pytest.raises(ValueError, match="via"):
        roundtrip(prepared_av2, "polygon")
