"""A training run's folder, RUN_DIR: config.json, run.json, log.jsonl, val.jsonl, tb/ (TensorBoard) and the
checkpoints (baselines/checkpoint.py), for a new run or one resumed, and the files `cli eval` adds
(RUN_FOLDER_FILES, the one list of them); only rank 0 writes.

A folder never mixes two runs: a new run starts only in a folder without a run's files, or with
--overwrite, which removes them all first. A resume goes on with the config its checkpoint was trained
with: a field changed on the resume's command line (`--set`, `--epochs`, ...) is written to config.json and
logged in run.json ("config_changes"); any other difference (config.json edited by hand) is refused by
name. best.pt and run.json's "best" compare validations measured alike only: a resume that validates by
another metric or on other frames starts the best anew (one line, and "best_restarts" in run.json).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path

from rich.console import Console

from baselines.checkpoint import (
    BEST,
    CHECKPOINT,
    DAMAGED,
    PREVIOUS,
    CheckpointError,
    CheckpointWriter,
    copy_atomic,
    peek,
    resume_checkpoint,
)
from baselines.config import Config, TrainConfig
from benchmark.metric.bootstrap import FRAME_COUNTS
from pipeline import io
from pipeline.manifest import PreparedData

console = Console(stderr=True)
TRAINING_FILES = ("config.json", "run.json", "log.jsonl", "val.jsonl", "tb",
                  CHECKPOINT, PREVIOUS, DAMAGED, BEST)  # fmt: skip
SUBMISSION = "submission.pkl"  # cli eval on OpenLane-V2 data: its predictions in OpenLane-V2's format
# benchmark/score.py write_run's, and baselines/evaluate.py's submission
EVALUATION_FILES = ("predictions.parquet", FRAME_COUNTS, "metrics.json", SUBMISSION)
# every file a run folder holds (the one list): `cli train --overwrite` removes them, and refuses without it
RUN_FOLDER_FILES = TRAINING_FILES + EVALUATION_FILES
EVENTS = "events.out.tfevents.*"  # TensorBoard's files, in tb/


def logged_lines(path: Path) -> list[str]:
    """The complete lines of a log (a kill can cut the last one short)."""
    if not path.is_file():
        return []
    return [line for line in path.read_text().splitlines(keepends=True) if line.endswith("\n")]


def half_written(path: Path, name: str) -> list[Path]:
    """The temporary files of `name` that a kill left behind (io.write_atomic's, the checkpoints')."""
    return sorted(path.glob(f".{name}.tmp*"))


def held_files(path: Path) -> list[str]:
    """The names of RUN_FOLDER_FILES that `path` holds, or holds half-written."""
    return [name for name in RUN_FOLDER_FILES if (path / name).exists() or half_written(path, name)]


def remove_run_files(path: Path) -> None:
    """Every file that a run or `cli eval` writes in `path` (RUN_FOLDER_FILES, their half-written
    temporaries, the event files of tb/); anything else in the folder is the user's and stays."""
    for name in RUN_FOLDER_FILES:
        for tmp in half_written(path, name):
            tmp.unlink()
        target = path / name
        if name == "tb":
            for events in target.glob(EVENTS):
                events.unlink()
            if target.is_dir() and not any(target.iterdir()):
                target.rmdir()
        else:
            target.unlink(missing_ok=True)


def measured_as(metric: str, split: str, eval_frames: int, seed: int) -> str:
    """How a validation score is measured, e.g. `miou on 5 frames of 'val' drawn by seed 0`."""
    frames = f"{eval_frames} frames of {split!r} drawn by seed {seed}" if eval_frames else f"all of {split!r}"
    return f"{metric} on {frames}"


def validated_as(config: Config) -> str:
    train = config.train
    return measured_as(train.best_metric, train.val_split, train.eval_frames, train.seed)


@dataclass(frozen=True)
class Best:
    """The validation whose weights best.pt holds: `value` of `metric` at `epoch` (`step`), measured on
    `eval_frames` frames of `split` drawn by `seed` (0: all of them); only values measured alike compare."""

    metric: str
    value: float
    epoch: int
    step: int
    split: str
    eval_frames: int
    seed: int

    @staticmethod
    def of(record: dict, config: Config) -> Best:
        """The best of a validation record (val.jsonl's) by the config's train.best_metric."""
        train = config.train
        return Best(train.best_metric, record[train.best_metric], record["epoch"], record["step"],
                    train.val_split, train.eval_frames, train.seed)  # fmt: skip

    @staticmethod
    def from_record(record: dict, trained: dict | None = None) -> Best | None:
        """A checkpoint's record of it; None when empty or when it does not say how it was measured. A
        record of an earlier version (metric, value, epoch and step only) was measured as the config the
        checkpoint was trained with (`trained`, its "config") validates: its split, frames and seed."""
        names = {field.name for field in dataclasses.fields(Best)}
        if trained is not None and set(record) == {"metric", "value", "epoch", "step"}:
            train = {**dataclasses.asdict(TrainConfig()), **trained.get("train", {})}  # older: defaults
            record = {**record, "split": train["val_split"], "eval_frames": train["eval_frames"],
                      "seed": train["seed"]}  # fmt: skip
        return Best(**record) if set(record) == names else None

    def measured(self) -> str:
        return measured_as(self.metric, self.split, self.eval_frames, self.seed)


@dataclass(frozen=True)
class ConfigChange:
    """A config field changed on the command line of a resume, at `step`: logged in run.json."""

    field: str
    before: object  # the value the checkpoint was trained with (JSON)
    after: object
    step: int


def flat_config(values: dict) -> dict[str, object]:
    """A Config.to_dict() as {section.field: its JSON value}, named as --set names them."""
    flat = {}
    for key, value in values.items():
        if isinstance(value, dict):
            flat.update({f"{key}.{name}": json.loads(json.dumps(item)) for name, item in value.items()})
        else:
            flat[key] = json.loads(json.dumps(value))
    return flat


def shown(value: object) -> str:
    """A config value as --set takes it (`3,5` for a tuple)."""
    return ",".join(map(str, value)) if isinstance(value, list) else str(value)


def config_changes(trained: dict, going_on: dict, told: Collection[str], logged: list[dict], step: int,
                   checkpoint: Path, config_file: Path) -> list[ConfigChange]:  # fmt: skip
    """The fields in which the config a resume goes on with (`going_on`) differs from the one its
    checkpoint (at `step`) was trained with: each one `told` (set on the resume's command line) is returned;
    one logged by an earlier resume from this step on (`logged`, run.json's) is kept as it is; any other is
    refused in one line naming it. A field that one of the two configs lacks (another version) is not
    compared."""
    before, after = flat_config(trained), flat_config(going_on)
    explained = {change["field"]: change["after"] for change in logged if change["step"] >= step}
    changes, unexplained = [], []
    for name in sorted(before.keys() & after.keys()):
        if before[name] == after[name]:
            continue
        if name in told:
            changes.append(ConfigChange(name, before[name], after[name], step))
        elif name not in explained or explained[name] != after[name]:
            unexplained.append(name)
    if unexplained:
        was = ", ".join(f"{name}={shown(before[name])}" for name in unexplained)
        now = ", ".join(f"{name}={shown(after[name])}" for name in unexplained)
        first = unexplained[0]
        raise CheckpointError(
            f"{checkpoint}: trained with {was}, but {config_file} has {now}, a change not given on the "
            f"command line: give it with --resume as --set {first}={shown(after[first])} (then it is logged "
            f"in run.json), or put {was} back"
        )
    return changes


def check_steps_per_epoch(trained: dict | None, now: TrainConfig, frames: int, world_size: int) -> None:
    """A resume may change how a batch splits into micro-batches (train.accumulate,
    max_batch_per_device) where that keeps the optimiser steps per epoch of the checkpoint's run (its
    config `trained`), on which the step count, the schedule and the place inside an interrupted epoch
    stand; otherwise refused in one line. `frames`: the training split's, over `world_size` processes."""
    if trained is None:  # a checkpoint of an earlier version: nothing to compare
        return
    names = ("batch_size", "accumulate", "max_batch_per_device")
    before = dataclasses.replace(now, **{name: trained["train"][name] for name in names
                                         if name in trained.get("train", {})})  # fmt: skip
    old, new = before.steps_per_epoch(frames, world_size), now.steps_per_epoch(frames, world_size)
    if old != new:
        changed = ", ".join(f"train.{name} {getattr(before, name)} -> {getattr(now, name)}"
                            for name in names if getattr(before, name) != getattr(now, name))  # fmt: skip
        raise CheckpointError(
            f"{changed} on --resume: {new} optimiser steps per epoch, the checkpoint's run had {old} (the "
            "epoch's last frames split otherwise): its step count, schedule and place in the epoch stand on "
            f"them; resume with the micro-batches it had or with ones that keep {old}"
        )


class RunFolder:
    """RUN_DIR (the module's docstring): a new run or one resumed, its logs, its TensorBoard events and
    its checkpoints. Only rank 0 (`master`) writes."""

    def __init__(self, path: Path, master: bool):
        self.path, self.master = path, master
        self.log_file = self.val_file = self.events = None
        self.writer = CheckpointWriter()
        # (file, step, fp16 loss scale or None) of the last one written or resumed from
        self.last_checkpoint: tuple[Path, int, float | None] | None = None
        self.best: Best | None = None  # what best.pt holds, or None: the next validation is the best
        self.resumed_from: Path | None = None  # the checkpoint file a resume loaded
        self.changes: list[ConfigChange] = []  # the config fields a resume changes

    @staticmethod
    def check_free(path: Path, resume: bool, overwrite: bool) -> None:
        """Refuse to start afresh in a folder that holds a run's files: the two runs would mix."""
        if resume and overwrite:
            raise ValueError("--resume and --overwrite: give one of them (--resume continues the run in "
                             "--out, --overwrite starts it afresh)")  # fmt: skip
        held = held_files(path)
        if held and not resume and not overwrite:
            raise ValueError(f"{path} holds a run already ({', '.join(held)}): continue it with --resume, "
                             "start it afresh with --overwrite (which removes those files first), or choose "
                             "another --out")  # fmt: skip

    def start(self, config: Config, run: dict) -> None:
        """A new run: every file of an earlier one removed (--overwrite; remove_run_files), then
        config.json, run.json (`run`) and empty logs."""
        if self.master:
            self.path.mkdir(parents=True, exist_ok=True)
            remove_run_files(self.path)
            config.save(self.path / "config.json")
            (self.path / "run.json").write_text(json.dumps(run, indent=2) + "\n")
            (self.path / "log.jsonl").write_text("")
            (self.path / "val.jsonl").write_text("")

    def resume(self, data: PreparedData, config: Config, told: Collection[str] = ()) -> dict:
        """The checkpoint to continue the run from (resume_checkpoint), after refusing stale data (the
        dataset must have the targets the run was trained on) and a config that differs from the
        checkpoint's in a field not `told` (config_changes). Writes nothing."""
        record = self.run_json()
        data.check_targets(record.get("targets", {}), f"the run {self.path}")
        checkpoint, self.resumed_from = resume_checkpoint(self.path, self.master)
        if "config" in checkpoint:  # every checkpoint of this version records it
            self.changes = config_changes(checkpoint["config"], config.to_dict(), told,
                                          record.get("config_changes", []), checkpoint["step"],
                                          self.resumed_from, self.path / "config.json")  # fmt: skip
        return checkpoint

    def resumed(self, checkpoint: dict, config: Config) -> None:
        """The run goes on from `checkpoint` (loaded into the trainer) with `config`: config.json and the
        changes in run.json; best.pt and run.json's best as the checkpoint has them (a kill while they were
        written repaired; an earlier version's record completed by Best.from_record), or started anew when
        this run validates otherwise; the log and validation lines
        of steps after the checkpoint (an interrupted epoch) dropped."""
        step = checkpoint["step"]
        self.last_checkpoint = (self.resumed_from, step, checkpoint["scaler"].get("scale"))
        self.best = Best.from_record(checkpoint.get("best") or {}, checkpoint.get("config"))
        recorded = self.best_record() or checkpoint.get("best") or {}  # an earlier version's, completed
        if self.master:
            self.write_config(config, step)
            self.repair_best(checkpoint, recorded)
        if recorded and (self.best is None or self.best.measured() != validated_as(config)):
            self.restart_best(recorded, config, step)
        if self.master:
            for name in ("log.jsonl", "val.jsonl"):
                lines = logged_lines(self.path / name)
                kept = "".join(line for line in lines if json.loads(line)["step"] <= step)
                io.write_atomic(self.path / name, lambda tmp, kept=kept: tmp.write_text(kept))

    def write_config(self, config: Config, step: int) -> None:
        """config.json as the run goes on, and this resume's changes logged in run.json (a resume from the
        same step again replaces its entries)."""
        values = config.to_dict()
        config_file = self.path / "config.json"
        if json.loads(config_file.read_text()) != json.loads(json.dumps(values)):
            io.write_json(config_file, values)
        if not self.changes:
            return
        record = self.run_json()
        again = {(change.field, change.step) for change in self.changes}
        kept = [c for c in record.get("config_changes", []) if (c["field"], c["step"]) not in again]
        logged = kept + [dataclasses.asdict(change) for change in self.changes]
        io.write_json(self.path / "run.json", {**record, "config_changes": logged})
        changed = ", ".join(f"{c.field} {shown(c.before)} -> {shown(c.after)}" for c in self.changes)
        console.print(f"resumed at step {step} with {changed} (config.json, and config_changes in run.json)",
                      soft_wrap=True, markup=False, highlight=False)  # fmt: skip

    def repair_best(self, checkpoint: dict, recorded: dict) -> None:
        """best.pt and run.json's best as the checkpoint records them: a run stopped between the checkpoint
        of its best validation and its copy to best.pt gets the copy now."""
        if not recorded:
            return
        best_file = self.path / BEST
        held = peek(best_file)
        own = recorded["step"] == checkpoint["step"]  # the best is the checkpoint's own weights
        if own and (held is None or held["sha256"] != checkpoint["sha256"]):
            copy_atomic(self.resumed_from, best_file)
            console.print(f"{best_file}: did not hold the best validation's weights (step "
                          f"{checkpoint['step']}: the run stopped before it copied them): copied from "
                          f"{self.resumed_from.name}",
                          soft_wrap=True, markup=False, highlight=False)  # fmt: skip
            held = peek(best_file)
        record = self.run_json()
        if held is not None and held["step"] == recorded["step"] and record.get("best") != recorded:
            io.write_json(self.path / "run.json", {**record, "best": recorded})

    def restart_best(self, recorded: dict, config: Config, step: int) -> None:
        """The next validation is the best: the checkpoint's best was measured otherwise (another
        --best-metric, --eval-frames, split or seed). best.pt and run.json's best stay until it replaces
        them; said in one line and in run.json's best_restarts."""
        self.best = None
        if not self.master:
            return
        was = self.best_was(recorded)
        now = validated_as(config)
        console.print(f"best.pt starts anew: it holds the best {was}; this run validates by {now}",
                      soft_wrap=True, markup=False, highlight=False)  # fmt: skip
        record = self.run_json()
        restarts = [entry for entry in record.get("best_restarts", []) if entry["step"] != step]
        restarts.append({"step": step, "previous": recorded, "now": now})
        io.write_json(self.path / "run.json", {**record, "best_restarts": restarts})

    @staticmethod
    def best_was(recorded: dict) -> str:
        best = Best.from_record(recorded)
        if best is None:  # an earlier version's record
            value, step = recorded.get("value"), recorded.get("step")
            return f"{recorded.get('metric')} ({value} at step {step}), on frames not recorded"
        return f"{best.measured()} ({best.value:.4f} at step {best.step})"

    def best_record(self) -> dict:
        """run.best as checkpoints, run.json and the summary keep it ({}: none yet)."""
        return dataclasses.asdict(self.best) if self.best else {}

    def open_logs(self, first_step: int) -> None:
        """log.jsonl and val.jsonl to append to; TensorBoard events in tb/, those of steps after
        `first_step` (an interrupted run's) dropped."""
        if self.master:
            from torch.utils.tensorboard import SummaryWriter

            self.log_file = (self.path / "log.jsonl").open("a")
            self.val_file = (self.path / "val.jsonl").open("a")
            self.events = SummaryWriter(str(self.path / "tb"), purge_step=first_step + 1, flush_secs=20)

    def log(self, record: dict, scalars: dict[str, float]) -> None:
        self.log_file.write(json.dumps(record) + "\n")
        self.log_file.flush()
        for tag, value in scalars.items():
            self.events.add_scalar(tag, value, record["step"])

    def log_validation(self, record: dict) -> None:
        self.val_file.write(json.dumps(record) + "\n")
        self.val_file.flush()
        for name, value in record.items():
            if name not in ("step", "epoch", "split", "frames"):
                self.events.add_scalar(f"val/{name}", value, record["step"])
        self.events.flush()

    def save(self, state: dict, best: bool) -> None:
        """checkpoint.pt (the one it replaces becomes checkpoint.prev.pt), and best.pt too when `best`,
        and then run.json's best: written on the writer's thread, in that order, so that run.json never
        names a best that best.pt does not hold."""
        path = self.path / CHECKPOINT
        self.last_checkpoint = (path, state["step"], state["scaler"].get("scale"))  # {} without fp16
        if not self.master:
            return
        if best:
            record = state["best"]

            def record_best() -> None:
                io.write_json(self.path / "run.json", {**self.run_json(), "best": record})

            self.writer.write(state, path, copies=[self.path / BEST], then=record_best)
        else:
            self.writer.write(state, path)

    def run_json(self) -> dict:
        return json.loads((self.path / "run.json").read_text())

    def close(self) -> None:
        """Every checkpoint on disk and every log closed (raises what a checkpoint's writing raised)."""
        for log in (self.log_file, self.val_file, self.events):
            if log is not None:
                log.close()
        self.log_file = self.val_file = self.events = None
        self.writer.wait()

    def finish(self, summary: dict) -> None:
        """Close the logs; the summary into run.json."""
        self.close()
        if self.master:
            io.write_json(self.path / "run.json", {**self.run_json(), "summary": summary})
