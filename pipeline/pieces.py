"""Graph2Piece: split a lane graph at its junctions into maximal chains (the STSU / MapTR targets)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.lane_graph import LaneGraph


@dataclass
class Pieces:
    chains: list[np.ndarray]  # vertex ids of each piece, in driving direction
    link_src: np.ndarray  # (K,) piece i ends at the vertex where piece link_dst[k] starts
    link_dst: np.ndarray
    junctions: np.ndarray  # vertex ids with in-degree != 1 or out-degree != 1

    @property
    def starts(self) -> np.ndarray:
        return np.array([c[0] for c in self.chains], np.int64)

    @property
    def ends(self) -> np.ndarray:
        return np.array([c[-1] for c in self.chains], np.int64)


def graph_to_pieces(graph: LaneGraph) -> Pieces:
    """Maximal chains between junction vertices (in-degree != 1 or out-degree != 1).

    A cycle with no junction on it (a roundabout ring whose entries are all outside the crop)
    becomes one closed piece that starts and ends at its smallest vertex id.
    """
    n = len(graph.x)
    src, dst = graph.src.astype(np.int64), graph.dst.astype(np.int64)
    indeg = np.bincount(dst, minlength=n)
    outdeg = np.bincount(src, minlength=n)
    is_junction = (indeg != 1) | (outdeg != 1)
    next_vertex = np.full(n, -1, np.int64)
    inner = ~is_junction[src]
    next_vertex[src[inner]] = dst[inner]  # unique: a non-junction vertex has exactly one out-edge

    chains = []
    visited = is_junction.copy()
    for s, d in zip(src[is_junction[src]].tolist(), dst[is_junction[src]].tolist()):
        chain = [s, d]
        while not is_junction[d]:
            visited[d] = True
            d = int(next_vertex[d])
            chain.append(d)
        chains.append(np.array(chain, np.int64))
    for v in np.flatnonzero(~visited).tolist():  # pure cycles, smallest vertex id first
        if visited[v]:
            continue
        chain = [v]
        d = v
        while True:
            visited[d] = True
            d = int(next_vertex[d])
            chain.append(d)
            if d == v:
                break
        chains.append(np.array(chain, np.int64))

    starts = np.array([c[0] for c in chains], np.int64)
    ends = np.array([c[-1] for c in chains], np.int64)
    order_start = np.argsort(starts, kind="stable")
    first = np.searchsorted(starts[order_start], ends, "left")
    last = np.searchsorted(starts[order_start], ends, "right")
    link_src = np.repeat(np.arange(len(chains)), last - first)
    link_dst = order_start[
        np.concatenate([np.arange(f, t) for f, t in zip(first, last)] or [np.zeros(0, np.int64)])
    ]
    return Pieces(chains, link_src.astype(np.int64), link_dst.astype(np.int64), np.flatnonzero(is_junction))


def pieces_to_graph(pieces: Pieces, x: np.ndarray, y: np.ndarray) -> LaneGraph:
    """The graph the pieces describe: every consecutive vertex pair of every chain is an edge."""
    edges = [np.stack([c[:-1], c[1:]], axis=1) for c in pieces.chains]
    edges = np.unique(np.concatenate(edges), axis=0) if edges else np.zeros((0, 2), np.int64)
    return LaneGraph(x, y, edges[:, 0].astype(np.int32), edges[:, 1].astype(np.int32))
