"""Small building blocks that several models share: MLP, feed-forward, inverse sigmoid, focal loss, the
Bernstein matrix of Bezier curves, the fp32 geometry under autocast and the loss normaliser over
processes."""

from __future__ import annotations

import functools
import math
from contextlib import nullcontext

import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import nn


class FeedForward(nn.Sequential):
    def __init__(self, dim: int, hidden: int, dropout: float):
        super().__init__(nn.Linear(dim, hidden), nn.ReLU(True), nn.Dropout(dropout), nn.Linear(hidden, dim))


def mlp(dim: int, out: int, layers: int = 3) -> nn.Sequential:
    modules: list[nn.Module] = []
    for _ in range(layers - 1):
        modules += [nn.Linear(dim, dim), nn.ReLU(True)]
    return nn.Sequential(*modules, nn.Linear(dim, out))


def inverse_sigmoid(x: torch.Tensor, eps: float = 1e-5) -> torch.Tensor:
    x = x.clamp(eps, 1 - eps)
    return torch.log(x / (1 - x))


def sigmoid_focal_loss(
    logits: torch.Tensor, labels: torch.Tensor, alpha: float, gamma: float
) -> torch.Tensor:
    """Summed focal loss (RetinaNet) of binary logits against 0 / 1 labels."""
    prob = logits.sigmoid()
    ce = F.binary_cross_entropy_with_logits(logits, labels, reduction="none")
    p_t = prob * labels + (1 - prob) * (1 - labels)
    alpha_t = alpha * labels + (1 - alpha) * (1 - labels)
    return (alpha_t * (1 - p_t) ** gamma * ce).sum()


@functools.lru_cache(maxsize=64)
def _constant(values: tuple, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    return torch.tensor(values, dtype=dtype, device=device)


def constant(values, device: torch.device | str, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """A small tensor of Python values (nested tuples or lists) on `device`, made once per values and
    device: made anew each step, it is a copy from the host that waits for the GPU to catch up. Read only."""
    freeze = lambda v: tuple(freeze(x) for x in v) if isinstance(v, list | tuple) else v  # noqa: E731
    return _constant(freeze(values), dtype, torch.device(device))


def count(value: float, device: torch.device | str) -> torch.Tensor:
    """A 0-d float tensor of a count known on the host: filled on the device, no copy, no wait."""
    return torch.full((), float(value), device=device)


def bernstein_basis(t: torch.Tensor, num_controls: int) -> torch.Tensor:
    """Parameters t (..., n) in [0, 1] -> (..., n, K) Bernstein basis of degree K - 1."""
    degree = num_controls - 1
    k = torch.arange(num_controls, dtype=t.dtype, device=t.device)
    binomial = constant([math.comb(degree, j) for j in range(num_controls)], t.device, t.dtype)
    t = t.unsqueeze(-1)
    return binomial * t**k * (1 - t) ** (degree - k)


def bernstein_matrix(num_points: int, num_controls: int) -> torch.Tensor:
    """(num_points, num_controls): row i is the Bernstein basis at t_i = i / (N - 1), so
    `matrix @ controls` samples the curve at N evenly spaced parameters (LaneGAP Eq. 2)."""
    t = torch.linspace(0, 1, num_points, dtype=torch.float64)
    return bernstein_basis(t, num_controls).float()


def fp32_grid_sample(values: torch.Tensor, grid: torch.Tensor, **kwargs) -> torch.Tensor:
    """F.grid_sample with the values and the grid in fp32 whatever autocast is on: CUDA's runs it in bf16
    when both come in bf16, rounding the sampling positions and summing the backward's samples in bf16."""
    device = values.device.type  # autocast knows no meta device (tests/test_device_placement.py)
    with torch.autocast(device, enabled=False) if torch.amp.is_autocast_available(device) else nullcontext():
        return F.grid_sample(values.float(), grid.float(), **kwargs)


def combine_points(weights: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """weights (M, N) @ points (..., N, D) -> (..., M, D) in fp32, as a sum of products: a matrix product
    runs in bf16 under autocast, and in TF32 on a GPU that allows it (baselines/train.py)."""
    return (weights.float()[..., None] * points.float().unsqueeze(-3)).sum(-2)


def mean_over_processes(counts: torch.Tensor) -> torch.Tensor:
    """Counts summed over all processes, divided by their number (DETR's num_boxes): every process
    normalises by the same figure, and DDP's gradient mean makes it the whole batch's."""
    if dist.is_available() and dist.is_initialized():
        counts = counts.clone()
        dist.all_reduce(counts)
        counts = counts / dist.get_world_size()
    return counts
