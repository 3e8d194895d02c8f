"""The fine BEV level of the query decoders: the shared BEV features lifted to cells a few times smaller,
which the deformable attention reads beside the coarse map, and the dense loss that trains them.

Why: the tiny preset's BEV cells are 1.5 m, three times the metric's 0.45 m match radius, and a point
regressed from them often lands beyond that radius (docs/EXPERIMENTS.md); the decoder's sparse
gradient alone does not teach the encoder where the paint lies inside a cell nor which way a lane runs.
The features upsampled (bilinear) by the scale and one 3x3 convolution make the fine level; a 1x1 head
on it regresses the lane mask and the travel direction against the prepared raster
(baselines/layers/raster_targets.py, as HDMapNet's branches), in training only. The paper's own grid (0.3 m
cells) needs no fine level.
"""

from __future__ import annotations

import torch
from torch import nn

from baselines.layers.raster_targets import raster_losses
from baselines.layers.targets import Targets


class FineBEV(nn.Module):
    """BEV features (B, C, H, W) -> the fine level (B, C, s H, s W) and, in training, its auxiliary
    outputs (B, 4, s H, s W): two lane logits, then the (cos, sin) direction."""

    def __init__(self, dim: int, scale: float, channels: int = 32):
        super().__init__()
        self.lift = nn.Sequential(
            nn.Upsample(scale_factor=scale, mode="bilinear"),
            nn.Conv2d(dim, channels, 3, padding=1),
            nn.ReLU(True),
        )
        self.level = nn.Conv2d(channels, dim, 1)
        self.aux = nn.Conv2d(channels, 4, 1)

    def forward(self, bev: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        fine = self.lift(bev)
        return self.level(fine), (self.aux(fine) if self.training else None)


def fine_losses(aux: torch.Tensor, targets: Targets) -> dict[str, torch.Tensor]:
    """The fine level's auxiliary outputs against the prepared raster pooled to their cells: lane
    cross-entropy "fine_seg" and direction L2 "fine_direction"."""
    if targets.raster_mask is None:
        raise ValueError("the fine BEV level trains on the prepared rasters: the model must need 'raster'")
    seg, direction = raster_losses(
        aux[:, :2], aux[:, 2:], targets.raster_mask, targets.raster_direction, adaptive=True
    )
    return {"fine_seg": seg, "fine_direction": direction}
