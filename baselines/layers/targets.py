"""What the losses train on: a batch's `Targets`, each field filled when a model `needs` it
(baselines/models), on the BEV grid or in unit BEV coordinates."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch


@dataclass
class Targets:
    """What the models train on; a model reads the fields of its `needs` (baselines/models)."""

    paths: list[torch.Tensor]  # per frame (G, N, 2) unit BEV coordinates; empty unless "paths"
    seg: torch.Tensor  # (B, bev_h, bev_w) int64 lane mask on the BEV grid
    raster_mask: torch.Tensor | None = None  # (B, H, W) uint8: the prepared 0.15 m lane raster ("raster")
    raster_direction: torch.Tensor | None = None  # (B, H, W) uint8 direction bins, 0 = none ("raster")
    pieces: list[torch.Tensor] | None = None  # per frame (P, n, 2) unit BEV coordinates ("pieces")
    piece_links: list[torch.Tensor] | None = None  # per frame (L, 2) int64: piece src ends where dst starts

    def to(self, device: torch.device | str) -> Targets:
        def move(value):
            if isinstance(value, list):
                return [v.to(device, non_blocking=True) for v in value]
            return None if value is None else value.to(device, non_blocking=True)

        return Targets(*(move(getattr(self, f.name)) for f in fields(self)))
