"""GPU acceptance in one command (`make gpu-check`): on one CUDA GPU, `cli synth` with enough frames for a
real schedule -> `cli prepare` -> `cli train` of all four models under the `gpu` preset (one schedule
for all) -> `cli eval` -> `cli report`, then one table of the paper's claims against their bars.

Bars (each model, directed F1 on the validation world that no training log drives): it reads its
sensors (its TOPO F1 minus with another log's sensors) by >= 0.15 and beats the best constant in
hindsight by >= 0.15 TOPO F1; LaneGAP reaches 0.5 TOPO F1; the whole run takes at most 10 minutes.
Whether LaneGAP leads on Junction TOPO F1 (the paper's claim) is reported either way.

Epochs: with `--bench` (the bench_step.json of `python -m baselines.bench_step --preset gpu`, run first on
the same GPU), each model gets as many epochs as its measured step time fits into its share of
`--train-seconds`, at most the gpu preset's; else the preset's.

`--smoke` (`make gpu-smoke`, in CI): the same commands and code path on tiny data, one epoch per model at
batch 2, on whatever device there is; it fails unless every output exists and every score is finite.

    python -m baselines.gpu_check [--out gpu_check] [--smoke] [--epochs N] [--bench bench_step.json]
        [--train-seconds 270]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table

from pipeline.checkout import checkout_root

MODELS = ("lanegap", "hdmapnet", "maptr", "stsu")
SENSOR_GAP = CONSTANT_MARGIN = 0.15
LANEGAP_TOPO = 0.5
WALL_SECONDS = 600
# Synthetic data: 10 logs (8 train, 2 val) of 50 frames 0.4 s apart; smoke: 8 logs of 2 frames.
DATA = {
    "logs": 10,
    "frames-per-log": 50,
    "frame-period": 0.4,
    "val-frames-per-log": 50,
    "val-frame-period": 0.4,
}
SMOKE_DATA = {
    "logs": 8,
    "frames-per-log": 2,
    "frame-period": 1.0,
    "val-frames-per-log": 2,
    "val-frame-period": 1.0,
}

console = Console()
PHASES: list[tuple[str, float]] = []  # (command, seconds) of every `cli` command run so far


def cli(*args: str) -> None:
    """One `cli` command in its own process, as a user runs it; its failure ends the check."""
    command = [sys.executable, "-m", "cli", *args]
    console.print(f"[bold]$ cli {' '.join(args)}[/bold]")
    start = time.perf_counter()
    subprocess.run(command, check=True, cwd=Path(__file__).resolve().parent.parent)
    PHASES.append((" ".join(args[:3]), time.perf_counter() - start))


def sized_epochs(bench: Path, prepared: Path, train_seconds: float) -> dict[str, int]:
    """Each model's epochs: as many as its measured step time (bench_step.json) fits into an equal share
    of `train_seconds` on the prepared data, at least 1 and at most the gpu preset's."""
    from baselines.config import gpu
    from pipeline.io import read_table

    preset = gpu().train
    frames = read_table(prepared, "frames", columns=["split"])["split"].to_pylist().count(preset.train_split)
    steps_per_epoch = max(1, frames // preset.batch_size)
    share = train_seconds / len(MODELS)
    epochs = {}
    for row in json.loads(bench.read_text()):
        fitting = int(share // (row["step_s"] * steps_per_epoch))
        epochs[row["model"]] = max(1, min(preset.epochs, fitting))
    missing = [model for model in MODELS if model not in epochs]
    if missing:
        raise SystemExit(f"--bench {bench}: no step time of {', '.join(missing)}")
    return epochs


def contract_row(model: str, run: Path) -> dict:
    """The figures of one evaluated run: directed F1s, the sensor gap, the margin over the best constant,
    training speed and GPU memory."""
    metrics = json.loads((run / "metrics.json").read_text())
    record = json.loads((run / "run.json").read_text())
    summary = record.get("summary", {})
    floor = metrics["floor"]
    directed = {m: metrics["directed"][m]["f1"] for m in ("topo", "junction_topo")}
    other = floor["other_log_sensors"]["directed"]["topo"]["f1"]
    best = floor["best_constant"]["directed"]
    return {
        "model": model,
        "topo": directed["topo"],
        "junction_topo": directed["junction_topo"],
        "sensor_gap": directed["topo"] - other,
        "over_best_constant": directed["topo"] - best["topo"]["f1"],
        "best_constant": best["topo"]["f1"],
        "epochs": record.get("epochs"),
        "samples_per_s": summary.get("samples_per_s", float("nan")),
        "gpu_memory_gib": summary.get("gpu_memory_gib", float("nan")),
        "device": metrics.get("device", "?"),
    }


def bars(rows: list[dict], seconds: float) -> list[tuple[str, bool]]:
    """(what, passed) for every bar of the check."""
    checks = []
    for row in rows:
        checks.append(
            (f"{row['model']} reads its sensors by >= {SENSOR_GAP}", row["sensor_gap"] >= SENSOR_GAP)
        )
        checks.append((
            f"{row['model']} beats the best constant by >= {CONSTANT_MARGIN}",
            row["over_best_constant"] >= CONSTANT_MARGIN,
        ))  # fmt: skip
    lanegap = next(row for row in rows if row["model"] == "lanegap")
    checks.append((f"LaneGAP directed TOPO F1 >= {LANEGAP_TOPO}", lanegap["topo"] >= LANEGAP_TOPO))
    checks.append((f"wall time <= {WALL_SECONDS} s", seconds <= WALL_SECONDS))
    return checks


def smoke_failures(out: Path, rows: list[dict]) -> list[str]:
    """What is missing or not finite after a smoke run."""
    failures = []
    for model in MODELS:
        for name in ("checkpoint.pt", "predictions.parquet", "metrics.json", "run.json"):
            if not (out / "runs" / model / name).is_file():
                failures.append(f"missing {out / 'runs' / model / name}")
    if not (out / "report" / "report.md").is_file():
        failures.append(f"missing {out / 'report' / 'report.md'}")
    for row in rows:
        for key in ("topo", "junction_topo", "sensor_gap", "over_best_constant", "samples_per_s"):
            if not math.isfinite(row[key]):
                failures.append(f"{row['model']}: {key} is {row[key]}")
    return failures


def main() -> int:
    checkout_root("python -m baselines.gpu_check", "make gpu-check or make gpu-smoke in a clone")
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("gpu_check"))
    parser.add_argument("--smoke", action="store_true", help="tiny data, one epoch per model, any device")
    parser.add_argument("--epochs", type=int, help="every model's epochs (default: sized by --bench, else "
                        "the gpu preset's; 1 with --smoke)")  # fmt: skip
    parser.add_argument("--bench", type=Path, help="bench_step.json of this GPU: size each model's epochs")
    parser.add_argument("--train-seconds", type=float, default=270.0, help="the four trainings' time "
                        "together, for the epochs sized by --bench")  # fmt: skip
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="cli synth's and prepare's "
                        "processes (default: one per core)")  # fmt: skip
    args = parser.parse_args()
    if args.bench is not None and not args.bench.is_file():
        parser.error(
            f"--bench {args.bench}: no such file (python -m baselines.bench_step --preset gpu writes it)"
        )

    start = time.perf_counter()
    out = args.out.resolve()
    if out.exists():
        shutil.rmtree(out)
    data = SMOKE_DATA if args.smoke else DATA
    workers = f"--workers={args.workers}"
    cli("synth", "--out", str(out / "raw"), *(f"--{key}={value}" for key, value in data.items()), workers)
    prepared, sensor = out / "prepared", out / "raw" / "av2" / "sensor"
    cli("prepare", "--dataset", "av2", "--root", str(sensor), "--out", str(prepared), workers)
    epochs = {model: args.epochs or (1 if args.smoke else None) for model in MODELS}
    if args.bench is not None and not args.epochs and not args.smoke:
        epochs = sized_epochs(args.bench, prepared, args.train_seconds)
        console.print(f"epochs sized from {args.bench}: {epochs}")
    for model in MODELS:
        run = out / "runs" / model
        schedule = ["--epochs", str(epochs[model])] if epochs[model] else []
        # the gpu preset's batch of 8 takes ~21 GB on the CPU, near CI's 24: the smoke trains batches of 2
        schedule += ["--batch-size", "2"] if args.smoke else []
        cli(
            "train",
            "--model",
            model,
            "--preset",
            "gpu",
            "--data",
            str(prepared),
            "--out",
            str(run),
            *schedule,
        )
        cli("eval", "--run", str(run), "--data", str(prepared), "--split", "val")
    cli("report", "--runs", str(out / "runs"), "--out", str(out / "report"))
    seconds = time.perf_counter() - start

    rows = [contract_row(model, out / "runs" / model) for model in MODELS]
    table = Table(title=f"gpu preset on synthetic data, {rows[0]['device']}: {seconds:.0f} s in all")
    for column in ("model", "epochs", "TOPO F1", "J-TOPO F1", "sensor gap", "best constant", "over it",
                   "samples/s", "GPU GiB"):  # fmt: skip
        table.add_column(column, justify="left" if column == "model" else "right")
    for row in rows:
        table.add_row(row["model"], str(row["epochs"]), *(f"{row[k]:.3f}" for k in ("topo", "junction_topo",
                      "sensor_gap", "best_constant", "over_best_constant")), f"{row['samples_per_s']:.2f}",
                      f"{row['gpu_memory_gib']:.1f}")  # fmt: skip
    console.print(table)
    best = max(row["junction_topo"] for row in rows)
    leaders = [row["model"] for row in rows if row["junction_topo"] == best]
    console.print(f"Junction TOPO F1 is led by {' and '.join(leaders)} (the paper's claim: LaneGAP; the "
                  "report's summary says whether a lead is beyond the bootstrap interval)")  # fmt: skip
    for command, phase_seconds in PHASES:
        console.print(f"{phase_seconds:7.1f} s  cli {command}")
    checks = [] if args.smoke else bars(rows, seconds)
    summary = {"seconds": seconds, "epochs": epochs, "rows": rows, "phases": PHASES,
               "checks": [{"what": what, "passed": passed} for what, passed in checks]}  # fmt: skip
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    console.print(f"wrote {out / 'runs'}, {out / 'report' / 'report.md'} and {out / 'summary.json'}")
    if args.smoke:
        failures = smoke_failures(out, rows)
        for failure in failures:
            console.print(f"[red]smoke: {failure}[/red]")
        console.print("smoke: every output exists, every score is finite" if not failures else "smoke FAILED")
        return 1 if failures else 0
    for what, passed in checks:
        console.print(f"{'PASS' if passed else 'FAIL'}  {what}")
    return 0 if all(passed for _, passed in checks) else 1


if __name__ == "__main__":
    sys.exit(main())
