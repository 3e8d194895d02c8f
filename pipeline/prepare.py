"""`cli prepare`: every log of a raw dataset -> one shard per table of the prepared Parquet dataset."""

from __future__ import annotations

import contextlib
import functools
import hashlib
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
from pipeline.error_records import ErrorRecords, earlier_errors
from pipeline.errors import DataError
from pipeline.executor import import_ray, run_local, run_ray
from pipeline.lane_graph import LaneMap
from pipeline.manifest import (
    MANIFEST,
    PICTURE,
    STAGE,
    check_manifest,
    check_no_interrupted_overwrite,
    move_in,
    recorded_version,
    recover_overwrite,
)
from pipeline.progress import tracked
from pipeline.records import Frame, Log, LogIndex
from pipeline.splits.geographic import draw_dataset_splits
from pipeline.splits.leakage import reach, read_and_measure
from pipeline.splits.plan import (
    SCHEMES,
    geographic_plan,
    needs_index,
    plan_from_files,
    read_split_files,
    split_file_digests,
    split_name_digests,
)
from pipeline.targets import FrameTargets, TargetOptions, flat_pose, frame_targets, warm_up

console = Console(stderr=True)

# what manifest.json holds of the summary beside its last_run: measured over the whole folder, or the plan's
BESIDE_LAST_RUN = ("leakage", "split_shares", "frames_without_images")


@dataclass(frozen=True)
class Job:
    """One log to prepare: what a worker needs to find and read it, and the split of its frames."""

    dataset: str
    split: str  # of every frame, or "" when `frame_splits` gives each frame's
    name: str
    n_frames: int  # the frames it prepares
    ref: object  # av2: the log folder; nuscenes: a SceneRef; openlanev2: a SegmentRef
    root: Path
    frame_splits: dict[int, str | None] | None = None  # timestamp_ns -> split, None: left out
    planned: tuple[str, ...] = ()  # every split the plan gives its frames, --split or not

    def split_of(self, timestamp_ns: int) -> str | None:
        return self.split if self.frame_splits is None else self.frame_splits.get(timestamp_ns)

    @property
    def splits(self) -> list[str]:
        """The splits it writes a shard of."""
        return sorted({self.split} if self.frame_splits is None else set(self.frame_splits.values()) - {None})

    @property
    def shards(self) -> list[str]:
        return [f"{split}__{self.name}" for split in self.splits]


@dataclass(frozen=True)
class SourceOptions:
    """What of a raw root is read, and what its files do not say: OpenLane-V2's --subset (A: the AV2 ring
    cameras, B: the nuScenes cameras; None: both) and --cities (a CSV of each segment's city)."""

    subset: str | None = None
    cities: Path | None = None

    def check(self, dataset: str, scheme: str) -> None:
        if dataset != "openlanev2" and (self.subset or self.cities):
            given = "--subset" if self.subset else "--cities"
            raise ValueError(f"{given} is for --dataset openlanev2, not {dataset}")
        if self.subset not in (None, "A", "B"):
            raise ValueError(f"--subset must be A or B, not {self.subset!r}")
        if self.cities is not None and not Path(self.cities).is_file():
            raise ValueError(f"{self.cities}: --cities file not found")
        if dataset == "openlanev2" and scheme == "geographic" and self.cities is None:
            raise ValueError("--split-scheme geographic needs each segment's city, which OpenLane-V2's "
                             "frame files do not carry: give --cities FILE (segment_id or source_id, "
                             "city)")  # fmt: skip


@dataclass
class LogResult:
    shards: list[str]
    frames: int = 0
    paths: int = 0
    pieces: int = 0
    junctions: int = 0
    cap_hits: int = 0
    skipped: int = 0
    errors: list[dict] = field(default_factory=list)
    peak_mib: float = 0.0  # peak resident memory of the process that prepared it, so far


def find_jobs(
    dataset: str, root: Path, version: str, split: str | None, frame_stride: int, source: SourceOptions
) -> list[Job]:
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
    if dataset == "openlanev2":
        from pipeline.adapters import openlanev2

        return [
            Job("openlanev2", r.split, r.segment_id, -(-len(r.files) // frame_stride), r, root)
            for r in openlanev2.find_segments(root, split, source.subset, source.cities)
        ]
    raise ValueError(f"unknown dataset {dataset!r}: expected av2, nuscenes or openlanev2")


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
    if dataset == "openlanev2":
        return (f"{root}: no OpenLane-V2 segment{in_split} (looked for ROOT/{split or '<split>'}/"
                "<segment_id>/info/<timestamp>.json); --root is the folder that holds train/, val/, "
                "...")  # fmt: skip
    return f"{root}: no nuScenes scene{in_split} in the {version} tables (looked in {root / version})"


def check_options(
    options: TargetOptions, frame_stride: int, workers: int, on_error: str, executor: str,
    dataset: str = "av2", source: SourceOptions = SourceOptions(), scheme: str = "original",
) -> None:  # fmt: skip
    """Refuse values that would crash or mean nothing later (a 0-point resample ends the interpreter), each
    named as its `cli prepare` option; the command line refuses most of them already."""
    source.check(dataset, scheme)
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


def load_job(job: Job, frame_stride: int, options: TargetOptions) -> Log:
    if job.dataset == "av2":
        from pipeline.adapters import av2

        return av2.load_log(job.root, job.split, job.ref, frame_stride)
    if job.dataset == "openlanev2":
        from pipeline.adapters import openlanev2

        return openlanev2.load_segment(job.ref, job.root, frame_stride)
    from pipeline.adapters import nuscenes

    log = nuscenes.load_log(job.ref, options.bev_range.radius)
    log.frames = log.frames[::frame_stride]
    return log


def index_job(job: Job) -> LogIndex:
    """Where the log's frames are (adapters' index_log), without reading its map or sensors."""
    if job.dataset == "av2":
        from pipeline.adapters import av2

        return av2.index_log(job.ref)
    if job.dataset == "openlanev2":
        from pipeline.adapters import openlanev2

        return openlanev2.index_segment(job.ref)
    from pipeline.adapters import nuscenes

    return nuscenes.index_log(job.ref)


def index_jobs(jobs: list[Job]) -> dict[str, LogIndex]:
    """Every log's LogIndex, with a bar: a whole dataset's poses before any frame is prepared."""
    return {job.name: index_job(job) for job in tracked(jobs, "index logs", len(jobs))}


def prepare_log(
    job: Job, out: Path, options: TargetOptions, frame_stride: int, on_error: str, on_frame=None
) -> LogResult:
    """Prepare one log and write its shards, one per split of its frames (frames the plan leaves out are
    not read); bad frames raise (fail) or are recorded (skip)."""
    result = LogResult(job.shards)
    try:
        log = load_job(job, frame_stride, options)
    except DataError as error:
        if on_error == "fail":
            raise
        result.errors.append({"log": job.name, "splits": job.splits, "frame_id": None, "source": error.source,
                              "error": str(error)})  # fmt: skip
        result.skipped = job.n_frames
        return result
    lane_map = LaneMap.from_lanes(log.lanes)
    frames, targets = [], []
    for frame in log.frames:
        frame.split = job.split_of(frame.timestamp_ns)  # a split file or the scheme may have moved it
        if frame.split is None:
            continue
        try:
            targets.append(targets_of_frame(job, log, lane_map, frame, options))
            frames.append(frame)
        except DataError as error:
            if on_error == "fail":
                raise
            result.errors.append({"log": job.name, "splits": [frame.split], "frame_id": frame.frame_id,
                                  "source": error.source, "error": str(error)})  # fmt: skip
            result.skipped += 1
        if on_frame:
            on_frame()
    remove_stale_shards(out, job)
    for shard in job.shards:
        split = shard.split("__")[0]
        ours = [i for i, frame in enumerate(frames) if frame.split == split]
        tables = shard_tables(job, log, [frames[i] for i in ours], [targets[i] for i in ours], options)
        io.write_shard(out, shard, tables)
    result.frames = len(frames)
    result.paths = sum(len(t.paths.vertex_ids) for t in targets)
    result.pieces = sum(len(t.pieces.chains) for t in targets)
    result.junctions = sum(len(t.pieces.junctions) for t in targets)
    result.cap_hits = sum(t.paths.cap_hit for t in targets)
    result.peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return result


def targets_of_frame(
    job: Job, log: Log, lane_map: LaneMap, frame: Frame, options: TargetOptions
) -> FrameTargets:
    """One frame's targets: from its own annotated lanes (OpenLane-V2), else cropped from the log's map."""
    if job.dataset == "openlanev2":
        from pipeline.adapters import openlanev2

        return openlanev2.frame_targets(log, frame, options)
    if not np.isfinite(frame.ego_to_world).all():
        raise DataError(log.pose_source, f"frame {frame.frame_id}", "ego pose has NaN or infinite values")
    pose = flat_pose(frame.ego_to_world) if log.map_is_2d else frame.ego_to_world
    return frame_targets(lane_map, pose, options)


def shard_tables(
    job: Job, log: Log, frames: list[Frame], targets: list[FrameTargets], options: TargetOptions
) -> dict[str, pa.Table]:
    """The tables of one shard: OpenLane-V2's add the frames' annotated lanes, unchanged."""
    tables = io.log_tables(frames, targets, options)
    if job.dataset == "openlanev2":
        from pipeline.adapters import openlanev2

        tables[io.ANNOTATED_LANES] = openlanev2.annotated_table(log, frames)
    return tables


def remove_stale_shards(out: Path, job: Job) -> None:
    """The log's shards of splits its plan no longer gives it (its folder moved to another split folder of
    the same root): its frames must not stand in two splits."""
    planned = {f"{split}__{job.name}" for split in job.planned or {job.split}}
    for table in io.ALL_TABLES:
        for path in (out / table).glob(f"*__{job.name}.parquet"):
            if path.stem not in planned:
                path.unlink()


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


@dataclass
class SplitOptions:
    """How frames are put in splits: the dataset's own or `split_files` (the original scheme), or the
    geographic scheme's cells of `geo_cell` metres, buffer of `geo_buffer` metres (None: the range's
    diagonal, so that no val or test window shares ground with a training window) and seed."""

    scheme: str = "original"
    split_files: dict[str, Path] | None = None
    geo_cell: float = 100.0
    geo_buffer: float | None = None
    geo_seed: int = 0

    def check(self, options: TargetOptions) -> None:
        if self.scheme not in SCHEMES:
            raise ValueError(f"--split-scheme must be one of {', '.join(SCHEMES)}, not {self.scheme!r}")
        if self.scheme == "geographic" and self.split_files:
            raise ValueError("--split-scheme geographic and --split-file: the scheme makes the splits, "
                             "the files name them; choose one")  # fmt: skip
        # before any log is indexed; inf and nan pass the command line's ranges
        if not (np.isfinite(self.geo_cell) and self.geo_cell > 0):
            raise ValueError(
                f"--geo-cell must be a finite number of metres greater than 0, not {self.geo_cell}"
            )
        if self.geo_buffer is not None and not (np.isfinite(self.geo_buffer) and self.geo_buffer >= 0):
            raise ValueError(
                f"--geo-buffer must be a finite number of metres, 0 or more, not {self.geo_buffer}"
            )
        if self.geo_buffer is None:
            self.geo_buffer = reach(options.bev_range)


@dataclass
class Plan:
    """The logs to prepare with the split of their frames, and what the plan left out."""

    jobs: list[Job]
    counts: dict = field(default_factory=dict)  # for the summary: logs and frames left out, and why
    geo: object = None  # the geographic scheme's GeoSplit (pipeline/splits/geographic.py), for the picture


def with_frame_splits(job: Job, frame_splits: dict[int, str | None]) -> Job:
    planned = tuple(sorted(set(frame_splits.values()) - {None}))
    n_frames = sum(split is not None for split in frame_splits.values())
    return replace(job, split="", frame_splits=frame_splits, n_frames=n_frames, planned=planned)


def only_split(job: Job, split: str) -> Job | None:
    """The job restricted to the frames of `split` (--split), None when it has none."""
    if job.frame_splits is None:
        return job if job.split == split else None
    frames = {t: (s if s == split else None) for t, s in job.frame_splits.items()}
    n_frames = sum(s is not None for s in frames.values())
    return replace(job, frame_splits=frames, n_frames=n_frames) if n_frames else None


def plan_files(found: list[Job], split_files: dict[str, Path], frame_stride: int) -> Plan:
    """The split files' splits, of whole logs or of frames; logs and frames in no file are left out."""
    lines = read_split_files(split_files)
    indexes = index_jobs(found) if needs_index(lines) else {}
    files = plan_from_files(lines, [job.name for job in found], indexes)
    jobs, frames_unnamed = [], 0
    for job in found:
        if job.name in files.frame_split:
            named, whole = files.frame_split[job.name], files.log_split.get(job.name)
            times = indexes[job.name].timestamps[::frame_stride].tolist()
            frame_splits = {t: named.get(t, whole) for t in times}
            frames_unnamed += sum(split is None for split in frame_splits.values())
            jobs.append(with_frame_splits(job, frame_splits))
        elif job.name in files.log_split:
            jobs.append(replace(job, split=files.log_split[job.name]))
    counts = {"logs_in_no_split_file": len(found) - len(jobs)}
    if indexes:
        counts |= {"frames_in_no_split_file": frames_unnamed,
                   "split_file_lines_unmatched": [f"{line.path}:{line.number}: {line.text}"
                                                  for line in files.unmatched]}  # fmt: skip
    counts["split_file_lines_naming_nothing_here"] = files.elsewhere
    return Plan(jobs, counts)


def plan_geographic(found: list[Job], splits: SplitOptions, frame_stride: int) -> Plan:
    """The geographic scheme over every log's frames (pipeline/splits/geographic.py)."""
    indexes = index_jobs(found)
    original = {job.name: job.split for job in found}
    try:
        frame_splits, geo = geographic_plan(
            [job.name for job in found], indexes, original, frame_stride, splits.geo_cell, splits.geo_buffer,
            splits.geo_seed,
        )  # fmt: skip
    except ValueError as error:
        raise ValueError(f"--split-scheme geographic: {error}") from error
    jobs = [with_frame_splits(job, frame_splits[job.name]) for job in found]
    return Plan([job for job in jobs if job.n_frames], {"frames_in_buffer": sum(geo.left_out.values())}, geo)


def plan_jobs(
    dataset: str, root: Path, version: str, split: str | None, frame_stride: int, splits: SplitOptions,
    source: SourceOptions = SourceOptions(),
) -> Plan:  # fmt: skip
    """The logs to prepare, each frame's split, and what was left out; a root without a log is an error (a
    wrong --root or --dataset would otherwise prepare 0 frames and leave a manifest behind)."""
    whole = bool(splits.split_files) or splits.scheme == "geographic"  # --split picks among the plan's
    found = find_jobs(dataset, root, version, None if whole else split, frame_stride, source)
    if not found and not splits.split_files:
        raise ValueError(no_logs_found(dataset, root, version, split))
    if splits.split_files:
        plan = plan_files(found, splits.split_files, frame_stride)
    elif splits.scheme == "geographic":
        plan = plan_geographic(found, splits, frame_stride)
    else:
        plan = Plan(found, {"logs_in_no_split_file": 0})
    if whole and split:
        plan.jobs = [job for job in map(functools.partial(only_split, split=split), plan.jobs) if job]
    if not plan.jobs and splits.split_files:
        names = ", ".join(f"{name}={path}" for name, path in splits.split_files.items())
        in_split = f" of split {split}" if split else ""
        raise ValueError(
            f"{root}: none of its {len(found)} logs is named in the split files{in_split} ({names})"
        )
    if not plan.jobs:
        raise ValueError(f"{root}: --split-scheme geographic puts no frame in split {split!r}")
    return plan


def manifest_parameters(
    options: TargetOptions, frame_stride: int, splits: SplitOptions, dataset: str = "av2",
    source: SourceOptions = SourceOptions(),
) -> dict:  # fmt: skip
    """The options that make the shards what they are, as the manifest records them."""
    options_dict = asdict(options)
    options_dict["bev_range"] = options.bev_range.text
    parameters = {**options_dict, "frame_stride": frame_stride, "split_scheme": splits.scheme}
    if splits.split_files:
        parameters["split_files"] = {
            name: str(Path(path).resolve()) for name, path in splits.split_files.items()
        }
        parameters["split_file_sha256"] = split_file_digests(splits.split_files)
        parameters["split_file_names_sha256"] = split_name_digests(splits.split_files)
    if splits.scheme == "geographic":
        parameters |= {"geo_cell": splits.geo_cell, "geo_buffer": splits.geo_buffer,
                       "geo_seed": splits.geo_seed}  # fmt: skip
    if dataset == "openlanev2":  # the subset read and the cities given (their file's contents by digest)
        cities = source.cities and Path(source.cities).resolve()
        digest = cities and hashlib.sha256(cities.read_bytes()).hexdigest()
        parameters |= {"subset": source.subset, "cities": cities and str(cities), "cities_sha256": digest}
    return parameters


def run_jobs(
    todo: list[Job], out: Path, options: TargetOptions, frame_stride: int, on_error: str, workers: int,
    executor: str, address: str | None, advance: Callable, on_log: Callable,
) -> list[LogResult]:  # fmt: skip
    """prepare_log of every job on the chosen executor (pipeline/executor.py), results in job order;
    advance(n) moves the progress bar by n frames, on_log(job, result) as each log is done."""
    work = functools.partial(
        prepare_log, out=out, options=options, frame_stride=frame_stride, on_error=on_error
    )

    def done(job: Job, result: LogResult, frames: int) -> None:
        advance(frames)
        on_log(job, result)

    if executor == "ray":
        return run_ray(todo, work, workers, address, lambda job, result: done(job, result, job.n_frames))
    if workers <= 1:  # in this process: the bar moves frame by frame
        return run_local(todo, functools.partial(work, on_frame=advance), 1, lambda j, r: done(j, r, 0))
    warm_up()  # fork: workers inherit the loaded nuScenes tables instead of reading them again
    return run_local(todo, work, workers, lambda job, result: done(job, result, job.n_frames))


def summarize(plan: Plan, todo: list[Job], results: list[LogResult], seconds: float, leakage: dict) -> dict:
    """The run's summary: what `prepare` returns and the manifest's last_run (its leakage and the
    geographic scheme's achieved shares stand beside it)."""
    jobs, frames = plan.jobs, sum(r.frames for r in results)
    return {
        "logs": len(jobs),
        **plan.counts,
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
        "leakage": leakage,
        **({"split_shares": plan.geo.achieved()} if plan.geo is not None else {}),
    }


def write_manifest(
    out: Path, dataset: str, root: Path, version: str, parameters: dict, split: str | None,
    options: TargetOptions, summary: dict,
) -> None:  # fmt: skip
    io.write_json(
        out / MANIFEST,
        {
            "schema_version": io.SCHEMA_VERSION,
            "dataset": dataset,
            "root": str(root),
            "version": recorded_version(dataset, version),
            "parameters": {**parameters, "split": split},
            "range": {"x_min": options.bev_range.x_min, "x_max": options.bev_range.x_max,
                      "y_min": options.bev_range.y_min, "y_max": options.bev_range.y_max},
            "packages": package_versions(),
            "rows": {table: io.count_rows(out, table) for table in io.dataset_tables(dataset)},
            "leakage": summary["leakage"],
            **{key: summary[key] for key in ("split_shares", "frames_without_images") if key in summary},
            "last_run": {key: value for key, value in summary.items() if key not in BESIDE_LAST_RUN},
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
    split_scheme: str = "original",
    geo_cell: float = 100.0,
    geo_buffer: float | None = None,
    geo_seed: int = 0,
    subset: str | None = None,
    cities: Path | None = None,
) -> dict:
    """Prepare every log of root into out; returns (and prints) a summary. split_files ({split: file of
    log ids, scene names or frames}) replaces the dataset's own splits; logs and frames in no file are left
    out. split_scheme "geographic" puts frames in splits by place (SplitOptions, pipeline/splits/). Every
    run measures the leakage of the whole output's non-training splits (pipeline/splits/leakage.py) into
    manifest.json and draws OUT/splits.png. overwrite: start afresh: the run writes into OUT/.overwrite
    and, once all of it has succeeded, replaces what earlier runs wrote (written_files) with it (move_in);
    failed or interrupted at any step, the earlier output is put back whole (recover_overwrite, also at
    the next run). Without it, logs already done are kept and the folder must have been prepared the same
    way (check_manifest), and a folder that an interrupted --overwrite run left is refused.
    executor: local (this process, or a fork pool of `workers`) or ray (one Ray task per log: a local
    instance of `workers` CPUs, or the cluster at address, "auto" or HOST:PORT; pipeline/executor.py).
    subset, cities: OpenLane-V2's (SourceOptions)."""
    source = SourceOptions(subset, cities)
    check_options(options, frame_stride, workers, on_error, executor, dataset, source, split_scheme)
    splits = SplitOptions(split_scheme, split_files, geo_cell, geo_buffer, geo_seed)
    splits.check(options)
    if address and executor != "ray":
        raise ValueError("--address is for --executor ray")
    if executor == "ray":  # before any work: a missing Ray is a one-line error, not a traceback later
        import_ray()
    root, out = Path(root).resolve(), Path(out)
    parameters = manifest_parameters(options, frame_stride, splits, dataset, source)
    if not overwrite:
        check_no_interrupted_overwrite(out)
    check_manifest(out, dataset, root, version, parameters, overwrite)
    earlier = [] if overwrite else earlier_errors(out)  # before any work: a damaged file is one line
    plan = plan_jobs(dataset, root, version, split, frame_stride, splits, source)
    run = Run(dataset, root, version, split, options, frame_stride, on_error, workers, executor, address,
              source)  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    if not overwrite:
        return write_output(out, plan, splits, parameters, run, ErrorRecords(out, earlier))
    said = recover_overwrite(out)  # what an interrupted --overwrite run left
    if said:
        console.print(said, soft_wrap=True)
    stage = out / STAGE
    try:
        summary = write_output(stage, plan, splits, parameters, run, ErrorRecords(stage, []), redo=True)
        move_in(stage, out)
    except BaseException:  # failed or interrupted at any step: the earlier output is put back whole
        with contextlib.suppress(OSError):  # else the next run puts it right, or names the folder left
            recover_overwrite(out)
        raise
    return summary


@dataclass(frozen=True)
class Run:
    """What one `prepare` call was asked for, besides the plan and the manifest's parameters."""

    dataset: str
    root: Path
    version: str
    split: str | None
    options: TargetOptions
    frame_stride: int
    on_error: str
    workers: int
    executor: str
    address: str | None
    source: SourceOptions = SourceOptions()


def measured_leakage(out: Path, run: Run) -> dict:
    """The leakage of the whole folder's non-training splits; not measured for OpenLane-V2 frames without
    --cities (they carry no city, and frames of different cities must not be measured together)."""
    if run.dataset == "openlanev2" and run.source.cities is None:
        return {"train_splits": [], "splits": {}, "not_measured": "OpenLane-V2's frame files carry no city; "
                "give --cities FILE (segment_id or source_id, city) to measure it"}  # fmt: skip
    return read_and_measure(out, run.options.bev_range)


def write_output(out: Path, plan: Plan, splits: SplitOptions, parameters: dict, run: Run,
                 records: ErrorRecords, redo: bool = False) -> dict:  # fmt: skip
    """Prepare the plan's logs into out (those not already done there, or all with `redo`), then its
    errors.jsonl, manifest.json and splits.png; returns the summary."""
    done = functools.partial(io.shard_done, out, tables=io.dataset_tables(run.dataset))
    todo = [job for job in plan.jobs if redo or not all(map(done, job.shards))]
    start = time.perf_counter()
    columns = [
        TextColumn("prepare {task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
    ]
    with Progress(*columns, console=console, transient=False) as progress:
        task = progress.add_task(f"{run.dataset} frames", total=sum(j.n_frames for j in todo))
        advance = functools.partial(progress.advance, task)
        logged = lambda job, result: records.log_done(job.name, job.splits, result.errors)  # noqa: E731
        results = run_jobs(todo, out, run.options, run.frame_stride, run.on_error, run.workers, run.executor,
                           run.address, advance, logged)  # fmt: skip
    elapsed = time.perf_counter() - start
    records.finish([job.name for job in todo])
    leakage = measured_leakage(out, run)
    summary = summarize(plan, todo, results, elapsed, leakage)
    if run.dataset == "openlanev2":  # over the whole folder, as the leakage: what `cli train` refuses
        missing = io.read_table(out, io.ANNOTATED_LANES, ["images_missing"]).column("images_missing")
        summary["frames_without_images"] = sum(count > 0 for count in missing.to_pylist())
    write_manifest(out, run.dataset, run.root, run.version, parameters, run.split, run.options, summary)
    cells = plan.geo.cells if plan.geo is not None else None
    draw_dataset_splits(out, out / PICTURE, cells, splits.geo_cell if cells else None)
    return summary
