"""OpenLane-V2's lane confidences from the result files that carry scores: each output edge's score (the
highest of the vectors that produce it) from CGNet's merged pieces and MapTRv2's Path2Graph, against plain
slow readings; Path2Graph's graph unchanged by them; and `cli score --metric openlanev2` ranking by them."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from test_score_external import (
    MAPTRV2_CENTERLINE,
    frames_of,
    lines_of,
    to_source,
    token_of,
    vector,
    write_results,
)
from typer.testing import CliRunner

from benchmark.formats.cgnet_json import merge_equal_points, merge_equal_points_scored
from benchmark.graphs.path2graph import path2graph, path2graph_scored
from benchmark.metric.openlanev2 import SCORED
from benchmark.metric.params import EPS, MetricParams
from benchmark.metric.table import METRICS
from benchmark.score import score_frames
from cli import app
from pipeline.lane_graph import LaneGraph


def slow_piece_scores(pieces: list[np.ndarray], scores: list[float], graph: LaneGraph) -> dict:
    """{(src, dst): score} read plainly: each piece's consecutive points, their vertices the graph's vertex at
    the very same coordinates, a self-loop none, an edge the highest score of the pieces that give it."""
    vertex_at = {(x, y): v for v, (x, y) in enumerate(zip(graph.x.tolist(), graph.y.tolist()))}
    edges: dict = {}
    for piece, score in zip(pieces, scores):
        for a, b in zip(piece[:-1].tolist(), piece[1:].tolist()):
            u, v = vertex_at[(a[0] + 0.0, a[1] + 0.0)], vertex_at[(b[0] + 0.0, b[1] + 0.0)]
            if u != v:
                edges[(u, v)] = max(edges.get((u, v), -math.inf), score)
    return edges


def slow_path_scores(paths: list[np.ndarray], scores: list[float], graph: LaneGraph, step: float = 0.15,
                     exact: bool = True) -> dict:  # fmt: skip
    """{(src, dst): score} read plainly: each path's segments split into k = max(1, ceil(L / step - EPS))
    equal parts, each part's ends the graph's nearest vertices (the very same point when `exact`), an edge
    the highest score of the paths whose parts give it."""
    vertices = np.stack([graph.x, graph.y], axis=1)

    def nearest(point) -> int:
        distance = np.hypot(vertices[:, 0] - point[0], vertices[:, 1] - point[1])
        assert not exact or distance.min() < 1e-9
        return int(np.argmin(distance))

    edges: dict = {}
    for path, score in zip(paths, scores):
        for (ax, ay), (bx, by) in zip(path[:-1].tolist(), path[1:].tolist()):
            k = max(1, math.ceil(math.sqrt((bx - ax) ** 2 + (by - ay) ** 2) / step - EPS))
            ends = [(ax + (bx - ax) * (i / k), ay + (by - ay) * (i / k)) for i in range(k)] + [(bx, by)]
            for a, b in zip(ends[:-1], ends[1:]):
                u, v = nearest(a), nearest(b)
                if u != v:
                    edges[(u, v)] = max(edges.get((u, v), -math.inf), score)
    return edges


def as_dict(graph: LaneGraph, scores: np.ndarray) -> dict:
    assert scores.shape == graph.src.shape and scores.dtype == np.float64
    return {(int(u), int(v)): float(s) for u, v, s in zip(graph.src, graph.dst, scores)}


def same_graph(a: LaneGraph, b: LaneGraph) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f)) and getattr(a, f).dtype == getattr(b, f).dtype
               for f in ("x", "y", "src", "dst"))  # fmt: skip


# --- CGNet's pieces -------------------------------------------------------------------------------------


def test_piece_edges_take_their_vectors_score_and_the_highest_where_repeated():
    a = np.array([[0.0, 0.0], [0.0, 1.0], [0.0, 2.0]])
    b = np.array([[0.0, 1.0], [0.0, 2.0], [1.0, 3.0]])  # repeats a's edge (0, 1) -> (0, 2)
    c = np.array([[0.0, 2.0], [0.0, 2.0], [-1.0, 3.0]])  # a repeated point: a self-loop, dropped
    d = np.array([[5.0, 5.0]])  # one point: no edge
    scores = [0.4, 0.8, 0.6, 0.99]
    graph, edge_scores = merge_equal_points_scored([a, b, c, d], scores)
    assert same_graph(graph, merge_equal_points([a, b, c, d]))
    got = as_dict(graph, edge_scores)
    assert got == slow_piece_scores([a, b, c, d], scores, graph)
    xy = {(float(graph.x[u]), float(graph.y[u]), float(graph.x[v]), float(graph.y[v])): s
          for (u, v), s in got.items()}  # fmt: skip
    assert xy == {(0.0, 0.0, 0.0, 1.0): 0.4, (0.0, 1.0, 0.0, 2.0): 0.8, (0.0, 2.0, 1.0, 3.0): 0.8,
                  (0.0, 2.0, -1.0, 3.0): 0.6}  # fmt: skip
    # equal end points: two pieces meeting at one point share its vertex, each edge keeps its own score
    e, f = np.array([[0.0, 0.0], [1.0, 1.0]]), np.array([[1.0, 1.0], [2.0, 0.5]])
    graph, edge_scores = merge_equal_points_scored([e, f], [0.3, 0.7])
    assert len(graph.x) == 3 and as_dict(graph, edge_scores) == {(0, 1): 0.3, (1, 2): 0.7}
    empty, none = merge_equal_points_scored([d], [0.5])
    assert len(empty.x) == 0 and none.shape == (0,)


@pytest.mark.parametrize("seed", range(5))
def test_piece_scores_match_the_slow_reading_on_generated_pieces(seed):
    rng = np.random.default_rng(seed)
    pieces = [rng.integers(0, 4, (int(rng.integers(1, 6)), 2)).astype(np.float64) for _ in range(30)]
    pieces += [pieces[i].copy() for i in rng.integers(0, 30, 8)]  # whole pieces repeated
    scores = rng.random(len(pieces)).round(3).tolist()
    graph, edge_scores = merge_equal_points_scored(pieces, scores)
    assert same_graph(graph, merge_equal_points(pieces))
    assert as_dict(graph, edge_scores) == slow_piece_scores(pieces, scores, graph)
    assert len(graph.src) > 10


# --- MapTRv2's paths ------------------------------------------------------------------------------------


def test_a_shared_segment_of_two_paths_takes_the_higher_score():
    trunk = np.array([[0.0, 0.0], [0.0, 3.0]])
    left = np.array([[0.0, 0.0], [0.0, 3.0], [-2.0, 5.0]])  # shares the trunk, then turns left
    right = np.array([[0.0, 3.0], [2.0, 5.0]])
    scores = [0.5, 0.9, 0.7]
    graph, edge_scores = path2graph_scored([trunk, left, right], scores)
    assert same_graph(graph, path2graph([trunk, left, right]))
    got = as_dict(graph, edge_scores)
    assert got == slow_path_scores([trunk, left, right], scores, graph)
    on_trunk = [s for (u, v), s in got.items() if graph.x[u] == 0.0 and graph.x[v] == 0.0]
    assert len(on_trunk) == 20 and set(on_trunk) == {0.9}  # 3 m in 0.15 m parts, the higher of 0.5 and 0.9
    assert sorted(set(got.values())) == [0.7, 0.9]
    # the same paths, the other way round: the trunk's own score wins
    _, flipped = path2graph_scored([trunk, left, right], [0.95, 0.9, 0.7])
    assert sorted(set(flipped.tolist())) == [0.7, 0.9, 0.95]


def test_merged_vertices_take_the_higher_of_the_merged_paths():
    a = np.array([[0.0, 0.0], [0.0, 3.0]])
    b = a + [0.05, 0.0]  # merged into a's vertices (0.05 m apart, the same way)
    graph, edge_scores = path2graph_scored([a, b], [0.3, 0.6])
    assert same_graph(graph, path2graph([a, b])) and len(graph.x) == 21
    got = as_dict(graph, edge_scores)
    assert got == slow_path_scores([a, b], [0.3, 0.6], graph, exact=False)
    assert set(got.values()) == {0.6}
    apart, apart_scores = path2graph_scored([a, b], [0.3, 0.6], merge_radius=0.0)
    assert len(apart.x) == 42 and sorted(set(apart_scores.tolist())) == [0.3, 0.6]


def grid_paths(rng: np.random.Generator, count: int) -> list[np.ndarray]:
    """Monotone walks (right or up) on a 1 m grid from a few starts: they share segments, and pieces that
    share no vertex stay 1 m apart (nothing is merged)."""
    paths = []
    for _ in range(count):
        at = rng.integers(0, 2, 2).astype(np.float64)
        points = [at.copy()]
        for _ in range(int(rng.integers(1, 6))):
            at = at + ([1.0, 0.0] if rng.random() < 0.5 else [0.0, 1.0])
            points.append(at.copy())
        paths.append(np.array(points) * 1.3 - 2.0)
    return paths


@pytest.mark.parametrize("seed", range(4))
def test_path_scores_match_the_slow_reading_on_generated_paths(seed):
    rng = np.random.default_rng(seed)
    paths = grid_paths(rng, 12)
    scores = rng.random(len(paths)).round(3).tolist()
    graph, edge_scores = path2graph_scored(paths, scores)
    assert same_graph(graph, path2graph(paths))
    assert as_dict(graph, edge_scores) == slow_path_scores(paths, scores, graph)
    # free paths, no merging: every part's ends at their very points
    free = [rng.uniform(-10, 10, (int(rng.integers(2, 5)), 2)) for _ in range(6)]
    free.append(free[0][:2].copy())  # a path on another's first segment
    free_scores = rng.random(len(free)).tolist()
    graph, edge_scores = path2graph_scored(free, free_scores, merge_radius=0.0)
    assert same_graph(graph, path2graph(free, merge_radius=0.0))
    assert as_dict(graph, edge_scores) == slow_path_scores(free, free_scores, graph)


def test_path2graph_graph_is_the_same_with_and_without_scores():
    rng = np.random.default_rng(7)
    free = [rng.uniform(-5, 5, (4, 2)) for _ in range(5)]
    for paths in (grid_paths(rng, 10), free, [], [np.zeros((1, 2))]):
        plain = path2graph(paths)
        for scores in (None, rng.random(len(paths))):
            graph, edge_scores = path2graph_scored(paths, scores)
            assert same_graph(graph, plain) and edge_scores.shape == (len(plain.src),)
    with pytest.raises(ValueError, match="one per path"):
        path2graph_scored(grid_paths(rng, 3), [0.5])


# --- end to end -----------------------------------------------------------------------------------------


def scored_maptrv2_file(data, path, scores_of) -> tuple:
    """MapTRv2's file of the val frames: each ground-truth path a centerline scored by `scores_of(i)`, and
    a wrong centerline across the road scored high."""
    paths = lines_of(data, "paths")
    records, i = [], 0
    for frame in frames_of(data):
        vectors = []
        for p in paths[frame["frame_id"]]:
            vectors.append(vector(to_source(p, "nuscenes"), scores_of(i), MAPTRV2_CENTERLINE))
            i += 1
        wrong = to_source(np.array([[-14.0, 29.0], [14.0, -29.0]]), "nuscenes")
        vectors.append(vector(wrong, 0.95, MAPTRV2_CENTERLINE))
        records.append({"sample_token": token_of(frame), "vectors": vectors})
    return write_results(path, records)


def test_cli_openlanev2_ranks_lanes_by_the_files_scores(synth_prepared, tmp_path):
    data = synth_prepared["nuscenes"]
    rng = np.random.default_rng(3)
    distinct_scores = rng.uniform(0.45, 0.99, 1000)
    results = {}
    for name, scores_of in (("distinct", lambda i: float(distinct_scores[i])), ("equal", lambda i: 0.95)):
        path = scored_maptrv2_file(data, tmp_path / f"{name}.json", scores_of)
        out = tmp_path / f"{name}_scores.json"
        run = CliRunner().invoke(app, ["score", "--pred", str(path), "--gt", str(data), "--format", "maptrv2",
                                       "--metric", "openlanev2", "--out", str(out)])  # fmt: skip
        assert run.exit_code == 0, run.output
        results[name] = json.loads(out.read_text())["openlanev2"]
    assert results["distinct"]["confidences"] == SCORED == results["equal"]["confidences"]
    assert results["distinct"]["lanes"] == results["equal"]["lanes"]
    assert results["distinct"]["det_l"] != results["equal"]["det_l"]
    assert 0.0 < results["distinct"]["det_l"] <= 1.0


def test_score_frames_with_scores_in_two_workers_equals_one():
    rng = np.random.default_rng(11)
    pairs, scores = [], []
    for frame in range(12):
        gt_paths = grid_paths(rng, 5)
        pred_paths = [p + rng.normal(0, 0.2, p.shape) for p in gt_paths[:4]]
        pred, edge_scores = path2graph_scored(pred_paths, rng.random(len(pred_paths)))
        pairs.append((pred, path2graph(gt_paths)))
        scores.append(None if frame % 5 == 0 else edge_scores)
    metrics = METRICS
    one, one_counts = score_frames(pairs, MetricParams(), workers=1, metrics=metrics, pred_scores=scores)
    two, two_counts = score_frames(pairs, MetricParams(), workers=2, metrics=metrics, pred_scores=scores)
    assert one == two and np.array_equal(one_counts, two_counts)
    confidences = one["openlanev2"]["confidences"]
    assert confidences.startswith(SCORED) and "(9 of 12 frames)" in confidences  # frames 0, 5, 10: None
    unscored, _ = score_frames(pairs, MetricParams(), workers=1, metrics=metrics)
    assert unscored["openlanev2"]["det_l"] != one["openlanev2"]["det_l"]
    assert unscored["directed"] == one["directed"] and unscored["cgnet"] == one["cgnet"]  # OpenLane-V2's only
