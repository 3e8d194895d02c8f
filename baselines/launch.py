"""`cli train`'s run: its config, then the training loop (baselines/train.py).

A new run's config is a preset with the options given (resolve_config); a resume's is the run's own
config.json with the options given on its command line applied as told changes, or refused by name
(resume_config). The long runs' options (--eval-every, ...) travel as `--set train.NAME=VALUE` items.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from baselines.config import WITHOUT_LIDAR, Config
from baselines.models import resolve_config, resume_config
from baselines.run_folder import RunFolder
from baselines.train import train
from pipeline.manifest import PreparedData

LONG_RUN = ("eval_every", "eval_frames", "best_metric", "checkpoint_every", "max_bad_steps")  # train.NAME


@dataclass
class TrainOptions:
    """The options of `cli train` that were given, by their parameter's name; None: not given, so the
    default's value (lanegap, paper, the preset's; on resume, the run's). A resume applies every option
    given (`given`) as a told change, or refuses it by name."""

    out: Path
    data: Path | None = None
    model: str | None = None
    preset: str | None = None
    modality: str | None = None
    epochs: int | None = None
    batch_size: int | None = None
    path_points: int | None = None
    bezier_points: int | None = None
    aux_seg: bool | None = None
    pretrained: Path | None = None
    from_scratch: bool | None = None
    accumulate: int | None = None
    set_: list[str] = field(default_factory=list)
    eval_every: int | None = None
    eval_frames: int | None = None
    best_metric: str | None = None
    checkpoint_every: int | None = None
    max_bad_steps: int | None = None
    resume: bool = False
    overwrite: bool = False
    stop_after: int = 0

    def overrides(self) -> list[str]:
        """The long runs' options given, as `--set` items, then the `--set` items."""
        long_run = {name: getattr(self, name) for name in LONG_RUN}
        given = [f"train.{name}={value}" for name, value in long_run.items() if value is not None]
        return given + list(self.set_)

    def given(self) -> dict[str, Any]:
        """The options given, by their parameter's name (the run's own ones among them: out, resume, ...)."""
        return {option.name: getattr(self, option.name) for option in fields(self)
                if getattr(self, option.name) is not None}  # fmt: skip


@dataclass
class Launched:
    """A finished `cli train`: the config it trained, the data it trained on and the training's summary."""

    config: Config
    data: Path
    summary: dict

    @property
    def title(self) -> str:
        """What was trained, how and on what (`cli train`'s heading)."""
        config = self.config
        return f"{config.model} ({config.preset}, {config.encoder.modality}) trained on {self.data}"


def run_config(options: TrainOptions) -> tuple[Config, Path, set[str]]:
    """The config and the data of the run, and on resume the config fields told by the options given,
    which run.json logs. On a dataset without LiDAR (WITHOUT_LIDAR) the modality is camera unless given,
    and another is refused (check_modality)."""
    data, told = options.data, set()
    if options.resume:
        config, told = resume_config(options.out, options.given(), options.overrides())
        data = data or Path(json.loads((options.out / "run.json").read_text())["data"])
    else:
        if data is None:
            raise ValueError("--data is required")
        pretrained = options.pretrained
        if pretrained is not None and not pretrained.is_file():
            raise ValueError(f"--pretrained {pretrained}: no such file")
        camera_only = PreparedData.open(data).kind in WITHOUT_LIDAR
        modality = options.modality or ("camera" if camera_only else None)
        config = resolve_config(options.preset or "paper", modality, options.epochs,
                                options.batch_size, options.path_points, options.bezier_points,
                                options.aux_seg, str(pretrained) if pretrained else None, options.overrides(),
                                options.model or "lanegap", options.accumulate,
                                options.from_scratch)  # fmt: skip
    prepared = PreparedData.open(data)
    check_modality(config, prepared, options)
    check_images(config, prepared)
    return config, data, told


def check_images(config: Config, data: PreparedData) -> None:
    """Training reads every frame's images: a dataset with frames whose images are absent (cli prepare counts
    them, PreparedData.frames_without_images) is refused in one line, before any work."""
    missing = data.frames_without_images
    if config.encoder.modality == "lidar" or not missing:
        return
    raise ValueError(f"{data.path}: {missing} frame(s) of this prepared {data.kind} dataset lack their "
                     f"images under {data.sensor_root} (manifest.json: frames_without_images); add them and "
                     "prepare it again with --overwrite")  # fmt: skip


def check_modality(config: Config, data: PreparedData, options: TrainOptions) -> None:
    """A dataset without LiDAR (OpenLane-V2's: camera images only) trains the camera modality alone: another
    is refused in one line naming where it came from and the dataset, before any work."""
    modality = config.encoder.modality
    if data.kind not in WITHOUT_LIDAR or modality == "camera":
        return
    set_items = [item for item in options.set_ if item.partition("=")[0].strip() == "encoder.modality"]
    if set_items:  # applied after --modality: the last one wins
        source = f"--set {set_items[-1]}"
    elif options.modality:
        source = f"--modality {options.modality}"
    else:
        source = f"the run {options.out} (modality {modality})"
    raise ValueError(f"{source}: {data.path} is a prepared {data.kind} dataset (its manifest.json), which "
                     "has no LiDAR: train on its cameras (--modality camera, the default on it)")  # fmt: skip


def launch(options: TrainOptions) -> Launched:
    """Check the run folder, put the config together and train it (a resume goes on from its checkpoint)."""
    RunFolder.check_free(options.out, options.resume, options.overwrite)
    config, data, told = run_config(options)
    summary = train(config, data, options.out, resume=options.resume, stop_after=options.stop_after,
                    overwrite=options.overwrite, told=told)  # fmt: skip
    return Launched(config, data, summary)
