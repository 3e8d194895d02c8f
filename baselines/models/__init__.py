"""The baselines under one contract: `build(config)` of each model module returns a `Built`
(baselines/models/base.py). `MODELS` maps a model name to its module's `build`, `HEADS` to its head config
per preset (the config's `decoder`), beside the encoder, data and training presets of baselines/config.py.
This is the one place that knows every model, so a run's config is put together here: a preset and a
model (`resolve_config`, with the `cli train` flags), or a saved config.json (`load_config`).

Training (`baselines/train.py`) and evaluation (`baselines/evaluate.py`) only use the record: the
`model` (whose `.encoder` is the shared `BEVEncoder`), its `loss`, its `to_graphs` post-processing and
the prepared tables its targets come from (`needs`).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from baselines.config import PRESETS, Config, apply_overrides, set_field
from baselines.models import hdmapnet, lanegap, maptr, stsu
from baselines.models.base import Built

MODELS = {"lanegap": lanegap.build, "hdmapnet": hdmapnet.build, "maptr": maptr.build, "stsu": stsu.build}
# preset name -> the model's head config (the config's `decoder`)
HEADS = {"lanegap": lanegap.head, "hdmapnet": hdmapnet.head, "maptr": maptr.head, "stsu": stsu.head}


def build(config) -> Built:
    """The model named by `config.model`, with its loss and post-processing."""
    if config.model not in MODELS:
        raise ValueError(f"unknown model {config.model!r}: expected one of {', '.join(MODELS)}")
    return MODELS[config.model](config)


def head(model: str, preset: str) -> Any:
    """The head config of `model` for `preset`."""
    if model not in HEADS:
        raise ValueError(f"unknown model {model!r}: expected one of {', '.join(HEADS)}")
    return HEADS[model](preset)


def load_config(path: Path) -> Config:
    """A run's saved config.json; a field it lacks (a file older than the field) takes its default, the
    paper preset's."""
    values = json.loads(Path(path).read_text())
    model = values.get("model", "lanegap")  # files from before the other models
    return Config.from_dict({**values, "model": model}, head(model, "paper"))


def resolve_config(
    preset: str,
    modality: str | None = None,
    epochs: int | None = None,
    batch_size: int | None = None,
    path_points: int | None = None,
    bezier_points: int | None = None,
    aux_seg: bool | None = None,
    backbone_weights: str | None = None,
    overrides: list[str] | None = None,
    model: str = "lanegap",
) -> Config:
    """A preset with the `cli train` flags (None: keep the preset's value), then `--set` overrides;
    `model` picks the head config (`decoder`): a flag of another model's head is an error."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}: expected one of {', '.join(PRESETS)}")
    config = dataclasses.replace(PRESETS[preset](), model=model, decoder=head(model, preset))
    flags = {
        "--modality": ("encoder.modality", modality),
        "--epochs": ("train.epochs", epochs),
        "--batch-size": ("train.batch_size", batch_size),
        "--path-points": ("decoder.path_points", path_points),
        "--bezier-points": ("decoder.bezier_points", bezier_points),
        "--aux-seg": ("decoder.aux_seg", aux_seg),
        "--pretrained": ("encoder.backbone_weights", backbone_weights),
    }
    for flag, (name, value) in flags.items():
        if value is not None:
            set_field(config, f"{name}={value}", flag)
    apply_overrides(config, overrides or [])
    if config.encoder.modality not in ("camera", "lidar", "fusion"):
        raise ValueError(f"modality must be camera, lidar or fusion, not {config.encoder.modality!r}")
    return config
