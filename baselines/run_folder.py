"""A training run's folder, RUN_DIR: config.json, run.json, log.jsonl, val.jsonl, tb/ (TensorBoard) and the
checkpoints (baselines/checkpoint.py), for a new run or one resumed; only rank 0 writes."""

from __future__ import annotations

import json
from pathlib import Path

from baselines.checkpoint import BEST, CHECKPOINT, CheckpointWriter, resume_checkpoint
from baselines.config import Config
from pipeline import io
from pipeline.manifest import PreparedData


def logged_lines(path: Path) -> list[str]:
    """The complete lines of a log (a kill can cut the last one short)."""
    if not path.is_file():
        return []
    return [line for line in path.read_text().splitlines(keepends=True) if line.endswith("\n")]


class RunFolder:
    """RUN_DIR (the module's docstring): a new run or one resumed, its logs, its TensorBoard events and
    its checkpoints. Only rank 0 (`master`) writes."""

    def __init__(self, path: Path, master: bool):
        self.path, self.master = path, master
        self.log_file = self.val_file = self.events = None
        self.writer = CheckpointWriter()
        self.last_checkpoint: tuple[Path, int] | None = None  # (file, step) of the last one written
        self.best: dict = {}  # metric, value, epoch, step of best.pt

    @staticmethod
    def check_free(path: Path, resume: bool, overwrite: bool) -> None:
        """Refuse to start afresh in a folder that holds a run: its checkpoint and log would be replaced."""
        if not resume and not overwrite and (path / "config.json").exists():
            raise ValueError(f"{path} holds a run already: continue it with --resume, start it afresh with "
                             "--overwrite, or choose another --out")  # fmt: skip

    def start(self, config: Config, run: dict) -> None:
        """A new run: config.json, run.json (`run`) and empty logs (an --overwrite'n run's files go)."""
        if self.master:
            self.path.mkdir(parents=True, exist_ok=True)
            for stale in (BEST, "val.jsonl"):
                (self.path / stale).unlink(missing_ok=True)
            config.save(self.path / "config.json")
            (self.path / "run.json").write_text(json.dumps(run, indent=2) + "\n")
            (self.path / "log.jsonl").write_text("")
            (self.path / "val.jsonl").write_text("")

    def resume(self, data: PreparedData) -> dict:
        """The checkpoint to continue the run from (resume_checkpoint), after refusing stale data (the
        dataset must have the targets the run was trained on)."""
        data.check_targets(self.run_json().get("targets", {}), f"the run {self.path}")
        return resume_checkpoint(self.path, self.master)

    def resumed(self, checkpoint: dict) -> None:
        """The run goes on from `checkpoint` (loaded into the trainer): its best so far, and the log and
        validation lines of steps after it (an interrupted epoch) dropped."""
        self.best = checkpoint.get("best", {})
        self.last_checkpoint = (self.path / CHECKPOINT, checkpoint["step"])
        if self.master:
            for name in ("log.jsonl", "val.jsonl"):
                lines = logged_lines(self.path / name)
                kept = "".join(line for line in lines if json.loads(line)["step"] <= checkpoint["step"])
                io.write_atomic(self.path / name, lambda tmp, kept=kept: tmp.write_text(kept))

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
        """checkpoint.pt (the one it replaces becomes checkpoint.prev.pt), and best.pt too when `best`;
        written on the writer's thread."""
        path = self.path / CHECKPOINT
        self.last_checkpoint = (path, state["step"])
        if self.master:
            self.writer.write(state, path, copies=[self.path / BEST] if best else [])
            if best:
                io.write_json(self.path / "run.json", {**self.run_json(), "best": self.best})

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
