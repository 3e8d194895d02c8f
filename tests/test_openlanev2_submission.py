"""OpenLane-V2 submissions (`cli score --format openlanev2`, benchmark/formats/openlanev2_submission.py): the
restricted unpickler against hostile pickles and with real numpy arrays, the JSON form, the matching of the
submission's keys to the prepared frames, the round trip of write_submission; and the graph of a frame's
predicted lanes with each edge's score from its lane's confidence."""

from __future__ import annotations

import numpy as np

from pipeline.geometry import Range
from pipeline.lane_graph import graph_of_annotated, scored_graph_of_annotated
from pipeline.records import AnnotatedLanes


def lanes(points: list, links=None, confidence=None, ids=None) -> AnnotatedLanes:
    arrays = [np.asarray(p, np.float64) for p in points]
    links = np.zeros((len(arrays), len(arrays))) if links is None else np.asarray(links, np.float64)
    ids = ids if ids is not None else [str(i) for i in range(len(arrays))]
    conf = None if confidence is None else np.asarray(confidence, np.float64)
    return AnnotatedLanes(arrays, links, ids, conf)


def test_each_edge_of_a_predicted_graph_scores_its_lanes_highest_confidence():
    # ego frame: x forward, y left; the BEV graph has x right (= -y), y forward (= x)
    trunk = [[0, 0, 0], [10, 0, 0], [20, 0, 0]]
    twin = [[10, 0, 0], [20, 0, 0]]  # lies on the trunk's second edge
    branch = [[20, 0, 0], [30, -5, 0]]  # linked after the trunk: a fork at (20, 0)
    links = [[0, 0, 0.9], [0, 0, 0], [0, 0, 0]]
    predicted = lanes([trunk, twin, branch], links, [0.3, 0.8, 0.6])
    graph, scores = scored_graph_of_annotated(predicted, Range.parse("50x100"))
    xy = graph.xy
    by_edge = {(tuple(xy[s]), tuple(xy[d])): score for s, d, score in zip(graph.src, graph.dst, scores)}
    assert by_edge == {((0.0, 0.0), (0.0, 10.0)): 0.3, ((0.0, 10.0), (0.0, 20.0)): 0.8,
                       ((0.0, 20.0), (5.0, 30.0)): 0.6}  # fmt: skip
    unscored = graph_of_annotated(predicted, Range.parse("50x100"))
    assert all(np.array_equal(getattr(graph, f), getattr(unscored, f)) for f in ("x", "y", "src", "dst"))
    # clipped to 15 m ahead: the branch leaves the range with its score; the trunk and its twin, cut at the
    # border at the same point, share their last edge, which keeps the higher score
    short, short_scores = scored_graph_of_annotated(predicted, Range.parse("50x30"))
    xy = short.xy
    by_edge = {(tuple(xy[s]), tuple(xy[d])): score for s, d, score in zip(short.src, short.dst, short_scores)}
    assert by_edge == {((0.0, 0.0), (0.0, 10.0)): 0.3, ((0.0, 10.0), (0.0, 15.0)): 0.8}
    # annotated lanes have no confidence: no scores; no lanes: no edges
    assert scored_graph_of_annotated(lanes([trunk]))[1] is None
    empty, empty_scores = scored_graph_of_annotated(lanes([], confidence=[]))
    assert len(empty.src) == 0 and empty_scores.shape == (0,)
