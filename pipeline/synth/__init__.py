"""`cli synth`: a tiny synthetic raw dataset, the same world written in the AV2 and nuScenes on-disk formats,
and OpenLane-V2's (subset A) converted from the AV2 logs.

    out/av2/sensor/{train,val}/<log_id>/...   read by the av2 API
    out/nuscenes/{v1.0-mini,maps}/...         read by nuscenes-devkit (v1.0-mini's split scene names;
                                              v1.0-trainval's beyond 8 training logs)
    out/openlanev2/{train,val}/<log_id>/...   OpenLane-V2's frame files, images hard-linked to the AV2 logs'

Logs spread over `worlds` procedural worlds (one nuScenes map location / AV2 city each); validation logs
drive only in the last `val_worlds`, which no training log visits: a geographically disjoint split.
    out/synth.json                            what was written; "complete" turns true at the very end

Neither devkit is imported here (they take seconds to import): the formats are written directly.
"""

from __future__ import annotations

import functools
import json
import shutil
import time
from pathlib import Path

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn
from rich.table import Table

from pipeline.executor import run_local
from pipeline.synth import av2_writer, nuscenes_map, nuscenes_writer, openlanev2_writer
from pipeline.synth.ids import token
from pipeline.synth.logs import MAX_LOGS, POSE_PERIOD_NS, LogPlan, nuscenes_version, plan_logs
from pipeline.synth.sensors import write_sensors
from pipeline.synth.world import MAX_WORLDS, World, build_world

MARKER = "synth.json"


def synth(
    out: Path,
    logs: int = 18,
    frames_per_log: int = 10,
    seed: int = 0,
    sensors: bool = True,
    frame_period: float = 2.0,
    worlds: int = 4,
    val_worlds: int = 1,
    workers: int = 1,
    val_frames_per_log: int = 20,
    val_frame_period: float = 1.0,
) -> dict:
    """Write the dataset into out (replacing an earlier synth output there) and return a summary;
    sensors=False leaves out the camera images and LiDAR sweeps (and the AV2 calibration);
    frame_period: seconds between frames (2 s: 10 frames cover much of a route; both datasets sweep at
    10 Hz, 0.1 s); val_frames_per_log and val_frame_period: the same for the validation logs;
    workers: processes writing the logs, one log at a time each (the same bytes as one).
    The defaults are the learning checks' data: 16 training logs x 10 frames 2 s apart, 2 validation
    logs x 20 frames 1 s apart (more routes in training, 40 validation frames; docs/EXPERIMENTS.md)."""
    out = Path(out)
    check_arguments(logs, frames_per_log, seed, frame_period, worlds, val_worlds, workers, val_frames_per_log,
                    val_frame_period)  # fmt: skip
    built = [build_world(seed, k) for k in range(worlds)]
    plans = plan_logs(built, logs, frames_per_log, seed, round(frame_period * 1e9), val_worlds,
                      val_frames_per_log, round(val_frame_period * 1e9))  # fmt: skip
    driven = sorted({plan.world for plan in plans})
    av2_root, nuscenes_root, openlanev2_root = out / "av2" / "sensor", out / "nuscenes", out / "openlanev2"
    summary = {
        "complete": False,
        "seed": seed,
        "frames_per_log": frames_per_log,
        "frame_period": frame_period,
        "val_frames_per_log": val_frames_per_log,
        "val_frame_period": val_frame_period,
        "sensors": sensors,
        "av2_root": str(av2_root.relative_to(out)),
        "nuscenes_root": str(nuscenes_root.relative_to(out)),
        "openlanev2_root": str(openlanev2_root.relative_to(out)),
        "nuscenes_version": nuscenes_version(plans),
        "worlds": [_world_summary(built[k], plans) for k in range(worlds)],
        "logs": [_log_summary(plan, built[plan.world]) for plan in plans],
    }
    _clear(out)
    (out / MARKER).write_text(json.dumps(summary, indent=1))  # says "incomplete" until the end
    priors = {k: f"maps/{token(seed, 'semantic prior', k)}.png" for k in driven}
    channels = nuscenes_writer.channels(sensors)
    with _LazyProgress(total=len(plans) + len(driven) + 1) as progress:
        for k in driven:
            nuscenes_map.write_map(nuscenes_root, built[k], built[k].nuscenes_map, priors[k])
            progress.advance()
        write = functools.partial(_write_log, built, av2_root, nuscenes_root, openlanev2_root, sensors)
        run_local(plans, write, min(workers, len(plans)), lambda plan, _: progress.advance())
        nuscenes_writer.write_tables(nuscenes_root, built, plans, channels, priors)
        progress.advance()
    summary["complete"] = True
    (out / MARKER).write_text(json.dumps(summary, indent=1))
    return summary


def _write_log(
    built: list[World],
    av2_root: Path,
    nuscenes_root: Path,
    openlanev2_root: Path,
    sensors: bool,
    plan: LogPlan,
) -> None:
    """One log's AV2 files and, with sensors, its images and sweeps in both formats (its own seeded
    random stream: the order of the logs does not change a byte); then the AV2 log as OpenLane-V2's."""
    log_dir = av2_writer.write_log(av2_root, built[plan.world], plan)
    if sensors:
        write_sensors(built[plan.world], plan, log_dir, nuscenes_root)
    openlanev2_writer.write_from_av2(log_dir, openlanev2_root, plan.split)


def check_arguments(
    logs: int,
    frames_per_log: int,
    seed: int,
    frame_period: float,
    worlds: int,
    val_worlds: int,
    workers: int,
    val_frames_per_log: int,
    val_frame_period: float,
) -> None:
    """Refuse bad arguments before the worlds are built, each named as its `cli synth` option."""
    if not 1 <= logs <= MAX_LOGS:
        raise ValueError(f"--logs must be 1 to {MAX_LOGS} (the nuScenes scene names held here), not {logs}")
    shapes = (("", frames_per_log, frame_period), ("val-", val_frames_per_log, val_frame_period))
    for prefix, frames, period in shapes:
        if frames < 1:
            raise ValueError(f"--{prefix}frames-per-log must be at least 1, not {frames}")
        period_ns = round(period * 1e9)
        if period_ns <= 0 or period_ns % POSE_PERIOD_NS:
            raise ValueError(
                f"--{prefix}frame-period {period} is not a positive multiple of {POSE_PERIOD_NS / 1e9} s "
                "(the pose period)"
            )
    if seed < 0:
        raise ValueError(f"--seed must be at least 0, not {seed}")
    if workers < 1:
        raise ValueError(f"--workers must be at least 1, not {workers}")
    if not 1 <= worlds <= MAX_WORLDS:
        raise ValueError(f"--worlds must be 1 to {MAX_WORLDS} (one nuScenes map location each), not {worlds}")
    if worlds > 1 and not 1 <= val_worlds < worlds:
        raise ValueError(
            f"--val-worlds {val_worlds} must be at least 1 and fewer than --worlds {worlds} (training "
            "needs a world of its own)"
        )


def _log_summary(plan: LogPlan, world: World) -> dict:
    return {"split": plan.split, "log_id": plan.log_id, "scene": plan.scene_name, "route": plan.route.name,
            "world": plan.world, "nuscenes_map": world.nuscenes_map,
            "frames": len(plan.frame_ns)}  # fmt: skip


def _world_summary(world: World, plans: list[LogPlan]) -> dict:
    splits = sorted({plan.split for plan in plans if plan.world == world.index})
    return {"index": world.index, "nuscenes_map": world.nuscenes_map, "av2_city": world.av2_city,
            "lanes": len(world.lanes), "junction_arms": world.landmarks.intersection_arms,
            "roundabout_arms": len(world.landmarks.roundabout_entries), "splits": splits}  # fmt: skip


def _clear(out: Path) -> None:
    """Remove an earlier synth output (its marker proves it is one); refuse to mix with anything else."""
    ours = [out / "av2", out / "nuscenes", out / "openlanev2"]
    if any(p.exists() for p in ours):
        if not (out / MARKER).is_file():
            raise FileExistsError(
                f"{out} holds av2/, nuscenes/ or openlanev2/ not written by synth; choose another --out"
            )
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


def summary_table(summary: dict) -> Table:
    """The logs of a synth summary: split, world, ids, route and frames (`cli synth` prints it)."""
    table = Table()
    for column in ("split", "world", "AV2 log id", "nuScenes scene", "route", "frames"):
        table.add_column(column, overflow="fold")  # a narrow terminal folds the long ids
    for log in summary["logs"]:
        table.add_row(
            log["split"], str(log["world"]), log["log_id"], log["scene"], log["route"], str(log["frames"])
        )
    return table
