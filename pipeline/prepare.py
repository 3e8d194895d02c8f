"""`cli prepare`: every log of a raw dataset -> one shard per table of the prepared Parquet dataset."""

from __future__ import annotations

import functools
import json
import resource
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from importlib import metadata
from pathlib import Path

import numpy as np
import pyarrow as pa
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from pipeline import io
from pipeline.errors import DataError
from pipeline.executor import import_ray, run_local, run_ray
from pipeline.geometry import matrix_quaternion
from pipeline.lane_graph import LaneMap
from pipeline.records import Frame, Log
from pipeline.targets import FrameTargets, TargetOptions, flat_pose, frame_targets, warm_up

console = Console(stderr=True)


@dataclass(frozen=True)
class Job:
    """One log to prepare: what a worker needs to find and read it."""

    dataset: str
    split: str
    name: str
    n_frames: int
    ref: object  # av2: the log folder; nuscenes: a SceneRef
    root: Path


@dataclass
class LogResult:
    shard: str
    frames: int = 0
    paths: int = 0
    pieces: int = 0
    junctions: int = 0
    cap_hits: int = 0
    skipped: int = 0
    errors: list[dict] = field(default_factory=list)
    peak_mib: float = 0.0  # peak resident memory of the process that prepared it, so far


def find_jobs(dataset: str, root: Path, version: str, split: str | None, frame_stride: int) -> list[Job]:
    if dataset == "av2":
        from pipeline.adapters import av2

        return [
            Job("av2", s, d.name, -(-len(av2.frame_timestamps(d)) // frame_stride), d, root)
            for s, d in av2.find_logs(root, split)
        ]
    if dataset == "nuscenes":
        from pipeline.adapters import nuscenes

        return [
            Job("nuscenes", r.split, r.name, -(-r.n_frames // frame_stride), r, root)
            for r in nuscenes.find_scenes(root, version, split)
        ]
    raise ValueError(f"unknown dataset {dataset!r}: expected av2 or nuscenes")


def no_logs_found(dataset: str, root: Path, version: str, split: str | None) -> str:
    """The error of a root (and split) without a log: what was looked for where (a wrong --root or
    --dataset would otherwise prepare 0 frames and leave a manifest behind)."""
    in_split = f" in split {split}" if split else ""
    if dataset == "av2":
        folders = sorted(p.name for p in root.iterdir() if p.is_dir())
        return (
            f"{root}: no AV2 log{in_split} (looked for ROOT/{split or '<split>'}/<log id>/map/; the folders "
            f"here: {', '.join(folders) or 'none'}); --root is the folder that holds train/, val/, ..."
        )
    return f"{root}: no nuScenes scene{in_split} in the {version} tables (looked in {root / version})"


def option_name(parameter: str) -> str:
    """The `cli prepare` option of a manifest parameter."""
    return {"bev_range": "--range", "split_files": "--split-file"}.get(
        parameter, f"--{parameter.replace('_', '-')}"
    )


def shown(value) -> str:
    """A manifest parameter as the command line writes it."""
    if isinstance(value, dict):  # split files
        return ",".join(f"{name}={path}" for name, path in value.items())
    return "none" if value is None else str(value)


def check_options(
    options: TargetOptions, frame_stride: int, workers: int, on_error: str, executor: str
) -> None:
    """Refuse values that would crash or mean nothing later (a 0-point resample ends the interpreter), each
    named as its `cli prepare` option; the command line refuses most of them already."""
    at_least = {"--path-points": (options.path_points, 2), "--piece-points": (options.piece_points, 2),
                "--max-paths": (options.max_paths, 1), "--line-width": (options.line_width, 1),
                "--frame-stride": (frame_stride, 1), "--workers": (workers, 1)}  # fmt: skip
    for name, (value, least) in at_least.items():
        if value < least:
            raise ValueError(f"{name} must be at least {least}, not {value}")
    if not options.resolution > 0:
        raise ValueError(f"--resolution must be greater than 0, not {options.resolution}")
    rows, cols = options.grid.shape
    if rows < 1 or cols < 1:
        raise ValueError(
            f"--resolution {options.resolution} leaves no raster cell ({rows} x {cols}) in --range "
            f"{options.bev_range.text}"
        )
    if on_error not in ("fail", "skip"):
        raise ValueError(f"--on-error must be fail or skip, not {on_error!r}")
    if executor not in ("local", "ray"):
        raise ValueError(f"--executor must be local or ray, not {executor!r}")


def read_split_files(split_files: dict[str, Path]) -> dict[str, str]:
    """{log id or scene name: split} from one file of names (one per line) per split, e.g. the
    geographically disjoint splits of StreamMapNet. A name in two files is an error."""
    split_of: dict[str, str] = {}
    for split, path in split_files.items():
        if not Path(path).is_file():
            raise FileNotFoundError(f"{path}: split file of split {split!r} not found")
        for number, line in enumerate(Path(path).read_text().splitlines(), 1):
            name = line.strip()
            if not name or name.startswith("#"):
                continue
            if split_of.get(name, split) != split:
                raise DataError(path, f"line {number}", f"{name} is already in split {split_of[name]!r}")
            split_of[name] = split
    return split_of


def load_job(job: Job, frame_stride: int, options: TargetOptions) -> Log:
    if job.dataset == "av2":
        from pipeline.adapters import av2

        return av2.load_log(job.root, job.split, job.ref, frame_stride)
    from pipeline.adapters import nuscenes

    log = nuscenes.load_log(job.ref, options.bev_range.radius)
    log.frames = log.frames[::frame_stride]
    return log


def frame_row(frame: Frame, targets: FrameTargets) -> dict:
    return {
        "frame_id": frame.frame_id,
        "dataset": frame.dataset,
        "split": frame.split,
        "sample_token": frame.sample_token,
        "log_id": frame.log_id,
        "timestamp_ns": frame.timestamp_ns,
        "city": frame.city,
        "pose_translation": frame.ego_to_world[:3, 3].tolist(),
        "pose_rotation": matrix_quaternion(frame.ego_to_world).tolist(),
        "cameras": [
            {
                "name": c.name,
                "image_path": c.image_path,
                "intrinsics": np.asarray(c.intrinsics, np.float64).ravel().tolist(),
                "sensor_to_ego": np.asarray(c.sensor_to_ego, np.float64).ravel().tolist(),
                "width": c.width,
                "height": c.height,
            }
            for c in frame.cameras
        ],
        "lidar_path": frame.lidar_path,
        "lidar_to_ego": np.asarray(frame.lidar_to_ego, np.float64).ravel().tolist(),
        "ground_z": frame.ground_z,
        "ground_slope": [float(v) for v in frame.ground_slope],
        "n_vertices": len(targets.graph.x),
        "n_edges": len(targets.graph.src),
        "n_paths": len(targets.paths.vertex_ids),
        "n_pieces": len(targets.pieces.chains),
        "n_junctions": len(targets.pieces.junctions),
        "path_cap_hit": targets.paths.cap_hit,
    }


def chain_table(
    frame_ids: list[str], chains: list[list[np.ndarray]], graphs, points, lengths, index: str
) -> pa.Table:
    """Rows of paths or pieces: one per chain, with its vertex ids, full polyline and resampled points."""
    flat = [c for frame_chains in chains for c in frame_chains]
    xs = [g.x[c] for g, frame_chains in zip(graphs, chains) for c in frame_chains]
    ys = [g.y[c] for g, frame_chains in zip(graphs, chains) for c in frame_chains]
    resampled = np.concatenate(points).astype(np.float32) if flat else np.zeros((0, 1, 2), np.float32)
    counts = [len(c) for c in chains]
    return pa.table(
        {
            "frame_id": pa.array(np.repeat(frame_ids, counts).tolist(), pa.string()),
            index: pa.array(np.concatenate([np.arange(n) for n in counts] or [[]]).astype(np.int32)),
            "vertex_ids": io.list_array([c.astype(np.int32) for c in flat], pa.int32()),
            "x": io.list_array(xs, pa.float32()),
            "y": io.list_array(ys, pa.float32()),
            "rx": io.list_array(list(resampled[:, :, 0]), pa.float32()),
            "ry": io.list_array(list(resampled[:, :, 1]), pa.float32()),
            "length": pa.array(np.concatenate(lengths or [[]]).astype(np.float32)),
        }
    )


def log_tables(
    frames: list[Frame], targets: list[FrameTargets], options: TargetOptions
) -> dict[str, pa.Table]:
    ids = [f.frame_id for f in frames]
    graphs = [t.graph for t in targets]
    height, width = options.grid.shape
    links = [(t.pieces.link_src, t.pieces.link_dst) for t in targets]
    return {
        "frames": pa.Table.from_pylist(list(map(frame_row, frames, targets)), io.SCHEMAS["frames"]),
        "graphs": pa.table(
            {
                "frame_id": pa.array(ids, pa.string()),
                "x": io.list_array([g.x for g in graphs], pa.float32()),
                "y": io.list_array([g.y for g in graphs], pa.float32()),
                "src": io.list_array([g.src for g in graphs], pa.int32()),
                "dst": io.list_array([g.dst for g in graphs], pa.int32()),
            }
        ),
        "paths": chain_table(
            ids, [t.paths.vertex_ids for t in targets], graphs,
            [t.path_points for t in targets], [t.path_lengths for t in targets], "path_index",
        ),
        "pieces": chain_table(
            ids, [t.pieces.chains for t in targets], graphs,
            [t.piece_points for t in targets], [t.piece_lengths for t in targets], "piece_index",
        ),
        "piece_links": pa.table(
            {
                "frame_id": pa.array(np.repeat(ids, [len(s) for s, _ in links]).tolist(), pa.string()),
                "src_piece": pa.array(np.concatenate([s for s, _ in links] or [[]]).astype(np.int32)),
                "dst_piece": pa.array(np.concatenate([d for _, d in links] or [[]]).astype(np.int32)),
            }
        ),
        "rasters": pa.table(
            {
                "frame_id": pa.array(ids, pa.string()),
                "height": pa.array([height] * len(ids), pa.int32()),
                "width": pa.array([width] * len(ids), pa.int32()),
                "resolution": pa.array([options.resolution] * len(ids), pa.float32()),
                "line_width": pa.array([options.line_width] * len(ids), pa.int32()),
                "mask": pa.array([io.encode_mask(t.mask) for t in targets], pa.binary()),
                "direction": pa.array([io.encode_raster(t.direction) for t in targets], pa.binary()),
            }
        ),
    }  # fmt: skip


def prepare_log(
    job: Job, out: Path, options: TargetOptions, frame_stride: int, on_error: str, on_frame=None
) -> LogResult:
    """Prepare one log and write its shards; bad frames raise (fail) or are recorded (skip)."""
    result = LogResult(f"{job.split}__{job.name}")
    try:
        log = load_job(job, frame_stride, options)
    except DataError as error:
        if on_error == "fail":
            raise
        result.errors.append({"log": job.name, "frame_id": None, "source": error.source, "error": str(error)})
        result.skipped = job.n_frames
        return result
    lane_map = LaneMap.from_lanes(log.lanes)
    frames, targets = [], []
    for frame in log.frames:
        frame.split = job.split  # a split file may have moved the log to another split
        try:
            if not np.isfinite(frame.ego_to_world).all():
                raise DataError(
                    log.pose_source, f"frame {frame.frame_id}", "ego pose has NaN or infinite values"
                )
            pose = flat_pose(frame.ego_to_world) if log.map_is_2d else frame.ego_to_world
            targets.append(frame_targets(lane_map, pose, options))
            frames.append(frame)
        except DataError as error:
            if on_error == "fail":
                raise
            result.errors.append(
                {"log": job.name, "frame_id": frame.frame_id, "source": error.source, "error": str(error)}
            )
            result.skipped += 1
        if on_frame:
            on_frame()
    io.write_shard(out, result.shard, log_tables(frames, targets, options))
    result.frames = len(frames)
    result.paths = sum(len(t.paths.vertex_ids) for t in targets)
    result.pieces = sum(len(t.pieces.chains) for t in targets)
    result.junctions = sum(len(t.pieces.junctions) for t in targets)
    result.cap_hits = sum(t.paths.cap_hit for t in targets)
    result.peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return result


def package_versions() -> dict[str, str]:
    names = (
        "numpy",
        "shapely",
        "pyarrow",
        "scipy",
        "numba",
        "opencv-python-headless",
        "av2",
        "nuscenes-devkit",
    )
    versions = {}
    for name in names:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    return versions


def select_jobs(
    dataset: str, root: Path, version: str, split: str | None, frame_stride: int,
    split_files: dict[str, Path] | None,
) -> tuple[list[Job], int]:  # fmt: skip
    """The logs to prepare and how many logs the split files leave out; a root without one is an error
    (a wrong --root or --dataset would otherwise prepare 0 frames and leave a manifest behind)."""
    if split_files:  # the files' splits replace the dataset's own; --split then picks one of theirs
        found = find_jobs(dataset, root, version, None, frame_stride)
        split_of = read_split_files(split_files)
        named = [replace(job, split=split_of[job.name]) for job in found if job.name in split_of]
        jobs = [job for job in named if split is None or job.split == split]
        left_out = len(found) - len(named)
    else:
        jobs, left_out = find_jobs(dataset, root, version, split, frame_stride), 0
    if not jobs and not split_files:
        raise ValueError(no_logs_found(dataset, root, version, split))
    if not jobs:
        names = ", ".join(f"{name}={path}" for name, path in split_files.items())
        in_split = f" of split {split}" if split else ""
        raise ValueError(
            f"{root}: none of its {len(found)} logs is named in the split files{in_split} ({names})"
        )
    return jobs, left_out


def manifest_parameters(
    options: TargetOptions, frame_stride: int, split_files: dict[str, Path] | None
) -> dict:
    """The options that make the shards what they are, as the manifest records them."""
    options_dict = asdict(options)
    options_dict["bev_range"] = options.bev_range.text
    parameters = {**options_dict, "frame_stride": frame_stride}
    if split_files:
        parameters["split_files"] = {name: str(Path(path).resolve()) for name, path in split_files.items()}
    return parameters


def check_manifest(out: Path, dataset: str, parameters: dict, overwrite: bool) -> None:
    """Refuse to add to a folder prepared with other options or another schema version (unless
    `overwrite`): shards made with other options must not be mixed with new ones."""
    manifest_path = out / "manifest.json"
    if not manifest_path.is_file() or overwrite:
        return
    before = json.loads(manifest_path.read_text())
    old = {"dataset": before.get("dataset"), **before.get("parameters", {})}
    new = {"dataset": dataset, **parameters}
    differing = [key for key in {**old, **new} if key != "split" and old.get(key) != new.get(key)]
    if differing:
        changes = ", ".join(
            f"{option_name(k)} {shown(old.get(k))} (now {shown(new.get(k))})" for k in differing
        )
        raise ValueError(
            f"{out} was prepared with other options: {changes}; pass --overwrite or choose another --out"
        )
    if before.get("schema_version") != io.SCHEMA_VERSION:
        raise ValueError(
            f"{manifest_path}: schema_version {before.get('schema_version')}, this version writes "
            f"{io.SCHEMA_VERSION}; pass --overwrite to prepare it again, or choose another --out"
        )


def run_jobs(
    todo: list[Job], out: Path, options: TargetOptions, frame_stride: int, on_error: str, workers: int,
    executor: str, address: str | None, advance: Callable,
) -> list[LogResult]:  # fmt: skip
    """prepare_log of every job on the chosen executor (pipeline/executor.py), results in job order;
    advance(n) moves the progress bar by n frames."""
    work = functools.partial(
        prepare_log, out=out, options=options, frame_stride=frame_stride, on_error=on_error
    )
    if executor == "ray":
        return run_ray(todo, work, workers, address, lambda job: advance(job.n_frames))
    if workers <= 1:  # in this process: the bar moves frame by frame
        return run_local(todo, functools.partial(work, on_frame=advance), 1, lambda job: None)
    warm_up()  # fork: workers inherit the loaded nuScenes tables instead of reading them again
    return run_local(todo, work, workers, lambda job: advance(job.n_frames))


def append_errors(out: Path, errors: list[dict]) -> None:
    """The records of the frames and logs that failed, added to out/errors.jsonl (atomically)."""
    if errors:
        previous = (out / "errors.jsonl").read_text() if (out / "errors.jsonl").is_file() else ""
        lines = previous + "".join(json.dumps(e) + "\n" for e in errors)
        io.write_atomic(out / "errors.jsonl", lambda tmp: tmp.write_text(lines))


def summarize(
    jobs: list[Job], todo: list[Job], left_out: int, results: list[LogResult], seconds: float
) -> dict:
    """The run's summary: what `prepare` returns and the manifest's last_run."""
    frames = sum(r.frames for r in results)
    return {
        "logs": len(jobs),
        "logs_in_no_split_file": left_out,
        "logs_prepared": len(todo),
        "logs_already_done": len(jobs) - len(todo),
        "frames": frames,
        "frames_skipped": sum(r.skipped for r in results),
        "paths_per_frame": sum(r.paths for r in results) / max(frames, 1),
        "pieces_per_frame": sum(r.pieces for r in results) / max(frames, 1),
        "junctions_per_frame": sum(r.junctions for r in results) / max(frames, 1),
        "path_cap_hits": sum(r.cap_hits for r in results),
        "seconds": seconds,
        "frames_per_second": frames / seconds if seconds > 0 else 0.0,
        "peak_worker_mib": max((r.peak_mib for r in results), default=0.0),
    }


def write_manifest(
    out: Path, dataset: str, root: Path, version: str, parameters: dict, split: str | None,
    options: TargetOptions, summary: dict,
) -> None:  # fmt: skip
    io.write_json(
        out / "manifest.json",
        {
            "schema_version": io.SCHEMA_VERSION,
            "dataset": dataset,
            "root": str(root),
            "version": version if dataset == "nuscenes" else None,
            "parameters": {**parameters, "split": split},
            "range": {"x_min": options.bev_range.x_min, "x_max": options.bev_range.x_max,
                      "y_min": options.bev_range.y_min, "y_max": options.bev_range.y_max},
            "packages": package_versions(),
            "rows": {table: io.count_rows(out, table) for table in io.TABLES},
            "last_run": summary,
        },
    )  # fmt: skip


def prepare(
    dataset: str,
    root: Path,
    out: Path,
    options: TargetOptions,
    version: str = "v1.0-trainval",
    split: str | None = None,
    workers: int = 1,
    frame_stride: int = 1,
    on_error: str = "fail",
    overwrite: bool = False,
    split_files: dict[str, Path] | None = None,
    executor: str = "local",
    address: str | None = None,
) -> dict:
    """Prepare every log of root into out; returns (and prints) a summary. split_files ({split: file
    of log ids or scene names}) replaces the dataset's own splits; logs in no file are left out.
    executor: local (this process, or a fork pool of `workers`) or ray (one Ray task per log: a local
    instance of `workers` CPUs, or the cluster at address, "auto" or HOST:PORT; pipeline/executor.py)."""
    check_options(options, frame_stride, workers, on_error, executor)
    if address and executor != "ray":
        raise ValueError("--address is for --executor ray")
    if executor == "ray":  # before any work: a missing Ray is a one-line error, not a traceback later
        import_ray()
    root, out = Path(root).resolve(), Path(out)
    jobs, left_out = select_jobs(dataset, root, version, split, frame_stride, split_files)
    parameters = manifest_parameters(options, frame_stride, split_files)
    check_manifest(out, dataset, parameters, overwrite)
    out.mkdir(parents=True, exist_ok=True)
    todo = [j for j in jobs if overwrite or not io.shard_done(out, f"{j.split}__{j.name}")]
    start = time.perf_counter()
    columns = [
        TextColumn("prepare {task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
    ]
    with Progress(*columns, console=console, transient=False) as progress:
        task = progress.add_task(f"{dataset} frames", total=sum(j.n_frames for j in todo))
        advance = functools.partial(progress.advance, task)
        results = run_jobs(todo, out, options, frame_stride, on_error, workers, executor, address, advance)
    elapsed = time.perf_counter() - start
    append_errors(out, [e for r in results for e in r.errors])
    summary = summarize(jobs, todo, left_out, results, elapsed)
    write_manifest(out, dataset, root, version, parameters, split, options, summary)
    return summary
