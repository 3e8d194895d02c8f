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

import copy
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


# The `cli train` options that set one config field each, by their parameter's name: (option, field).
OPTION_FIELDS = {
    "modality": ("--modality", "encoder.modality"),
    "epochs": ("--epochs", "train.epochs"),
    "batch_size": ("--batch-size", "train.batch_size"),
    "path_points": ("--path-points", "decoder.path_points"),
    "bezier_points": ("--bezier-points", "decoder.bezier_points"),
    "aux_seg": ("--aux-seg", "decoder.aux_seg"),
    "pretrained": ("--pretrained", "encoder.backbone_weights"),
    "accumulate": ("--accumulate", "train.accumulate"),
}


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
    values = {"modality": modality, "epochs": epochs, "batch_size": batch_size, "path_points": path_points,
              "bezier_points": bezier_points, "aux_seg": aux_seg, "pretrained": backbone_weights,
              "accumulate": accumulate}  # fmt: skip
    for name, value in values.items():
        if value is not None:
            flag, field_name = OPTION_FIELDS[name]
            set_field(config, f"{field_name}={value}", flag)
    apply_overrides(config, overrides or [])
    if config.encoder.modality not in ("camera", "lidar", "fusion"):
        raise ValueError(f"modality must be camera, lidar or fusion, not {config.encoder.modality!r}")
    if from_scratch:
        config.encoder.backbone_frozen_stages, config.encoder.backbone_norm_eval = -1, False
    return config


SHAPES = "it shapes the model, whose weights the checkpoint holds"
# The fields that a resume keeps, and why: the checkpoint's weights, optimiser and place in its epoch were
# made with them. A resume's option or --set that would change one is refused by name (resume_config).
KEPT_ON_RESUME = {
    "model": "the checkpoint holds that model's weights",
    "preset": "the preset sized every section of the model and the run that the checkpoint holds",
    "encoder.modality": SHAPES,
    "decoder.path_points": SHAPES,
    "decoder.bezier_points": SHAPES,
    "decoder.aux_seg": SHAPES,
    "encoder.backbone_weights": "the checkpoint holds the backbone's weights: a resume reads no such file",
    "encoder.backbone_frozen_stages": "it sets which backbone weights the optimiser of the checkpoint trains",
    "encoder.backbone_norm_eval": "it sets how the backbone's BatchNorm of the checkpoint normalises",
    "train.batch_size": "another batch changes the steps per epoch, the learning-rate schedule and where an "
    "interrupted epoch goes on",
}
# The `cli train` options that a resume takes as they are: the run folder, the data, this invocation's own
# (--stop-after, --json) and those that cli.py passes as --set items (--set and the long runs' options).
RESUME_OWN = {"out", "resume", "overwrite", "data", "stop_after", "as_json", "set_", "eval_every",
              "eval_frames", "best_metric", "checkpoint_every", "max_bad_steps"}  # fmt: skip


def option_shown(name: str, value: Any) -> str:
    """A `cli train` option as given, by its parameter's name: `--batch-size 4`, `--no-aux-seg`."""
    flag = OPTION_FIELDS[name][0] if name in OPTION_FIELDS else f"--{name.replace('_', '-')}"
    if isinstance(value, bool):
        return flag if value else f"--no-{flag[2:]}"
    return f"{flag} {value}"


def field_value(config: Config, name: str) -> Any:
    """The value of `section.field` (or of a top-level field: model, preset) in `config`."""
    section, dot, field_name = name.partition(".")
    return getattr(getattr(config, section), field_name) if dot else getattr(config, name)


def parameter_shapes(config: Config) -> dict[str, tuple[int, ...]]:
    """The shape of each tensor of `config`'s model, built on the meta device: no memory, no file read."""
    import torch

    with torch.device("meta"):
        model = build(without_pretrained_weights(config)).model
    return {name: tuple(tensor.shape) for name, tensor in model.state_dict().items()}


def refuse_reshaping(out: Path, trained: Config, config: Config, overrides: list[str]) -> None:
    """Refuse, in one line naming them, the `--set` items of a resume that change the shape of the model
    whose weights the checkpoint holds (a field KEPT_ON_RESUME does not list: encoder.channels, ...), so
    that the resume stops before any work rather than when it loads the weights. train.* shape nothing."""
    changed = {item.partition("=")[0].strip(): item for item in overrides}
    changed = {name: item for name, item in changed.items() if not name.startswith("train.")
               and field_value(trained, name) != field_value(config, name)}  # fmt: skip
    if not changed:
        return
    shapes = parameter_shapes(trained)
    if parameter_shapes(config) == shapes:
        return

    def reshapes(name: str) -> bool:
        alone = copy.deepcopy(trained)
        set_field(alone, changed[name], f"--set {changed[name]}")
        return parameter_shapes(alone) != shapes

    names = [name for name in changed if reshapes(name)] or list(changed)  # else only together
    told = " ".join(f"--set {changed[name]}" for name in names)
    before = ", ".join(f"{name}={field_value(trained, name)!r}" for name in names)
    they, them = ("it shapes", "it") if len(names) == 1 else ("they shape", "them")
    raise ValueError(f"{told} on --resume: the run in {out} was trained with {before}, and {they} the "
                     f"model, whose weights the checkpoint holds: a resume goes on with {them} (leave the "
                     "option out, or start another run in another --out)")  # fmt: skip


def resume_config(out: Path, options: dict[str, Any], overrides: list[str]) -> tuple[Config, set[str]]:
    """The config that a resume of the run in `out` goes on with, and the fields told on its command line:
    its config.json with `options` (the `cli train` options given, by their parameter's name) and then
    `overrides` (`--set` items) applied as told changes, which run.json logs (RunFolder.resume). A change
    of a field that the resume keeps (KEPT_ON_RESUME) is refused in one line naming the option and why,
    before any work; an option given equal to the run's changes nothing."""
    if not (out / "config.json").is_file() or not (out / "run.json").is_file():
        raise ValueError(f"--out {out}: no run to resume (config.json and run.json of cli train)")
    config = load_config(out / "config.json")
    trained = copy.deepcopy(config)

    def keep(name: str, option: str) -> None:
        before, after = field_value(trained, name), field_value(config, name)
        if name in KEPT_ON_RESUME and before != after:
            raise ValueError(f"{option} on --resume: the run in {out} was trained with {name}={before!r}, "
                             f"and {KEPT_ON_RESUME[name]}: a resume goes on with it (leave the option out, "
                             "or start another run in another --out)")  # fmt: skip

    told: set[str] = set()
    for name, value in options.items():
        option = option_shown(name, value)
        if name in ("model", "preset"):
            setattr(config, name, value)
            keep(name, option)
        elif name == "from_scratch":  # resolve_config's two fields; --no-from-scratch: the preset's
            preset = PRESETS[config.preset]().encoder
            scratch = (-1, False) if value else (preset.backbone_frozen_stages, preset.backbone_norm_eval)
            config.encoder.backbone_frozen_stages, config.encoder.backbone_norm_eval = scratch
            keep("encoder.backbone_frozen_stages", option)
            keep("encoder.backbone_norm_eval", option)
        elif name in OPTION_FIELDS:
            field_name = OPTION_FIELDS[name][1]
            set_field(config, f"{field_name}={value}", OPTION_FIELDS[name][0])
            keep(field_name, option)
            told.add(field_name)
        elif name not in RESUME_OWN:
            raise ValueError(f"{option} on --resume: a resume does not apply it (leave it out)")
    for item in overrides:
        set_field(config, item, f"--set {item}")
        field_name = item.partition("=")[0].strip()
        keep(field_name, f"--set {item}")
        told.add(field_name)
    config.check_across("--set")
    refuse_reshaping(out, trained, config, overrides)
    return config, told
