"""Step 2 of the metric (docs/METRICS.md): the matching M(A, B) of the candidate pairs (Matching), greedy
in rank order (the default) or of maximum cardinality (Hopcroft-Karp)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from benchmark.metric.candidates import Candidates
from pipeline.kernels import kernel


@kernel
def _greedy(cand_a, cand_b, n_a, n_b):
    """Take the pairs in rank order, keeping one when neither end is taken yet.
    Returns each vertex's partner (-1: none) and the rank of its pair."""
    partner_a, partner_b = np.full(n_a, -1, np.int64), np.full(n_b, -1, np.int64)
    rank_a, rank_b = np.full(n_a, len(cand_a), np.int64), np.full(n_b, len(cand_a), np.int64)
    for r in range(len(cand_a)):
        a, b = cand_a[r], cand_b[r]
        if partner_a[a] < 0 and partner_b[b] < 0:
            partner_a[a], partner_b[b] = b, a
            rank_a[a], rank_b[b] = r, r
    return partner_a, partner_b, rank_a, rank_b


@dataclass
class Matching:
    """M(A, B) over all vertices: partner_a[a] = b (-1: unmatched), rank_a[a] the rank of that pair."""

    partner_a: np.ndarray
    partner_b: np.ndarray
    rank_a: np.ndarray
    rank_b: np.ndarray

    @property
    def pairs(self) -> tuple[np.ndarray, np.ndarray]:
        a = np.flatnonzero(self.partner_a >= 0)
        return a, self.partner_a[a]


def optimal_partners(cand_a: np.ndarray, cand_b: np.ndarray, n_a: int, n_b: int) -> np.ndarray:
    """Partner of each a (-1: none) in a maximum-cardinality matching (Hopcroft-Karp)."""
    from scipy.sparse import csr_matrix  # 0.1 s to import: loaded only for --matching optimal
    from scipy.sparse.csgraph import maximum_bipartite_matching

    graph = csr_matrix((np.ones(len(cand_a)), (cand_a, cand_b)), shape=(n_a, n_b))
    return np.asarray(maximum_bipartite_matching(graph, perm_type="column"), np.int64)


def match(cand: Candidates, n_a: int, n_b: int, matching: str) -> Matching:
    if matching == "greedy":
        return Matching(*_greedy(cand.a, cand.b, n_a, n_b))
    partner_a = optimal_partners(cand.a, cand.b, n_a, n_b)
    partner_b = np.full(n_b, -1, np.int64)
    paired = np.flatnonzero(partner_a >= 0)
    partner_b[partner_a[paired]] = paired
    none = np.full(max(n_a, n_b), len(cand.a), np.int64)  # ranks only serve the greedy kernel
    return Matching(partner_a, partner_b, none[:n_a], none[:n_b])
