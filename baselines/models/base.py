"""What every model module shares: the `Built` record that its `build(config)` returns, and the lookup
of its head config by preset."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from torch import nn


@dataclass
class Built:
    model: nn.Module  # SensorBatch -> dict of output tensors
    loss: nn.Module  # (outputs, data.Targets) -> dict of losses; "loss" is the total, the rest logged
    to_graphs: Callable  # outputs -> one LaneGraph (metres, BEV frame) per frame of the batch
    needs: frozenset[str]  # targets it trains on: "paths", "pieces" (+ links), "raster" (mask + direction)
    modeling: str  # the paper's family: "pixel", "piece" or "path"


def preset_head(model: str, heads: dict, preset: str):
    """`heads[preset]()`, or a clear error naming the model and the presets it has."""
    if preset not in heads:
        raise ValueError(f"{model} has no head size for preset {preset!r}: expected {', '.join(heads)}")
    return heads[preset]()
