"""Hungarian matching of predicted paths to ground-truth paths (paper Eq. 3).

Cost = cls_weight * focal classification cost + point_weight * ordered point L1. Paths are directed,
so the points are compared in order (no permutation of a path, unlike MapTR's map elements).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment


def focal_cost(logits: torch.Tensor, alpha: float = 0.25, gamma: float = 2.0) -> torch.Tensor:
    """(Q,) logits -> (Q,) cost of labelling each query 'path' (Deformable DETR's focal cost)."""
    prob = logits.sigmoid()
    positive = alpha * (1 - prob) ** gamma * -(prob + 1e-8).log()
    negative = (1 - alpha) * prob**gamma * -(1 - prob + 1e-8).log()
    return positive - negative


def ordered_point_cost(points: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """points (Q, N, 2), targets (G, N, 2) -> (Q, G) mean over the N points of |dx| + |dy|."""
    return torch.cdist(points.flatten(1), targets.flatten(1), p=1) / points.shape[1]


@torch.no_grad()
def hungarian_match(
    logits: torch.Tensor,
    points: torch.Tensor,
    targets: torch.Tensor,
    cls_weight: float,
    point_weight: float,
    alpha: float = 0.25,
    gamma: float = 2.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """One frame: logits (Q,), points (Q, N, 2), targets (G, N, 2) -> (query indices, target indices)."""
    if targets.shape[0] == 0:
        empty = torch.zeros(0, dtype=torch.long)
        return empty, empty
    cost = cls_weight * focal_cost(logits.float(), alpha, gamma)[:, None]
    cost = cost + point_weight * ordered_point_cost(points.float(), targets.float())
    rows, cols = linear_sum_assignment(cost.cpu().numpy())
    return torch.as_tensor(rows, dtype=torch.long), torch.as_tensor(np.asarray(cols), dtype=torch.long)
