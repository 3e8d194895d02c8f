"""`cli synth`: a tiny synthetic raw dataset, the same world written in the AV2 and nuScenes on-disk formats.

    out/av2/sensor/{train,val}/<log_id>/...   read by the av2 API
    out/nuscenes/{v1.0-mini,maps}/...         read by nuscenes-devkit (scene names from the mini splits)
    out/synth.json                            what was written; "complete" turns true at the very end

Neither devkit is imported here (they take seconds to import): the formats are written directly.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn
from rich.table import Table

from pipeline.synth import av2_writer, nuscenes_map, nuscenes_writer
from pipeline.synth.ids import token
from pipeline.synth.logs import LogPlan, plan_logs
from pipeline.synth.sensors import write_sensors
from pipeline.synth.world import NUSCENES_MAP, build_world

MARKER = "synth.json"


def synth(
    out: Path,
    logs: int = 4,
    frames_per_log: int = 20,
    seed: int = 0,
    sensors: bool = True,
    frame_period: float = 0.1,
) -> dict:
    """Write the dataset into out (replacing an earlier synth output there) and return a summary;
    sensors=False leaves out the camera images and LiDAR sweeps (and the AV2 calibration);
    frame_period: seconds between frames (10 Hz, as both datasets' sweeps, by default)."""
    out = Path(out)
    world = build_world(seed)
    plans = plan_logs(world, logs, frames_per_log, seed, round(frame_period * 1e9))
    av2_root, nuscenes_root = out / "av2" / "sensor", out / "nuscenes"
    summary = {
        "complete": False,
        "seed": seed,
        "frames_per_log": frames_per_log,
        "frame_period": frame_period,
        "sensors": sensors,
        "av2_root": str(av2_root.relative_to(out)),
        "nuscenes_root": str(nuscenes_root.relative_to(out)),
        "nuscenes_version": nuscenes_writer.VERSION,
        "nuscenes_map": NUSCENES_MAP,
        "lanes": len(world.lanes),
        "logs": [_log_summary(plan) for plan in plans],
    }
    _clear(out)
    (out / MARKER).write_text(json.dumps(summary, indent=1))  # says "incomplete" until the end
    prior = f"maps/{token(seed, 'semantic prior')}.png"
    channels = nuscenes_writer.channels(sensors)
    with _LazyProgress(total=len(plans) + 2) as progress:
        nuscenes_map.write_map(nuscenes_root, world, NUSCENES_MAP, prior)
        progress.advance()
        for plan in plans:
            log_dir = av2_writer.write_log(av2_root, world, plan)
            if sensors:
                write_sensors(world, plan, log_dir, nuscenes_root)
            progress.advance()
        nuscenes_writer.write_tables(nuscenes_root, world, plans, channels, NUSCENES_MAP, prior)
        progress.advance()
    summary["complete"] = True
    (out / MARKER).write_text(json.dumps(summary, indent=1))
    _print_summary(out, summary)
    return summary


def _log_summary(plan: LogPlan) -> dict:
    return {"split": plan.split, "log_id": plan.log_id, "scene": plan.scene_name, "route": plan.route.name,
            "frames": len(plan.frame_ns)}  # fmt: skip


def _clear(out: Path) -> None:
    """Remove an earlier synth output (its marker proves it is one); refuse to mix with anything else."""
    ours = [out / "av2", out / "nuscenes"]
    if any(p.exists() for p in ours):
        if not (out / MARKER).is_file():
            raise FileExistsError(f"{out} holds av2/ or nuscenes/ not written by synth; choose another --out")
        for p in ours:
            shutil.rmtree(p, ignore_errors=True)
    out.mkdir(parents=True, exist_ok=True)


class _LazyProgress:
    """A rich progress bar that shows itself only once the work has taken more than a second."""

    def __init__(self, total: int):
        self.bar = Progress(TextColumn("synth"), BarColumn(), MofNCompleteColumn(), transient=True)
        self.task = self.bar.add_task("synth", total=total)
        self.started, self.shown = time.monotonic(), False

    def __enter__(self) -> _LazyProgress:
        return self

    def advance(self) -> None:
        self.bar.advance(self.task)
        if not self.shown and time.monotonic() - self.started > 1.0:
            self.bar.start()
            self.shown = True

    def __exit__(self, *exc) -> None:
        if self.shown:
            self.bar.stop()


def _print_summary(out: Path, summary: dict) -> None:
    title = f"synth: {summary['lanes']} lanes, seed {summary['seed']} -> {out}"
    table = Table(title=title, title_justify="left")
    for column in ("split", "AV2 log id", "nuScenes scene", "route", "frames"):
        table.add_column(column)
    for log in summary["logs"]:
        table.add_row(log["split"], log["log_id"], log["scene"], log["route"], str(log["frames"]))
    Console().print(table)
