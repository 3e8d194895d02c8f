"""The query models' post-processing with their instance scores (issue 61: a submission's lane confidences):
`scored` gives the very graph of the plain post-processing (`to_graphs`) and each of its edges the highest
score of the model's paths (LaneGAP, path2graph_scored) or kept pieces (MapTR, STSU, piece2graph_scored)
that give it; HDMapNet's rasters have no instance score."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from baselines.config import tiny
from baselines.data import resample_polyline
from baselines.models import build, hdmapnet, lanegap, maptr, stsu
from benchmark.graphs.path2graph import path2graph_scored
from benchmark.graphs.piece2graph import piece2graph, piece2graph_scored
from pipeline.lane_graph import LaneGraph

torch.set_num_threads(1)

HEADS = {"lanegap": lanegap, "maptr": maptr, "stsu": stsu}


def small_config(model: str):
    """The tiny preset's head on a 6 x 12 m range (x -3..3, y -6..6) and the cheapest encoder."""
    config = tiny()
    config.model = model
    config.decoder = hdmapnet.HDMapNetConfig(width=8) if model == "hdmapnet" else HEADS[model].tiny_head()
    config.encoder.modality = "lidar"
    config.encoder.x_range, config.encoder.y_range = (-3.0, 3.0), (-6.0, 6.0)
    config.encoder.bev_h, config.encoder.bev_w = 8, 4
    return config


def unit_polyline(points: int, *xy: tuple[float, float]) -> np.ndarray:
    """A polyline in unit coordinates resampled to `points` points, as the data loader does."""
    return resample_polyline(np.array(xy, np.float64), points).astype(np.float32)


def edge_scores_by_position(graph: LaneGraph, scores: np.ndarray) -> dict[tuple[float, ...], float]:
    ends = zip(graph.x[graph.src], graph.y[graph.src], graph.x[graph.dst], graph.y[graph.dst], strict=True)
    return {tuple(map(float, end)): float(score) for end, score in zip(ends, scores, strict=True)}


def assert_same_graph(one: LaneGraph, other: LaneGraph) -> None:
    for name in ("x", "y", "src", "dst"):
        assert np.array_equal(getattr(one, name), getattr(other, name)), name


def test_piece2graph_scored_gives_each_edge_its_pieces_score():
    pieces = [
        np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]),
        np.array([[2.0, 0.0], [2.0, 1.0]]),  # linked from piece 0: its start joins piece 0's end
        np.array([[5.0, 5.0], [6.0, 5.0]]),
    ]
    links = np.array([[0, 1]])
    graph, scores = piece2graph_scored(pieces, links, np.array([0.3, 0.8, 0.6]), piece_threshold=0.0)
    assert_same_graph(graph, piece2graph(pieces, links))
    assert edge_scores_by_position(graph, scores) == {
        (0.0, 0.0, 1.0, 0.0): 0.3,
        (1.0, 0.0, 2.0, 0.0): 0.3,
        (2.0, 0.0, 2.0, 1.0): 0.8,
        (5.0, 5.0, 6.0, 5.0): 0.6,
    }
    # at the default threshold (0.5) piece 0 is dropped, with its link, as piece2graph drops it
    graph, scores = piece2graph_scored(pieces, links, np.array([0.3, 0.8, 0.6]))
    assert_same_graph(graph, piece2graph(pieces, links, np.array([0.3, 0.8, 0.6])))
    assert edge_scores_by_position(graph, scores) == {(2.0, 0.0, 2.0, 1.0): 0.8, (5.0, 5.0, 6.0, 5.0): 0.6}
    # without scores: every edge 0.0, as path2graph_scored; nothing kept: no edge
    assert np.array_equal(piece2graph_scored(pieces, links)[1], np.zeros(4))
    empty, none = piece2graph_scored([np.zeros((1, 2))], np.zeros((0, 2)))
    assert len(empty.src) == 0 and len(none) == 0


@pytest.mark.parametrize("model", ["maptr", "stsu"])
def test_piece_post_processing_scores_each_edge_by_its_kept_piece(model):
    config = small_config(model)
    config.decoder.score_threshold, config.decoder.link_threshold = 0.5, 0.5
    config.decoder.duplicate_radius = 0.5  # drops piece 0, the reversed copy of piece 1 0.3 m off
    n = config.decoder.piece_points
    lane = unit_polyline(n, (0.5, 0.95), (0.5, 0.5))
    successor = unit_polyline(n, (0.5, 0.5), (0.5, 0.05))
    pieces = np.stack([lane[::-1] + [0.05, 0], lane, successor, successor + [0.4, 0]])
    scores = torch.tensor([0.8, 0.9, 0.7, 0.2])  # 3: below the score threshold
    links = torch.full((4, 4), 0.1)
    links[1, 2] = links[0, 2] = links[2, 3] = 0.9
    outputs = {
        "logits": torch.logit(scores)[None, None],
        "points": torch.from_numpy(pieces)[None, None],
        "links": torch.logit(links)[None],
    }
    built = build(config)
    assert built.scored_graphs is not None
    [(graph, edge_scores)] = built.scored_graphs(outputs)
    assert_same_graph(graph, built.to_graphs(outputs)[0])
    kept = torch.logit(scores).sigmoid().numpy()[[1, 2]]  # the scores as the post-processing reads them
    metres = [config.encoder.polyline_to_metres(p.astype(np.float32)) for p in pieces[[1, 2]]]
    expected, expected_scores = piece2graph_scored(
        metres, [(0, 1)], kept.astype(np.float64), piece_threshold=0.0
    )
    assert_same_graph(graph, expected)
    assert np.array_equal(edge_scores, expected_scores)
    # the lane's edges take piece 1's score, the successor's piece 2's: n - 1 edges each
    assert sorted(edge_scores.tolist()) == [float(kept[1])] * (n - 1) + [float(kept[0])] * (n - 1)
    assert kept[0] == pytest.approx(0.9) and kept[1] == pytest.approx(0.7)


def test_lanegap_post_processing_scores_each_edge_by_its_best_path():
    config = small_config("lanegap")
    config.decoder.score_threshold, config.decoder.num_paths = 0.5, 3
    n = config.decoder.path_points
    straight = unit_polyline(n, (0.5, 0.95), (0.5, 0.05))  # metres: x 0, y -5.4 .. 5.4 (unit y runs down)
    turning = unit_polyline(n, (0.5, 0.95), (0.5, 0.5), (0.95, 0.5))  # shares the top half, then turns right
    below = unit_polyline(n, (0.1, 0.1), (0.2, 0.9))
    scores = torch.tensor([0.6, 0.9, 0.2])  # the turning path scores higher; the third is below the threshold
    outputs = {
        "logits": torch.logit(scores)[None, None],
        "points": torch.from_numpy(np.stack([straight, turning, below]))[None, None],
    }
    built = build(config)
    [(graph, edge_scores)] = built.scored_graphs(outputs)
    assert_same_graph(graph, built.to_graphs(outputs)[0])
    read = torch.logit(scores).sigmoid().numpy().astype(np.float64)
    metres = [config.encoder.polyline_to_metres(p) for p in (turning, straight)]  # best first, as selected
    expected, expected_scores = path2graph_scored(metres, read[[1, 0]])
    assert_same_graph(graph, expected)
    assert np.array_equal(edge_scores, expected_scores)
    assert set(edge_scores.tolist()) == {read[0], read[1]}
    x_src, x_dst, y_src = graph.x[graph.src], graph.x[graph.dst], graph.y[graph.src]
    assert np.all(edge_scores[(x_src > 0.5) & (x_dst > 0.5)] == read[1])  # the turn: the turning path's
    assert np.all(edge_scores[y_src > 0.5] == read[0])  # past the turn: the straight path's alone
    assert np.all(edge_scores[y_src < -0.5] == read[1])  # the shared half: the higher of the two


def test_hdmapnet_has_no_instance_score():
    assert build(small_config("hdmapnet")).scored_graphs is None
