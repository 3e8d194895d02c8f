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


def match_cost(
    logits: torch.Tensor, points: torch.Tensor, targets: torch.Tensor, cls_weight: float, point_weight: float,
    alpha: float, gamma: float,
) -> torch.Tensor:  # fmt: skip
    """One frame: logits (Q,), points (Q, N, 2), targets (G, N, 2) -> (Q, G) matching cost."""
    cost = cls_weight * focal_cost(logits.float(), alpha, gamma)[:, None]
    return cost + point_weight * ordered_point_cost(points.float(), targets.float())


@torch.no_grad()
def match_layers(
    logits: torch.Tensor, points: torch.Tensor, targets: list[torch.Tensor], cls_weight: float,
    point_weight: float, alpha: float = 0.25, gamma: float = 2.0,
) -> list[list[tuple[torch.Tensor, torch.Tensor]]]:  # fmt: skip
    """Every decoder layer and frame at once: logits (L, B, Q), points (L, B, Q, N, 2), targets per frame
    (G, N, 2) -> matches[layer][frame] = (query indices, target indices), on the logits' device.

    The cost matrices reach scipy in one copy and the indices come back in one: a copy per layer and
    frame would wait for the GPU each time."""
    device = logits.device
    layers, frames = logits.shape[:2]
    costs = [
        match_cost(logits[layer, frame], points[layer, frame], targets[frame], cls_weight, point_weight,
                   alpha, gamma)
        for layer in range(layers) for frame in range(frames)
    ]  # fmt: skip
    flat = torch.cat([cost.flatten() for cost in costs]).cpu().numpy()
    rows, cols, offset = [], [], 0
    for cost in costs:
        size = cost.numel()
        matrix = flat[offset : offset + size].reshape(cost.shape)
        offset += size
        found = linear_sum_assignment(matrix) if size else (np.zeros(0, np.int64), np.zeros(0, np.int64))
        rows.append(found[0])
        cols.append(found[1])
    sizes = [len(r) for r in rows]
    indices = torch.from_numpy(np.concatenate(rows + cols).astype(np.int64)).to(device)
    pairs = list(zip(indices[: sum(sizes)].split(sizes), indices[sum(sizes) :].split(sizes), strict=True))
    return [pairs[layer * frames : (layer + 1) * frames] for layer in range(layers)]


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
    return match_layers(logits[None, None], points[None, None], [targets], cls_weight, point_weight, alpha,
                        gamma)[0][0]  # fmt: skip
