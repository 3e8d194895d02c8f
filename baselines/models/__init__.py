"""The baselines under one contract: `build(config)` of each model module returns a `Built`; `MODELS`
maps a model name to its module's `build`, `HEADS` to its head config per preset (like `PRESETS`).

Training (`baselines/train.py`) and evaluation (`baselines/evaluate.py`) only use the record: the
`model` (whose `.encoder` is the shared `BEVEncoder`), its `loss`, its `to_graphs` post-processing and
the prepared tables its targets come from (`needs`).
"""

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


# After `Built` and `preset_head`: the model modules import them.
from baselines.models import hdmapnet, lanegap, maptr, stsu  # noqa: E402

MODELS = {"lanegap": lanegap.build, "hdmapnet": hdmapnet.build, "maptr": maptr.build, "stsu": stsu.build}
# preset name -> the model's head config (the config's `decoder`)
HEADS = {"lanegap": lanegap.head, "hdmapnet": hdmapnet.head, "maptr": maptr.head, "stsu": stsu.head}


def build(config) -> Built:
    """The model named by `config.model`, with its loss and post-processing."""
    if config.model not in MODELS:
        raise ValueError(f"unknown model {config.model!r}: expected one of {', '.join(MODELS)}")
    return MODELS[config.model](config)
