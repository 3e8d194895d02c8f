"""Command line of the lane-graph pipeline: synth, prepare, train, eval, score, roundtrip, report.

Heavy modules (torch, av2, nuscenes) are imported inside the commands so that `cli --help` is instant.
"""

from __future__ import annotations

from pathlib import Path

import typer

app = typer.Typer(add_completion=False, no_args_is_help=True, help=__doc__)


@app.command()
def synth(
    out: Path = typer.Option(..., help="Folder to write <out>/av2/sensor/... and <out>/nuscenes/..."),
    logs: int = typer.Option(4, help="Logs (AV2) / scenes (nuScenes) to write"),
    frames_per_log: int = typer.Option(20, help="Key frames per log"),
    seed: int = typer.Option(0, help="Random seed; the same seed writes the same bytes"),
    sensors: bool = typer.Option(True, help="Also render camera images and LiDAR sweeps"),
) -> None:
    """Write a tiny synthetic raw dataset in the real AV2 and nuScenes on-disk formats."""
    from pipeline.synth import synth as write_synth

    write_synth(out, logs=logs, frames_per_log=frames_per_log, seed=seed, sensors=sensors)


@app.command()
def prepare(
    dataset: str = typer.Option(..., help="av2 or nuscenes"),
    root: Path = typer.Option(..., help="AV2: the folder holding train/, val/, ... ; nuScenes: the dataroot"),
    out: Path = typer.Option(..., help="Output folder of the prepared Parquet dataset"),
    version: str = typer.Option(
        "v1.0-trainval", help="nuScenes table version (v1.0-mini, v1.0-trainval, ...)"
    ),
    split: str = typer.Option(None, help="Prepare one split (train, val, ...); default: all"),
    range_: str = typer.Option("30x60", "--range", help="Perception range WIDTHxLENGTH in metres (x by y)"),
    workers: int = typer.Option(1, help="Worker processes, one log at a time each"),
    frame_stride: int = typer.Option(1, help="Keep every K-th frame"),
    path_points: int = typer.Option(30, help="Points per resampled path"),
    piece_points: int = typer.Option(20, help="Points per resampled piece"),
    max_paths: int = typer.Option(256, help="Cap on paths per frame (the enumeration stops there)"),
    resolution: float = typer.Option(0.15, help="Raster cell size in metres"),
    line_width: int = typer.Option(5, help="Raster line width in pixels"),
    on_error: str = typer.Option(
        "fail", help="fail: stop at the first bad record; skip: log it to errors.jsonl"
    ),
    overwrite: bool = typer.Option(False, help="Redo logs whose shards already exist"),
) -> None:
    """Crop lane graphs to the ego frame; write graphs, paths, pieces and rasters to Parquet."""
    from rich.console import Console
    from rich.table import Table

    from pipeline.errors import DataError
    from pipeline.geometry import Range
    from pipeline.prepare import prepare as run_prepare
    from pipeline.targets import TargetOptions

    try:
        options = TargetOptions(
            Range.parse(range_), path_points, piece_points, max_paths, resolution, line_width
        )
        summary = run_prepare(
            dataset, root, out, options, version=version, split=split, workers=workers,
            frame_stride=frame_stride, on_error=on_error, overwrite=overwrite,
        )  # fmt: skip
    except (DataError, ValueError, FileNotFoundError) as error:
        typer.secho(f"error: {error}", fg="red", err=True)
        raise typer.Exit(1) from error
    table = Table(title=f"prepared {out}")
    for key in ("frames", "frames_skipped", "paths_per_frame", "pieces_per_frame", "junctions_per_frame",
                "path_cap_hits", "logs_already_done", "frames_per_second"):  # fmt: skip
        value = summary[key]
        table.add_row(key.replace("_", " "), f"{value:.2f}" if isinstance(value, float) else str(value))
    Console().print(table)


if __name__ == "__main__":
    app()
