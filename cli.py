"""Command line of the lane-graph pipeline: synth, prepare, train, eval, score, roundtrip, report, viz.

Heavy modules (torch, av2, nuscenes) are imported inside the commands so that `cli --help` is instant;
choices and ranges are checked by click before a command starts. Every command that prints a result
table takes --json (the result as one JSON line on stdout instead) and says which paths it wrote.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Literal

import typer

from benchmark.metric.table import METRIC_HELP

HELP = """Online lane graph construction (LaneGAP): training targets from nuScenes and Argoverse 2 maps,
four baselines (HDMapNet, STSU, MapTR, LaneGAP) under one encoder, and the TOPO and Junction TOPO
lane-graph metrics.

\b
Examples:
  cli synth --out demo/raw
  cli prepare --dataset av2 --root demo/raw/av2/sensor --out demo/prepared/av2
"""
app = typer.Typer(add_completion=False, no_args_is_help=True, rich_markup_mode=None, help=HELP)

# The choices of `cli train`, which must not import torch to list them (tests/test_cli_help.py compares
# them with baselines/config.py and baselines/models).
Model = Literal["lanegap", "hdmapnet", "maptr", "stsu"]
Preset = Literal["paper", "tiny", "gpu"]
Modality = Literal["camera", "lidar", "fusion"]
BestMetric = Literal[
    "directed_topo_f1", "directed_junction_topo_f1", "undirected_topo_f1", "undirected_junction_topo_f1",
    "miou",
]
PRESET_DEFAULTS = {  # the presets' values of the `cli train` options that default to them
    "epochs": "paper 110 on nuScenes, 24 on AV2 and OpenLane-V2, tiny 11, gpu 16",
    "batch_size": "paper 32, tiny 2, gpu 8",
    "modality": "paper camera, tiny fusion, gpu fusion",
    "path_points": "paper 30, tiny 20, gpu 30",
    "eval_every": "paper 4, tiny 1, gpu 4",
}
PATH_POINTS = Literal[10, 20, 30, 40]  # the paper's counts of points per path (Tab. 8)
JSON_HELP = "Print the result as one JSON line instead of the tables (for scripts)"


def positive(value: float | None) -> float | None:
    """Callback of the options that must be greater than 0 (typer's ranges include their bound)."""
    if value is not None and value <= 0:
        raise typer.BadParameter(f"{value} is not in the range x>0.")
    return value


def bezier_points_check(value: int | None) -> int | None:
    """Callback of train --bezier-points: one control point would be a curve of degree 0, a point."""
    if value is not None and (value < 0 or value == 1):
        raise typer.BadParameter(f"{value} is neither 0 (polyline) nor in the range x>=2.")
    return value


# The options that several commands share, help and range alike.
AsJson = Annotated[bool, typer.Option("--json", help=JSON_HELP)]
BOOTSTRAP_HELP = "Draws of the bootstrap over frames giving each F1 a 95 % interval (0: none)"
Bootstrap = Annotated[int, typer.Option(min=0, help=BOOTSTRAP_HELP)]
WorkersPerCore = Annotated[int, typer.Option(min=0, help="Worker processes (0: one per core)")]


def print_version(value: bool) -> None:
    if value:
        from benchmark.tables import version_text

        typer.echo(version_text())
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(
        False, "--version", callback=print_version, is_eager=True, help="Print the package version, "
        "metric_version and the prepared data's schema_version, and exit"),
) -> None:  # fmt: skip
    pass


@app.command(short_help="Write a synthetic raw dataset in the AV2 and nuScenes formats")
def synth(
    out: Path = typer.Option(..., help="Folder to write OUT/av2/sensor/... and OUT/nuscenes/... into"),
    logs: int = typer.Option(
        18, min=1, help="Logs (AV2) / scenes (nuScenes): 3/4 train, the rest (at most 2) val; nuScenes "
        "split names: v1.0-mini's up to 8 training logs, else v1.0-trainval's"),
    frames_per_log: int = typer.Option(10, min=1, help="Key frames per training log"),
    frame_period: float = typer.Option(
        2.0, min=0.02, help="Seconds between a training log's key frames, a multiple of 0.02"),
    val_frames_per_log: int = typer.Option(20, min=1, help="Key frames per validation log"),
    val_frame_period: float = typer.Option(
        1.0, min=0.02, help="Seconds between a validation log's key frames, a multiple of 0.02"),
    worlds: int = typer.Option(
        4, min=1, max=4, help="Procedural worlds, one nuScenes map location / AV2 city each"),
    val_worlds: int = typer.Option(
        1, min=1, help="Worlds that only validation logs drive in (unseen geography), fewer than --worlds"),
    seed: int = typer.Option(
        0, min=0, help="Random seed of the worlds, routes and sensors: same seed, same bytes"),
    sensors: bool = typer.Option(True, help="Also render camera images and LiDAR sweeps"),
    workers: int = typer.Option(1, min=1, help="Worker processes, one log at a time each (the same bytes)"),
    as_json: AsJson = False,
) -> None:  # fmt: skip
    """Write a synthetic raw dataset in the real AV2 and nuScenes on-disk formats, and OpenLane-V2's (subset
    A, OUT/openlanev2/) converted from its AV2 logs; the defaults are the learning checks' data (16 training
    logs x 10 frames 2 s apart, 2 validation logs x 20 frames 1 s apart on a world of their own). Guide:
    docs/guide/prepare.md.

    \b
    Examples:
      cli synth --out demo/raw
      cli synth --out tiny/raw --logs 2 --frames-per-log 3 --val-frames-per-log 3 --worlds 2 --no-sensors
    """
    from benchmark.tables import finish, reported_errors, synth_tables
    from pipeline.synth import synth as write_synth

    with reported_errors():
        summary = write_synth(out, logs=logs, frames_per_log=frames_per_log, seed=seed, sensors=sensors,
                              frame_period=frame_period, worlds=worlds, val_worlds=val_worlds,
                              workers=workers, val_frames_per_log=val_frames_per_log,
                              val_frame_period=val_frame_period)  # fmt: skip
    wrote = [out / summary[root] for root in ("av2_root", "nuscenes_root", "openlanev2_root")]
    wrote.append(out / "synth.json")
    finish(summary, synth_tables(summary), wrote, as_json)


def split_files(items: list[str]) -> dict[str, Path]:
    """prepare --split-file's SPLIT=FILE items by split."""
    files = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise ValueError(f"--split-file expects SPLIT=FILE, got {item!r}")
        files[name] = Path(path)
    return files


@app.command(short_help="Raw AV2 / nuScenes / OpenLane-V2 maps -> Parquet training targets")
def prepare(
    dataset: Literal["av2", "nuscenes", "openlanev2"] = typer.Option(..., help="The raw dataset's format"),
    root: Path = typer.Option(
        ..., help="AV2, OpenLane-V2: the folder holding train/, val/, ... ; nuScenes: the dataroot"),
    out: Path = typer.Option(..., help="Output folder of the prepared Parquet dataset"),
    version: str = typer.Option(
        "v1.0-trainval", help="nuScenes table version (v1.0-mini, v1.0-trainval, ...)"),
    split: str = typer.Option(None, show_default="all", help="Prepare one split (train, val, ...)"),
    range_: str = typer.Option(
        "30x60", "--range", metavar="WIDTHxLENGTH", help="Perception range in metres (x by y)"),
    workers: int = typer.Option(
        1, min=1, help="Worker processes, one log at a time each (ray: the local CPUs)"),
    executor: Literal["local", "ray"] = typer.Option(
        "local", help="local (this machine) or ray (one Ray task per log)"),
    address: str = typer.Option(
        None, show_default="a local Ray instance", help="--executor ray: the cluster to join, auto or "
        "HOST:PORT; HOST:PORT of a cluster with token authentication needs RAY_AUTH_MODE=token"),
    frame_stride: int = typer.Option(1, min=1, help="Keep every K-th frame"),
    path_points: int = typer.Option(30, min=2, help="Points per resampled path"),
    piece_points: int = typer.Option(20, min=2, help="Points per resampled piece"),
    max_paths: int = typer.Option(256, min=1, help="Cap on paths per frame (the enumeration stops there)"),
    resolution: float = typer.Option(0.15, callback=positive, help="Raster cell size in metres (x>0)"),
    line_width: int = typer.Option(5, min=1, help="Raster line width in pixels"),
    on_error: Literal["fail", "skip"] = typer.Option(
        "fail", help="fail: stop at the first bad record; skip: log it to errors.jsonl and go on"),
    overwrite: bool = typer.Option(
        False, help="Start afresh: once this run has succeeded, all that earlier runs wrote in --out goes "
        "(shards, manifest, errors, picture; other files stay)"),
    split_file: list[str] = typer.Option(
        [], metavar="SPLIT=FILE", show_default="the dataset's splits", help="A file of log ids / scene "
        "names, or of frames (frame ids, nuScenes sample tokens, AV2 <log>_<timestamp_ns>), one per line, "
        "for SPLIT (repeatable), replacing the dataset's splits, e.g. StreamMapNet's geographically "
        "disjoint ones; logs and frames in no file are left out"),
    split_scheme: Literal["original", "geographic"] = typer.Option(
        "original", help="original: the dataset's splits (or --split-file's); geographic: by place, per "
        "city, leaving out the val and test frames within --geo-buffer of a training frame"),
    geo_cell: float = typer.Option(100.0, callback=positive, help="geographic: cell size in metres (x>0)"),
    geo_buffer: float = typer.Option(
        None, min=0, show_default="the --range's diagonal: no val or test window shares ground with a "
        "training window", help="geographic: metres kept between val or test frames and training frames"),
    geo_seed: int = typer.Option(0, min=0, help="geographic: the seed of the cells' assignment"),
    subset: Literal["A", "B"] = typer.Option(
        None, show_default="both", help="OpenLane-V2: only subset A (AV2 ring cameras) or B (nuScenes "
        "cameras)"),
    cities: Path = typer.Option(
        None, show_default="none: leakage not measured, no geographic scheme", help="OpenLane-V2: a CSV of "
        "each segment's city (segment_id or source_id, city), whose frame files carry none"),
    as_json: AsJson = False,
) -> None:  # fmt: skip
    """Crop lane graphs to the ego frame; write graphs, paths, pieces and rasters to Parquet. A root without
    logs, and an --out prepared with other options, are refused before any work. Guide: docs/guide/prepare.md.

    \b
    Examples:
      cli prepare --dataset av2 --root data/av2/sensor --out prepared/geo --split-scheme geographic
      cli prepare --dataset nuscenes --root data/nuscenes --version v1.0-mini --out prepared/mini
    """
    from benchmark.tables import finish, prepare_tables, reported_errors
    from pipeline.geometry import Range
    from pipeline.prepare import prepare as run_prepare
    from pipeline.targets import TargetOptions

    with reported_errors():
        options = TargetOptions(Range.parse(range_), path_points, piece_points, max_paths, resolution,
                                line_width)  # fmt: skip
        summary = run_prepare(
            dataset, root, out, options, version=version, split=split, workers=workers,
            frame_stride=frame_stride, on_error=on_error, overwrite=overwrite,
            split_files=split_files(split_file), executor=executor, address=address,
            split_scheme=split_scheme, geo_cell=geo_cell, geo_buffer=geo_buffer, geo_seed=geo_seed,
            subset=subset, cities=cities,
        )  # fmt: skip
    wrote = [out, out / "splits.png"] + ([out / "errors.jsonl"] if summary["frames_skipped"] else [])
    finish(summary, prepare_tables(summary, dataset, root, split_scheme), wrote, as_json)


@app.command(short_help="Train a baseline: LaneGAP, MapTR, STSU or HDMapNet")
def train(
    ctx: typer.Context,
    data: Path = typer.Option(
        None, show_default="the run's, on --resume", help="Prepared dataset (cli prepare --out)"),
    out: Path = typer.Option(..., help="Run folder: config.json, run.json, checkpoint.pt, log.jsonl"),
    model: Model = typer.Option("lanegap", help="The baseline to train"),
    preset: Preset = typer.Option(
        "paper", help="paper (the paper's settings), tiny (CPU, seconds per epoch) or gpu (one CUDA GPU)"),
    modality: Modality = typer.Option(
        None, show_default=PRESET_DEFAULTS["modality"], help="Sensors (OpenLane-V2 has no LiDAR: camera)"),
    epochs: int = typer.Option(None, min=1, show_default=PRESET_DEFAULTS["epochs"], help="Epochs"),
    batch_size: int = typer.Option(
        None, min=1, show_default=PRESET_DEFAULTS["batch_size"], help="Batch size in total over all "
        "processes and accumulated micro-batches"),
    path_points: PATH_POINTS = typer.Option(
        None, show_default=PRESET_DEFAULTS["path_points"], help="Points per path N (query models)"),
    bezier_points: int = typer.Option(
        None, callback=bezier_points_check, show_default="0", help="Bezier head with K control points "
        "(paper: 5); 0: polyline (0 or x>=2)"),
    aux_seg: bool = typer.Option(
        None, "--aux-seg/--no-aux-seg", show_default="aux-seg", help="Auxiliary BEV segmentation loss"),
    pretrained: Path = typer.Option(
        None, show_default="none", help="Local torchvision ResNet state_dict file for the backbone"),
    from_scratch: bool = typer.Option(
        False, help="Train a backbone that the preset expects pretrained (paper) from random weights, "
        "every stage trained with batch statistics"),
    accumulate: int = typer.Option(
        None, min=1, show_default="paper: batch / 4 per process, tiny and gpu 1",
        help="Micro-batches accumulated per optimiser step (the batch size stays the effective batch)"),
    set_: list[str] = typer.Option(
        [], "--set", metavar="section.field=value", show_default="none",
        help="Any config field, e.g. train.lr=3e-4 or encoder.kernel_size=3,5 (repeatable)"),
    eval_every: int = typer.Option(
        None, min=0, show_default=PRESET_DEFAULTS["eval_every"], help="Validate every N epochs and after "
        "the last one (0: after the last one only): RUN/val.jsonl, RUN/best.pt"),
    eval_frames: int = typer.Option(
        None, min=0, show_default="0: the whole split", help="Validate on K frames, drawn once by the seed"),
    best_metric: BestMetric = typer.Option(
        None, show_default="directed_junction_topo_f1", help="The validation score that chooses RUN/best.pt"),
    checkpoint_every: int = typer.Option(
        None, min=0, show_default="0: at epoch ends only", help="Also save the full state every N steps "
        "inside an epoch (--resume goes on from there exactly)"),
    max_bad_steps: int = typer.Option(
        None, min=0, show_default="10", help="Stop after N steps in a row whose loss or gradient norm is "
        "not finite (each is skipped; under fp16, overflows count once the loss scale is down to 1; 0: "
        "never stop)"),
    resume: bool = typer.Option(False, help="Continue the run in --out from its last checkpoint"),
    overwrite: bool = typer.Option(
        False, help="Start afresh in an --out that holds a run (else refused), removing its files first"),
    stop_after: int = typer.Option(
        0, min=0, help="End this run after that many epochs (0: all); --resume goes on"),
    as_json: AsJson = False,
) -> None:  # fmt: skip
    """Train a baseline on a prepared dataset; DDP when started by torchrun (--batch-size is over all
    processes, and with --json every process prints its line). Validates during training (RUN/val.jsonl,
    RUN/best.pt) and writes TensorBoard events to RUN/tb (tensorboard --logdir RUN). A step whose loss or
    gradient norm is not finite is skipped. --resume goes on with the run's config: an option or --set given
    is logged in run.json (config_changes), or refused by name where the checkpoint was made otherwise (model,
    preset, shape, batch size) or config.json was edited; it refuses a dataset prepared with other target
    parameters, and falls back to checkpoint.prev.pt when checkpoint.pt is damaged.
    Guide: docs/guide/train.md.

    \b
    Examples:
      cli train --model lanegap --data prepared/av2 --out runs/lanegap --preset tiny --checkpoint-every 100
      torchrun --nproc_per_node 8 -m cli train --model maptr --data prep --out runs/maptr --pretrained r50.pth
    """
    from baselines.launch import TrainOptions, launch
    from baselines.run_folder import TRAINING_FILES
    from benchmark.tables import finish, reported_errors, train_tables

    # The options given on this command line (typer's own click names them): the others take their
    # defaults, and on --resume the given ones change the run's config as told (logged) or are refused.
    given = {name: value for name, value in ctx.params.items()
             if name != "as_json" and ctx.get_parameter_source(name).name == "COMMANDLINE"}  # fmt: skip
    with reported_errors():
        trained = launch(TrainOptions(**given))
    if not as_json and os.environ.get("RANK", "0") != "0":
        return  # under torchrun, rank 0 reports
    wrote = [out / name for name in TRAINING_FILES if (out / name).exists()]
    finish(trained.summary, train_tables(trained.title, trained.summary), wrote, as_json)


@app.command("eval", short_help="Predict a split with a trained run and score it")
def eval_(
    run: Path = typer.Option(..., help="Run folder written by cli train"),
    data: Path = typer.Option(
        None, show_default="the one the run trained on", help="Prepared dataset folder"),
    split: str = typer.Option(None, show_default="the config's val split", help="Split to predict"),
    device: Literal["cpu", "cuda"] = typer.Option(
        None, show_default="cuda when available", help="Device to predict on"),
    floor: bool = typer.Option(
        True, help="Also score the sensor-blind floor (other log's sensors, constant prior) and the margin"),
    bootstrap: Bootstrap = 1000,
    checkpoint: Literal["last", "best"] = typer.Option(
        "last", help="The weights: last (checkpoint.pt) or best (best.pt, the best validation in training)"),
    metric: str = typer.Option("lanegap", help=METRIC_HELP + "; lanegap always, cli report reads it"),
    as_json: AsJson = False,
) -> None:  # fmt: skip
    """Predict a split, turn the outputs into lane graphs (the model's post-processing), write
    predictions.parquet, frame_counts.parquet and metrics.json into the run folder, and on OpenLane-V2 data
    submission.pkl (OpenLane-V2's submission format); a dataset prepared with other target parameters than
    the run's is refused (stale data). Guide: docs/guide/train.md.

    \b
    Examples:
      cli eval --run runs/lanegap --split val --checkpoint best
      cli eval --run runs/lanegap --data prepared/other --device cpu --no-floor --json
    """
    from baselines.evaluate import evaluate
    from baselines.run_folder import EVALUATION_FILES
    from benchmark.metric.table import parse_metrics
    from benchmark.tables import eval_tables, finish, reported_errors

    with reported_errors():
        metrics = parse_metrics(metric, always=True)
        result = evaluate(run, data, split, device, floor=floor, bootstrap=bootstrap, checkpoint=checkpoint,
                          metrics=metrics)  # fmt: skip
    wrote = [run / name for name in EVALUATION_FILES if (run / name).is_file()]
    finish(result, eval_tables(run, result, metrics), wrote, as_json)


@app.command(short_help="Score predicted lane graphs: TOPO, Junction TOPO, mIoU")
def score(
    pred: Path = typer.Option(
        ..., help="Predictions: a graph-table Parquet file or a folder of shards (e.g. "
        "RUN/predictions.parquet), the results JSON of MapTRv2 / LaneGAP or CGNet, or an OpenLane-V2 "
        "submission (its pickle or the same as JSON)"),
    gt: Path = typer.Option(..., help="Ground truth: a prepared dataset or a graph-table file"),
    format_: Literal["auto", "graph", "maptrv2", "cgnet", "openlanev2"] = typer.Option(
        "auto", "--format", help="auto: told by the file's content; graph: our graph table; maptrv2: "
        "MapTRv2 / LaneGAP's nuscmap_results.json or av2map_results.json (paths, Path2Graph); cgnet: "
        "CGNet's nuscmap_results.json (snapped pieces, equal points merged); openlanev2: an OpenLane-V2 "
        "submission against OpenLane-V2 data (lanes and topology_lclc; traffic elements not read) "
        "(docs/guide/score.md)"),
    class_name: str = typer.Option(
        None, show_default="centerline", help="maptrv2 / cgnet: the class of vectors scored, others ignored"),
    min_score: float = typer.Option(
        None, min=0.0, max=1.0, show_default="maptrv2 0.4, cgnet 0.3: each codebase's own",
        help="maptrv2 / cgnet: keep vectors whose confidence_level is above this"),
    sweep: bool = typer.Option(
        False, help="maptrv2 / cgnet: also score at kept scores 0.1 to 0.8 (one scoring each, no intervals)"),
    split: str = typer.Option(
        None, show_default="the split(s) of the predicted frames", help="Score the ground truth's frames "
        "of this split (a prepared dataset's); graph: a frame without a prediction row is an empty "
        "prediction; maptrv2 / cgnet: the frames in the file; a predicted frame of another split is refused; "
        "openlanev2: the submission's frames of other splits are ignored, a frame it lacks is empty"),
    out: Path = typer.Option(
        None, show_default="not written", help="A .json file: the result (scores, thresholds, "
        "metric_version); otherwise a run folder (predictions.parquet, frame_counts.parquet, metrics.json) "
        "that `cli report --runs` shows as external"),
    as_json: AsJson = False,
    step: float = typer.Option(0.15, callback=positive, help="Densification step in metres (x>0)"),
    match_radius: float = typer.Option(
        0.45, callback=positive, help="Vertices closer than this may be paired, metres (x>0)"),
    reach_radius: float = typer.Option(
        7.5, callback=positive, help="Reach: path distance below this, metres (x>0)"),
    matching: Literal["greedy", "optimal"] = typer.Option(
        "greedy", help="greedy (by distance) or optimal (maximum cardinality)"),
    range_: str = typer.Option(
        None, "--range", metavar="WIDTHxLENGTH", show_default="the dataset's", help="mIoU grid in metres"),
    workers: WorkersPerCore = 1,
    bootstrap: Bootstrap = 1000,
    metric: str = typer.Option("lanegap", help=METRIC_HELP),
) -> None:  # fmt: skip
    """TOPO, Junction TOPO (directed and undirected) and mIoU of predicted lane graphs (docs/METRICS.md); the
    JSON records the thresholds and metric_version. Predictions of `cli eval` made by a model trained on other
    target parameters than the ground truth's are refused (stale data). Result files of MapTRv2 / LaneGAP and
    CGNet are scored as those codebases write them, and OpenLane-V2 submissions as its devkit reads them (a
    pickle read without running anything in it; any other pickle is refused). Guide: docs/guide/score.md.

    \b
    Examples:
      cli score --pred runs/lanegap/predictions.parquet --gt prepared/av2
      cli score --pred pts_bbox/nuscmap_results.json --gt prepared/nusc --out runs/maptrv2
    """
    from benchmark.metric.table import parse_metrics
    from benchmark.score import score as run_score
    from benchmark.tables import finish, reported_errors, score_tables

    params = dict(step=step, match_radius=match_radius, reach_radius=reach_radius, matching=matching)
    params |= {"bev_range": range_} if range_ else {}
    with reported_errors():
        metrics = parse_metrics(metric)
        result = run_score(
            pred, gt, out, workers=workers, bootstrap=bootstrap, split=split, fmt=format_,
            class_name=class_name, min_score=min_score, sweep=sweep, metrics=metrics, **params,
        )  # fmt: skip
    wrote = [out] if out is None or out.suffix.lower() == ".json" else [out / "metrics.json", out]
    finish(result, score_tables(pred, gt, result, metrics), [path for path in wrote if path], as_json)


@app.command(short_help="The ground truth through a representation and back")
def roundtrip(
    data: Path = typer.Option(..., help="Prepared dataset (cli prepare --out)"),
    via: Literal["path", "piece", "pixel"] = typer.Option(
        ..., help="path (Path2Graph), piece (Piece2Graph) or pixel (Pixel2Graph)"),
    out: Path = typer.Option(None, show_default="not written", help="Write the JSON (scores, thresholds, "
                             "metric_version) to this file"),
    as_json: AsJson = False,
    merge_radius: float = typer.Option(
        0.0, min=0.0, help="Path2Graph's near merge in metres (0: identical points only)"),
    frame_stride: int = typer.Option(1, min=1, help="Every K-th frame"),
    workers: WorkersPerCore = 1,
) -> None:  # fmt: skip
    """The ground truth through a representation and back, scored against itself (the paper's Tab. 10).
    Guide: docs/guide/score.md.

    \b
    Examples:
      cli roundtrip --data prepared/av2 --via path --out roundtrip_path.json
      cli roundtrip --data prepared/av2 --via pixel --frame-stride 10 --workers 0
    """
    from benchmark.roundtrip import roundtrip as run_roundtrip
    from benchmark.tables import finish, reported_errors, roundtrip_tables

    with reported_errors():
        result = run_roundtrip(data, via, out, merge_radius, workers, frame_stride)
    finish(result, roundtrip_tables(data, via, result), [out] if out else [], as_json)


@app.command(short_help="Tables and pictures comparing finished runs")
def report(
    runs: list[Path] = typer.Option(..., "--runs", metavar="RUN", help="A run folder, or a folder of run "
                                    "folders (repeatable: --runs A --runs B)"),
    roundtrip: list[Path] = typer.Option([], "--roundtrip", metavar="JSON", show_default="none",
                                         help="A `cli roundtrip --out` file (repeatable)"),
    out: Path = typer.Option(..., help="Folder for report.md, its PNGs and report.html"),
    workers: int = typer.Option(
        1, min=0, help="Worker processes of the scores by junction count and report.html's drawings "
        "(0: one per core)"),
    reference: Literal["paper"] = typer.Option(
        None, show_default="none", help="paper: place the paper's published tables beside the measured ones"),
    bootstrap: Bootstrap = 1000,
    metric: str = typer.Option("lanegap", help=METRIC_HELP + "; lanegap always, the others a table each"),
    browser_frames: int = typer.Option(
        3000, min=1, help="Most frames in report.html's frame browser; above it, those where runs differ "
        "most, each run's worst and a seeded sample"),
    thumbnails: bool = typer.Option(
        False, help="report.html: each browsed frame's front camera image, small"),
    as_json: AsJson = False,
) -> None:  # fmt: skip
    """The comparison tables and pictures of finished runs (from `cli eval` and `cli roundtrip`) as
    OUT/report.md and OUT/report.html (the same and a frame browser, one file to open in a browser); prints
    the main tables (with --reference, the paper's rows beside them).
    Guide: docs/guide/report.md.

    \b
    Examples:
      cli report --runs runs --out report
      cli report --runs runs/lanegap --runs runs/maptr --roundtrip rt_path.json --reference paper --out report
    """
    from benchmark.metric.table import parse_metrics
    from benchmark.report.writer import write_report
    from benchmark.tables import Printout, finish, report_tables, reported_errors

    with reported_errors():
        metrics = parse_metrics(metric, always=True)
        result = write_report(runs, out, roundtrip, workers, reference=reference, draws=bootstrap,
                              metrics=metrics, browser_frames=browser_frames,
                              thumbnails=thumbnails)  # fmt: skip
    shown, tables = report_tables(result)
    pictures = [str(p) for p in result.pictures]
    summary = {"report": str(result.path), "html": str(result.html), "pictures": pictures, "tables": tables}
    printout = Printout(shown, [f"{len(result.pictures)} pictures beside it"])
    finish(summary, printout, [result.path, result.html], as_json)


@app.command(short_help="One frame: ground truth beside prediction, as a PNG")
def viz(
    pred: Path = typer.Option(..., help="Predictions: a graph-table Parquet file (RUN/predictions.parquet)"),
    gt: Path = typer.Option(..., help="Ground truth: a prepared dataset (or a graph-table file)"),
    frame: str = typer.Option(
        None, show_default="the predicted frame of the lowest directed TOPO F1", help="Frame id"),
    camera: bool = typer.Option(False, help="Add the front camera image with both graphs on the ground"),
    out: Path = typer.Option(..., help="PNG file to write"),
) -> None:  # fmt: skip
    """One frame: ground truth and prediction side by side in BEV, matched and unmatched vertices coloured.
    Guide: docs/guide/report.md.

    \b
    Examples:
      cli viz --pred runs/lanegap/predictions.parquet --gt prepared/av2 --out worst.png
      cli viz --pred runs/lanegap/predictions.parquet --gt prepared/av2 --frame FRAME_ID --camera --out f.png
    """
    from benchmark.report.figures import viz as run_viz
    from benchmark.tables import reported_errors, viz_line

    with reported_errors():
        result = run_viz(pred, gt, frame, out, camera)
    typer.echo(viz_line(out, result))


if __name__ == "__main__":
    app()
