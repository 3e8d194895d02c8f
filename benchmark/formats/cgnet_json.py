"""CGNet's result JSON (`--format cgnet`): `pts_bbox/nuscmap_results.json` of XiaoMi/CGNet, one class,
centerline (type 0), each vector a piece whose linked endpoints CGNet's decoder already snapped to one
coordinate. Its graph is the one CGNet builds itself: points at exactly equal coordinates are one vertex
(`merge_equal_points`). The schema's reading is result_json.py's; docs/guide/score.md is the user's page.
"""

from __future__ import annotations

import numpy as np

from benchmark.formats import result_json
from benchmark.formats.base import GroundTruth, Options, PredictionFormat, Predictions, Source
from benchmark.metric.densify import identical_points
from pipeline.lane_graph import LaneGraph, graph_of_edges

# CGNet's config: its one class; the kept score of its decoder (configs/cgnet/cgnet_ep110.py,
# score_threshold, before it snaps and builds its graph)
CLASSES = ("centerline",)
MIN_SCORE = 0.3


def merge_equal_points(pieces: list[np.ndarray]) -> LaneGraph:
    """CGNet's graph of its snapped pieces: points at exactly equal coordinates are one vertex, each piece's
    consecutive points an edge; self-loops and repeated edges dropped."""
    return merge_equal_points_scored(pieces, None)[0]


def merge_equal_points_scored(pieces: list[np.ndarray], scores=None) -> tuple[LaneGraph, np.ndarray]:
    """(merge_equal_points' graph, each of its edges' score): the score of the piece it came from, the
    highest where pieces repeat it (`scores`: one per piece; None: every score 0.0)."""
    piece_score = np.zeros(len(pieces)) if scores is None else np.asarray(scores, np.float64)
    if piece_score.shape != (len(pieces),):
        raise ValueError(f"scores: one per piece ({len(pieces)}) is needed, not shape {piece_score.shape}")
    long = [i for i, p in enumerate(pieces) if len(p) >= 2]
    pieces, piece_score = [pieces[i] for i in long], piece_score[long]
    if not pieces:
        return LaneGraph.empty(), np.zeros(0)
    xy = np.concatenate(pieces) + 0.0  # no -0.0
    vertex, n = identical_points(xy)
    first = np.full(n, len(xy))
    np.minimum.at(first, vertex, np.arange(len(xy)))
    sizes = np.array([len(p) for p in pieces])
    is_last = np.zeros(len(xy), bool)
    is_last[np.cumsum(sizes) - 1] = True
    inner = ~is_last[:-1]
    src, dst = vertex[:-1][inner], vertex[1:][inner]
    edge_score = np.repeat(piece_score, sizes)[:-1][inner]
    return graph_of_edges(xy[first, 0], xy[first, 1], src, dst, edge_score)


CODEBASE = result_json.Codebase("cgnet", CLASSES, MIN_SCORE, merge_equal_points_scored)


def detect(source: Source) -> bool:
    """A result JSON whose every vector is a class-0 centerline (MapTRv2's centerline is class 3)."""
    kinds = result_json.vector_kinds(source)
    return bool(kinds) and kinds <= {("centerline", 0)}


def check(source: Source, options: Options) -> str | None:
    return result_json.check(CODEBASE, options)


def read(source: Source, options: Options, gt: GroundTruth) -> Predictions:
    return result_json.read(FORMAT, CODEBASE, source, options, gt)


FORMAT = PredictionFormat(
    name="cgnet", title="CGNet JSON", modeling="piece", external=True, detect=detect, check=check, read=read
)
