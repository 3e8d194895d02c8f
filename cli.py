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
) -> None:
    """Write a tiny synthetic raw dataset in the real AV2 and nuScenes on-disk formats."""
    from pipeline.synth import synth as write_synth

    write_synth(out, logs=logs, frames_per_log=frames_per_log, seed=seed)


if __name__ == "__main__":
    app()
