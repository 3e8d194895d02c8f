"""Graph2Path (LaneGAP, Alg. 1): the lane graph as a set of directed root-to-leaf paths.

Paths are enumerated over the pieces (maximal chains) rather than over single vertices: a path can
only branch at a junction, so this is the same enumeration with far fewer steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.pieces import Pieces


@dataclass
class Paths:
    vertex_ids: list[np.ndarray]  # graph vertices visited by each path, in order
    cap_hit: bool  # the enumeration stopped at max_paths


def pieces_to_paths(pieces: Pieces, n_vertices: int, max_paths: int = 256) -> Paths:
    """Every simple path from a root (in-degree 0) that runs until a leaf (out-degree 0) or until
    every way on would revisit a vertex (a cycle closes).

    Then, so that no edge is lost to cycles that no root reaches (a roundabout wholly inside the
    crop) or to the edge that closes a cycle, each piece no path has covered yet, smallest index
    first, gets one more path through it: extended backwards and forwards along the smallest-index
    pieces that keep the path simple, preferring pieces not yet covered. A closed piece (a loop that
    starts and ends at one vertex) is such a path alone. Deterministic throughout; at most max_paths.
    """
    starts, ends = pieces.starts, pieces.ends
    successors: dict[int, list[int]] = {}
    predecessors: dict[int, list[int]] = {}
    for i, j in zip(pieces.link_src.tolist(), pieces.link_dst.tolist()):
        successors.setdefault(i, []).append(j)
        predecessors.setdefault(j, []).append(i)
    indeg = np.zeros(n_vertices, np.int64)
    for c in pieces.chains:
        indeg[c[1:]] += 1

    found: list[list[int]] = []
    cap_hit = False

    def emit(path: list[int]) -> bool:
        nonlocal cap_hit
        if len(found) >= max_paths:
            cap_hit = True
            return False
        found.append(path)
        return True

    roots = [p for p in range(len(pieces.chains)) if indeg[starts[p]] == 0]
    for root in roots:
        # iterative DFS: each stack entry is (path, visited vertex ends, next successors to try)
        stack = [([root], {int(starts[root]), int(ends[root])})]
        while stack and not cap_hit:
            path, seen = stack.pop()
            ways = [q for q in successors.get(path[-1], []) if int(ends[q]) not in seen]
            if not ways:
                emit(path)
                continue
            for q in reversed(ways):  # reversed so that the smallest index is explored first
                stack.append((path + [q], seen | {int(ends[q])}))

    covered = np.zeros(len(pieces.chains), bool)
    for path in found:
        covered[path] = True
    for p in range(len(pieces.chains)):
        if covered[p] or cap_hit:
            continue
        path, seen = [p], {int(starts[p]), int(ends[p])}
        while starts[p] != ends[p]:  # backwards; a closed piece (a loop) is a path of its own
            ways = [q for q in predecessors.get(path[0], []) if int(starts[q]) not in seen]
            if not ways:
                break
            q = min(ways, key=lambda q: (covered[q], q))
            path.insert(0, q)
            seen.add(int(starts[q]))
        while starts[p] != ends[p]:  # forwards
            ways = [q for q in successors.get(path[-1], []) if int(ends[q]) not in seen]
            if not ways:
                break
            q = min(ways, key=lambda q: (covered[q], q))
            path.append(q)
            seen.add(int(ends[q]))
        if emit(path):
            covered[path] = True

    vertex_ids = [
        np.concatenate([pieces.chains[path[0]]] + [pieces.chains[q][1:] for q in path[1:]]) for path in found
    ]
    return Paths(vertex_ids, cap_hit)
