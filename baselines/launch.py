"""`cli train`'s run: its config, then the training loop (baselines/train.py).

A new run's config is a preset with the options given (resolve_config); a resume's is the run's own
config.json with the options given on its command line applied as told changes, or refused by name
(resume_config). The long runs' options (--eval-every, ...) travel as `--set train.NAME=VALUE` items.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from baselines.config import Config
from baselines.models import resolve_config, resume_config
from baselines.run_folder import RunFolder
from baselines.train import train

LONG_RUN = ("eval_every", "eval_frames", "best_metric", "checkpoint_every", "max_bad_steps")  # train.NAME


@dataclass
class TrainOptions:
    """The options of `cli train`, by their parameter's name; None: the preset's value (on resume, the
    run's)."""

    out: Path
    data: Path | None = None
    model: str = "lanegap"
    preset: str = "paper"
    modality: str | None = None
    epochs: int | None = None
    batch_size: int | None = None
    path_points: int | None = None
    bezier_points: int | None = None
    aux_seg: bool | None = None
    pretrained: Path | None = None
    from_scratch: bool = False
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


@dataclass
class Launched:
    """A finished `cli train`: the config it trained, the data it trained on and the training's summary."""

    config: Config
    data: Path
    summary: dict


def run_config(options: TrainOptions, given: dict[str, Any]) -> tuple[Config, Path, set[str]]:
    """The config and the data of the run, and on resume the config fields told on the command line
    (`given`: the options given there, by their parameter's name), which run.json logs."""
    data, told = options.data, set()
    if options.resume:
        config, told = resume_config(options.out, given, options.overrides())
        data = data or Path(json.loads((options.out / "run.json").read_text())["data"])
    else:
        pretrained = options.pretrained
        if pretrained is not None and not pretrained.is_file():
            raise ValueError(f"--pretrained {pretrained}: no such file")
        config = resolve_config(options.preset, options.modality, options.epochs, options.batch_size,
                                options.path_points, options.bezier_points, options.aux_seg,
                                str(pretrained) if pretrained else None, options.overrides(), options.model,
                                options.accumulate, options.from_scratch)  # fmt: skip
    if data is None:
        raise ValueError("--data is required")
    return config, data, told


def launch(options: TrainOptions, given: dict[str, Any]) -> Launched:
    """Check the run folder, put the config together and train it (a resume goes on from its checkpoint)."""
    RunFolder.check_free(options.out, options.resume, options.overwrite)
    config, data, told = run_config(options, given)
    summary = train(config, data, options.out, resume=options.resume, stop_after=options.stop_after,
                    overwrite=options.overwrite, told=told)  # fmt: skip
    return Launched(config, data, summary)
