"""Graph2Path (LaneGAP, Alg. 1): the lane graph as a set of directed root-to-leaf paths.

Paths are enumerated over the pieces (maximal chains) rather than over single vertices: a path can
only branch at a junction, so this is the same enumeration with far fewer steps.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.pieces import Pieces


@dataclass
class Paths:
    vertex_ids: list[np.ndarray]  # graph vertices visited by each path, in order
    cap_hit: bool  # the enumeration stopped at max_paths


@dataclass
class _PieceLinks:
    """The pieces as a graph of their own: each piece's first and last vertex, and the pieces that follow
    (successors) and precede (predecessors) each piece."""

    starts: np.ndarray
    ends: np.ndarray
    successors: dict[int, list[int]]
    predecessors: dict[int, list[int]]

    @classmethod
    def of(cls, pieces: Pieces) -> _PieceLinks:
        successors: dict[int, list[int]] = {}
        predecessors: dict[int, list[int]] = {}
        for i, j in zip(pieces.link_src.tolist(), pieces.link_dst.tolist()):
            successors.setdefault(i, []).append(j)
            predecessors.setdefault(j, []).append(i)
        return cls(pieces.starts, pieces.ends, successors, predecessors)

    def onward(self, path: list[int], seen: set[int]) -> list[int]:
        """The pieces that can follow the path's last without reaching a vertex it has seen."""
        return [q for q in self.successors.get(path[-1], []) if int(self.ends[q]) not in seen]

    def backward(self, path: list[int], seen: set[int]) -> list[int]:
        """The pieces that can precede the path's first without leaving a vertex it has seen."""
        return [q for q in self.predecessors.get(path[0], []) if int(self.starts[q]) not in seen]


@dataclass
class _Found:
    """The paths (piece indices) found so far: at most max_paths, cap_hit once one more was refused."""

    max_paths: int
    paths: list[list[int]] = field(default_factory=list)
    cap_hit: bool = False

    def emit(self, path: list[int]) -> bool:
        if len(self.paths) >= self.max_paths:
            self.cap_hit = True
            return False
        self.paths.append(path)
        return True


def pieces_to_paths(pieces: Pieces, n_vertices: int, max_paths: int = 256) -> Paths:
    """Every simple path from a root (in-degree 0) that runs until a leaf (out-degree 0) or until
    every way on would revisit a vertex (a cycle closes).

    Then, so that no edge is lost to cycles that no root reaches (a roundabout wholly inside the
    crop) or to the edge that closes a cycle, each piece no path has covered yet, smallest index
    first, gets one more path through it: extended backwards and forwards along the smallest-index
    pieces that keep the path simple, preferring pieces not yet covered. A closed piece (a loop that
    starts and ends at one vertex) is such a path alone. Deterministic throughout; at most max_paths.
    """
    links = _PieceLinks.of(pieces)
    found = _Found(max_paths)
    for root in _root_pieces(pieces, links, n_vertices):
        _root_to_leaf_paths(links, root, found)
    _cover_the_rest(links, len(pieces.chains), found)
    vertex_ids = [
        np.concatenate([pieces.chains[path[0]]] + [pieces.chains[q][1:] for q in path[1:]])
        for path in found.paths
    ]
    return Paths(vertex_ids, found.cap_hit)


def _root_pieces(pieces: Pieces, links: _PieceLinks, n_vertices: int) -> list[int]:
    """The pieces that start at a vertex no edge enters, by index."""
    indeg = np.zeros(n_vertices, np.int64)
    for c in pieces.chains:
        indeg[c[1:]] += 1
    return [p for p in range(len(pieces.chains)) if indeg[links.starts[p]] == 0]


def _root_to_leaf_paths(links: _PieceLinks, root: int, found: _Found) -> None:
    """Every simple path from the root piece on, smallest successor first, until the cap is hit."""
    # iterative DFS: each stack entry is (path, visited vertex ends)
    stack = [([root], {int(links.starts[root]), int(links.ends[root])})]
    while stack and not found.cap_hit:
        path, seen = stack.pop()
        ways = links.onward(path, seen)
        if not ways:
            found.emit(path)
            continue
        for q in reversed(ways):  # reversed so that the smallest index is explored first
            stack.append((path + [q], seen | {int(links.ends[q])}))


def _cover_the_rest(links: _PieceLinks, n_pieces: int, found: _Found) -> None:
    """One more path through each piece that no path covers yet, smallest index first."""
    covered = np.zeros(n_pieces, bool)
    for path in found.paths:
        covered[path] = True
    for p in range(n_pieces):
        if covered[p] or found.cap_hit:
            continue
        path = _path_through(links, p, covered)
        if found.emit(path):
            covered[path] = True


def _path_through(links: _PieceLinks, p: int, covered: np.ndarray) -> list[int]:
    """Piece p extended backwards, then forwards, along the smallest-index pieces that keep the path
    simple, those not yet covered first; a closed piece (a loop) is a path of its own."""
    path, seen = [p], {int(links.starts[p]), int(links.ends[p])}
    if links.starts[p] == links.ends[p]:
        return path
    while ways := links.backward(path, seen):
        q = min(ways, key=lambda q: (covered[q], q))
        path.insert(0, q)
        seen.add(int(links.starts[q]))
    while ways := links.onward(path, seen):
        q = min(ways, key=lambda q: (covered[q], q))
        path.append(q)
        seen.add(int(links.ends[q]))
    return path
