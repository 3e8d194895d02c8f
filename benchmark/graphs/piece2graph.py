"""Piece2Graph (STSU / CGNet style): pieces and the links between them back to one lane graph.

1. Pieces scoring below piece_threshold are dropped, and so are links scoring below link_threshold
   or touching a dropped piece.
2. Each piece becomes a chain of its points.
3. A link i -> j joins the end of i to the start of j. The endpoints that links join, directly or
   through other links (the end of i with the starts of all its successors, and so on), become one
   vertex at their mean: the joint moves to the mean, as STSU and CGNet do.
4. Self-loops and repeated edges are dropped.
On ground-truth pieces, linked endpoints are the same vertex, so the graph comes back exactly.

`suppress_duplicates` is an optional step before it for predicted pieces (not STSU's): a piece that
mostly lies on a higher-scoring one, either way round, is dropped, as detectors' non-maximum suppression.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial.distance import cdist

from pipeline.lane_graph import LaneGraph, graph_of_edges


def suppress_duplicates(
    pieces: Sequence[np.ndarray], scores: np.ndarray, radius: float, overlap: float
) -> np.ndarray:
    """pieces: (n_i, 2) polylines in metres, scores (P,) -> the sorted indices of the pieces kept.

    Greedy in decreasing score: a piece is dropped when at least `overlap` of its points lie within
    `radius` of a kept piece's points. Direction is ignored: of the copies that a short training leaves
    on one lane, about half drive it the wrong way (docs/EXPERIMENTS.md, 2026-12-04). radius 0 keeps
    every piece; a piece without points is dropped."""
    if radius <= 0:
        return np.arange(len(pieces))
    candidates = np.array([i for i, piece in enumerate(pieces) if len(piece)], np.int64)
    if len(candidates) == 0:
        return candidates
    chains = [np.asarray(pieces[i], np.float64).reshape(-1, 2) for i in candidates]
    sizes = np.array([len(chain) for chain in chains])
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    points = np.concatenate(chains)
    # near[i, b]: point i lies within radius of piece b; share[a, b]: the fraction of a's points that do
    near = np.minimum.reduceat(cdist(points, points), starts, axis=1) <= radius
    share = np.add.reduceat(near, starts, axis=0) / sizes[:, None]
    kept: list[int] = []
    for piece in np.argsort(-np.asarray(scores, np.float64)[candidates], kind="stable"):
        if not kept or share[piece, kept].max() < overlap:
            kept.append(int(piece))
    return candidates[np.sort(kept)]


def piece2graph(
    pieces: Sequence[np.ndarray],
    links: np.ndarray,
    piece_scores: np.ndarray | None = None,
    link_scores: np.ndarray | None = None,
    piece_threshold: float = 0.5,
    link_threshold: float = 0.5,
) -> LaneGraph:
    """pieces: (n_i, 2) polylines in driving order; links: (L, 2) piece indices (src, dst).
    Scores default to 1 (keep everything). Coordinates stay float64."""
    return piece2graph_scored(pieces, links, piece_scores, link_scores, piece_threshold, link_threshold)[0]


def piece2graph_scored(
    pieces: Sequence[np.ndarray],
    links: np.ndarray,
    piece_scores: np.ndarray | None = None,
    link_scores: np.ndarray | None = None,
    piece_threshold: float = 0.5,
    link_threshold: float = 0.5,
) -> tuple[LaneGraph, np.ndarray]:
    """(piece2graph's graph, each of its edges' score): the highest score among the kept pieces whose
    consecutive points give that edge (`piece_scores` None: every score 0.0)."""
    links = np.asarray(links, np.int64).reshape(-1, 2)
    keep_piece = (
        np.ones(len(pieces), bool) if piece_scores is None else np.asarray(piece_scores) >= piece_threshold
    )
    keep_piece &= np.array([len(p) >= 2 for p in pieces], bool).reshape(-1)
    keep_link = (
        np.ones(len(links), bool) if link_scores is None else np.asarray(link_scores) >= link_threshold
    )
    keep_link &= keep_piece[links[:, 0]] & keep_piece[links[:, 1]]
    kept = np.flatnonzero(keep_piece)
    if len(kept) == 0:
        return LaneGraph.empty(), np.zeros(0)
    chains = [np.asarray(pieces[i], np.float64).reshape(-1, 2) for i in kept]
    sizes = np.array([len(c) for c in chains])
    points = np.concatenate(chains)
    offset = np.concatenate([[0], np.cumsum(sizes)])
    new_index = np.full(len(pieces), -1)
    new_index[kept] = np.arange(len(kept))

    # endpoints joined by links, directly or through others, become one vertex (connected components)
    start, end = offset[:-1], offset[1:] - 1
    pairs = np.stack([end[new_index[links[keep_link, 0]]], start[new_index[links[keep_link, 1]]]], axis=1)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points), len(points)))
    _, label = connected_components(graph, directed=False)

    # vertices numbered by first appearance; each at the mean of its points (first + mean offset, so
    # that a vertex of one point, or of identical points, keeps its floats)
    _, first, vertex = np.unique(label, return_index=True, return_inverse=True)
    rank = np.empty(len(first), np.int64)
    rank[np.argsort(first)] = np.arange(len(first))
    vertex = rank[vertex.ravel()]
    base = points[np.sort(first)]
    size = np.bincount(vertex)[:, None]
    offsets = points - base[vertex]
    xy = base + np.stack([np.bincount(vertex, offsets[:, i]) for i in (0, 1)], axis=1) / size

    is_last = np.zeros(len(points), bool)
    is_last[end] = True
    src, dst = vertex[:-1][~is_last[:-1]], vertex[1:][~is_last[:-1]]
    if piece_scores is None:  # the models' post-processing, a hot path: no score to keep
        graph, _ = graph_of_edges(xy[:, 0], xy[:, 1], src, dst)
        return graph, np.zeros(len(graph.src))
    point_score = np.repeat(np.asarray(piece_scores, np.float64)[kept], sizes)
    return graph_of_edges(xy[:, 0], xy[:, 1], src, dst, point_score[:-1][~is_last[:-1]])
