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


def without_pretrained_weights(config: Config) -> Config:
    """A copy of `config` whose backbone starts from random weights: for a model whose every weight a
    checkpoint then restores (cli eval, --resume), so that the pretrained file need not be where it was."""
    encoder = dataclasses.replace(config.encoder, backbone_weights="")
    return dataclasses.replace(config, encoder=encoder)


def check_backbone_weights(config: Config) -> None:
    """A camera backbone that the config expects pretrained (frozen stages, eval-mode BatchNorm: the paper
    preset) needs its weights file: random weights frozen, or normalised by their initial statistics,
    learn nothing there. `--from-scratch` trains every stage instead (resolve_config)."""
    encoder = config.encoder
    expects_weights = encoder.backbone_frozen_stages >= 0 or encoder.backbone_norm_eval
    if encoder.modality != "lidar" and expects_weights and not encoder.backbone_weights:
        raise ValueError(
            f"--preset {config.preset} trains the {encoder.backbone} backbone from ImageNet weights: give "
            "--pretrained FILE, a torchvision state dict saved where torchvision can download (python -c "
            f'"import torch, torchvision; torch.save(torchvision.models.{encoder.backbone}(weights='
            f"'IMAGENET1K_V1').state_dict(), '{encoder.backbone}.pth')\"), or --from-scratch to train it "
            "from random weights"
        )


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
    return Config.from_dict({**values, "model": model}, head(model, "paper"), str(path))


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
    accumulate: int | None = None,
    from_scratch: bool | None = None,
) -> Config:
    """A preset with the `cli train` flags (None: keep the preset's value), then `--set` overrides;
    `model` picks the head config (`decoder`): a flag of another model's head is an error. `from_scratch`
    trains every backbone stage with batch statistics (check_backbone_weights)."""
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
        "--accumulate": ("train.accumulate", accumulate),
    }
    for flag, (name, value) in flags.items():
        if value is not None:
            set_field(config, f"{name}={value}", flag)
    apply_overrides(config, overrides or [])
    if config.encoder.modality not in ("camera", "lidar", "fusion"):
        raise ValueError(f"modality must be camera, lidar or fusion, not {config.encoder.modality!r}")
    if from_scratch:
        config.encoder.backbone_frozen_stages, config.encoder.backbone_norm_eval = -1, False
    return config
