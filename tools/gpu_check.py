"""GPU acceptance in one command (`make gpu-check`): on one CUDA GPU, `cli synth` with enough frames for a
real schedule -> `cli prepare` -> `cli train` of all four models under the `gpu` preset, every model the
same number of epochs -> `cli eval` -> `cli report`, then one table of the claims against their bars.

What it proves: that every model runs, learns (reads its sensors, beats the best constant) and fits on one
GPU in minutes, with its step time, peak memory and samples/s. It does not rank the models: the paper's
ranking needs the paper's schedule (24 epochs of batch 32 on AV2). Step times (bench_step, cli train) and
FPS (cli eval) are measured under the same CUDA settings: bf16 autocast, cuDNN benchmark and TF32
(baselines.device.cuda_settings, which cli train and cli eval both call).

Bars (each model, directed F1 on the validation world that no training log drives): it reads its
sensors (its TOPO F1 minus with another log's sensors) by >= 0.15 and beats the best constant in
hindsight by >= 0.15 TOPO F1; LaneGAP reaches 0.5 TOPO F1; the whole run takes at most 10 minutes, timed
from gpu_setup.sh's start (GPU_CHECK_STARTED, epoch seconds) when it runs this, set-up included.
Whether LaneGAP leads on Junction TOPO F1 (the paper's claim) is reported either way.

Epochs, the same for every model: with `--bench` (the bench_step.json of `python -m tools.bench_step
--preset gpu`, run first on the same GPU), the most that fit all four models into `--train-seconds` (the
sum of their step times x steps per epoch x epochs), at least 1 and at most the gpu preset's; without
step times, a short fixed schedule (FALLBACK_EPOCHS); `--epochs N` sets it.

`--results DIR` (gpu_setup.sh: $GPU_CHECK_OUT): each result is copied there as its stage ends, so
that a timeout keeps what finished: after each model, runs.tar.gz (every finished run's metrics.json and
run.json, one file, so that the folder stays a handful of files, quick to copy off the machine and read)
and summary.json so far; report.md and the final summary.json at the end.

A model whose training or evaluation fails does not stop the others: summary.json records each failure
(the command, its exit status and the last lines of its output), the report covers the models that
finished, and the check exits non-zero at the end.

`--smoke` (`make gpu-smoke`, in CI): the same commands and code path on tiny data, one epoch per model at
batch 2, on whatever device there is; it fails unless every output exists and every score is finite.

    python -m tools.gpu_check [--out gpu_check] [--smoke] [--epochs N] [--bench bench_step.json]
        [--train-seconds 110] [--results DIR]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tarfile
import time
import traceback
from collections import deque
from dataclasses import asdict, dataclass
from pathlib import Path

from rich.console import Console
from rich.table import Table

MODELS = ("lanegap", "hdmapnet", "maptr", "stsu")
SENSOR_GAP = CONSTANT_MARGIN = 0.15
LANEGAP_TOPO = 0.5
WALL_SECONDS = 600
# Without measured step times nothing says that the preset's 16 epochs fit: 2 epochs (100 steps of batch 8,
# ~23 TFLOP for one step of all four by BENCHMARKS.md's GFLOPs) fit 110 s from an effective 21 TFLOP/s on.
FALLBACK_EPOCHS = 2
# The default --train-seconds: the whole check (gpu_setup.sh, set-up included) must end inside its default
# time limit, LIMIT=540 s (the 10 minutes less one); with a longer LIMIT, give a longer --train-seconds.
# Not yet measured on a GPU; estimated from the CPU dry run and BENCHMARKS.md (assumptions in brackets):
#   set-up: venv, 9 wheels --no-deps, imports, cli --help       45 s  (the CPU dry run's 57 s with other jobs)
#   bench_step: its data, 4 x (first epoch + 10 steps)           90 s  (gpu_setup.sh stops it at 120 s)
#   synth + prepare of 10 logs x 50 frames                       15 s  (22 + 4 s on 2 CPU cores, 10 processes)
#   cli train per model beyond its steps: start, imports, 8     100 s  (4 x 25 s)
#     loader workers, the first steps' cuDNN autotuning, the
#     checkpoint, the validation after the last epoch
#   cli eval per model: 100 frames twice (floor), bootstrap     100 s  (4 x 25 s; the smoke's 19-25 s on CPU)
#   the floor's constant searches, once (then cached)            40 s  (~16 s + ~26 s of metric calls)
#   cli report                                                   15 s  (the smoke's 5 s, 25 x the frames)
#   the kill's grace and the last lines (gpu_setup.sh)           15 s
#   = 420 s, which leaves 120 s of training steps: 110, the rest a margin for the estimate.
TRAIN_SECONDS = 110.0
PROVES = (
    "what this check proves: every model runs, learns (reads its sensors, beats the best constant) and fits "
    "on one GPU in minutes, with its step time, peak memory and samples/s; it does not rank the models: the "
    "paper's ranking needs the paper's schedule (24 epochs of batch 32 on AV2)"
)
SETTINGS = (
    "step times (bench_step, cli train) and FPS (cli eval) are measured under the same CUDA settings: bf16 "
    "autocast, cuDNN benchmark, TF32 (baselines.device.cuda_settings, called by cli train and cli eval)"
)
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
EXPORTED_RUN_FILES = ("metrics.json", "run.json")  # a run's files in runs.tar.gz
LAST_LINES = 20  # of a failed command's output, kept in summary.json: its error and what led to it

console = Console()
PHASES: list[tuple[str, float]] = []  # (command, seconds) of every `cli` command run so far


@dataclass
class Failure:
    """What did not finish: the model (or "report"), the command that failed, its exit status (None when it
    was no command: the run's files were unreadable) and the last lines of its output or traceback."""

    stage: str
    command: str
    exit_status: int | None
    last_lines: list[str]

    def what(self) -> str:
        """What failed, in words."""
        return self.command if self.exit_status is None else f"cli {self.command} (exit {self.exit_status})"


class CommandFailed(Exception):
    """A `cli` command that exited non-zero, with the last lines of its output."""

    def __init__(self, command: str, exit_status: int, last_lines: list[str]):
        super().__init__(f"cli {command} failed (exit {exit_status})")
        self.command, self.exit_status, self.last_lines = command, exit_status, last_lines


def cli(*args: str) -> None:
    """One `cli` command in its own process, as a user runs it; its output is shown as it comes and its last
    lines kept, for the CommandFailed it raises when it fails."""
    command = [sys.executable, "-m", "cli", *args]
    console.print(f"[bold]$ cli {' '.join(args)}[/bold]")
    start = time.perf_counter()
    last: deque[str] = deque(maxlen=LAST_LINES)
    root = Path(__file__).resolve().parent.parent
    pipe = {"stdout": subprocess.PIPE, "stderr": subprocess.STDOUT, "text": True, "errors": "replace"}
    with subprocess.Popen(command, cwd=root, **pipe) as process:
        for line in process.stdout:
            sys.stdout.write(line)
            sys.stdout.flush()
            last.append(line.rstrip("\n").rsplit("\r", 1)[-1])  # a progress bar's last state
    PHASES.append((" ".join(args[:3]), time.perf_counter() - start))
    if process.returncode:
        raise CommandFailed(" ".join(args), process.returncode, list(last))


def check_model(model: str, run: Path, prepared: Path, epochs: int, smoke: bool, bench: dict) -> dict:
    """Train and evaluate one model: its row of figures (contract_row)."""
    # the gpu preset's batch of 8 takes ~21 GB on the CPU, near CI's 24: the smoke trains batches of 2
    batch = ["--batch-size", "2"] if smoke else []
    # validation after the last epoch only: the epochs are sized by step times alone, and a pass over
    # the 100 validation frames every few epochs would spend the budget on what cli eval measures after
    cli("train", "--model", model, "--preset", "gpu", "--data", str(prepared), "--out", str(run),
        "--epochs", str(epochs), "--eval-every", "0", *batch)  # fmt: skip
    cli("eval", "--run", str(run), "--data", str(prepared), "--split", "val")
    return contract_row(model, run, bench)


def failure_of(stage: str, error: Exception) -> Failure:
    """The Failure of a stage that raised `error`."""
    if isinstance(error, CommandFailed):
        return Failure(stage, error.command, error.exit_status, error.last_lines)
    lines = "".join(traceback.format_exception(error)).splitlines()
    return Failure(stage, "reading its metrics.json and run.json", None, lines[-LAST_LINES:])


def started_at() -> tuple[float, str]:
    """(epoch seconds, what) the check's wall time counts from: gpu_setup.sh's start (GPU_CHECK_STARTED,
    set before its set-up) when it runs this, else now."""
    if os.environ.get("GPU_CHECK_STARTED"):
        return float(os.environ["GPU_CHECK_STARTED"]), "gpu_setup.sh's start, set-up included"
    return time.time(), "gpu_check's start"


def equal_epochs(bench: Path, prepared: Path, train_seconds: float) -> int:
    """The epochs of every model: the most for which the four models' measured step times (bench_step.json)
    x steps per epoch on the prepared data x epochs fit `train_seconds`, at least 1 and at most the gpu
    preset's. Equal epochs, not equal seconds: a slower model must not get fewer steps."""
    from baselines.config import gpu
    from pipeline.io import read_table

    preset = gpu().train
    frames = read_table(prepared, "frames", columns=["split"])["split"].to_pylist().count(preset.train_split)
    steps_per_epoch = max(1, frames // preset.batch_size)  # the loader drops the last partial batch
    step_s = {row["model"]: row["step_s"] for row in json.loads(bench.read_text())}
    missing = [model for model in MODELS if model not in step_s]
    if missing:
        raise SystemExit(f"--bench {bench}: no step time of {', '.join(missing)}")
    epoch_s = steps_per_epoch * sum(step_s[model] for model in MODELS)
    return max(1, min(preset.epochs, int(train_seconds // epoch_s)))


def schedule(epochs: int | None, smoke: bool, bench: Path | None, prepared: Path,
             train_seconds: float) -> tuple[int, str]:  # fmt: skip
    """(every model's epochs, where they come from)."""
    if epochs:
        return epochs, "--epochs"
    if smoke:
        return 1, "--smoke"
    if bench is not None:
        fitted = equal_epochs(bench, prepared, train_seconds)
        return fitted, f"the most that fit {train_seconds:.0f} s by the step times of {bench}"
    return FALLBACK_EPOCHS, "no step times (bench_step failed or was not run): the short fixed schedule"


def contract_row(model: str, run: Path, bench: dict[str, dict]) -> dict:
    """The figures of one evaluated run: directed F1s, the sensor gap, the margin over the best constant,
    training speed, GPU memory, FPS, and the step time bench_step measured (`bench`, by model)."""
    metrics = json.loads((run / "metrics.json").read_text())
    record = json.loads((run / "run.json").read_text())
    summary = record.get("summary", {})
    floor = metrics["floor"]
    directed = {m: metrics["directed"][m]["f1"] for m in ("topo", "junction_topo")}
    other = floor["other_log_sensors"]["directed"]["topo"]["f1"]
    best = floor["best_constant"]["directed"]
    steps_per_s = summary.get("steps_per_s", 0.0)
    return {
        "model": model,
        "topo": directed["topo"],
        "junction_topo": directed["junction_topo"],
        "sensor_gap": directed["topo"] - other,
        "over_best_constant": directed["topo"] - best["topo"]["f1"],
        "best_constant": best["topo"]["f1"],
        "epochs": record.get("epochs"),
        "steps": summary.get("steps"),
        "train_seconds": summary.get("train_seconds", float("nan")),
        "step_s": 1 / steps_per_s if steps_per_s else float("nan"),  # the training's mean, first steps too
        "bench_step_s": bench.get(model, {}).get("step_s", float("nan")),  # bench_step's median
        "samples_per_s": summary.get("samples_per_s", float("nan")),
        "gpu_memory_gib": summary.get("gpu_memory_gib", float("nan")),
        "fps": metrics.get("fps", float("nan")),
        "precision": metrics.get("precision", "?"),
        "device": metrics.get("device", "?"),
    }


def bars(rows: list[dict], seconds: float, failures: list[Failure]) -> list[tuple[str, bool]]:
    """(what, passed) for every bar of the check: a model that failed fails its own."""
    checks = [(f"{failure.stage} finishes ({failure.what()} failed)", False) for failure in failures]
    for row in rows:
        checks.append(
            (f"{row['model']} reads its sensors by >= {SENSOR_GAP}", row["sensor_gap"] >= SENSOR_GAP)
        )
        checks.append((
            f"{row['model']} beats the best constant by >= {CONSTANT_MARGIN}",
            row["over_best_constant"] >= CONSTANT_MARGIN,
        ))  # fmt: skip
    for lanegap in (row for row in rows if row["model"] == "lanegap"):
        checks.append((f"LaneGAP directed TOPO F1 >= {LANEGAP_TOPO}", lanegap["topo"] >= LANEGAP_TOPO))
    checks.append((f"wall time <= {WALL_SECONDS} s", seconds <= WALL_SECONDS))
    return checks


def smoke_failures(out: Path, rows: list[dict]) -> list[str]:
    """What is missing or not finite after a smoke run, of the models that finished (the others' failures
    are said on their own)."""
    failures = []
    for model in (row["model"] for row in rows):
        for name in ("checkpoint.pt", "predictions.parquet", "metrics.json", "run.json"):
            if not (out / "runs" / model / name).is_file():
                failures.append(f"missing {out / 'runs' / model / name}")
    if rows and not (out / "report" / "report.md").is_file():
        failures.append(f"missing {out / 'report' / 'report.md'}")
    for row in rows:
        for key in ("topo", "junction_topo", "sensor_gap", "over_best_constant", "samples_per_s"):
            if not math.isfinite(row[key]):
                failures.append(f"{row['model']}: {key} is {row[key]}")
    return failures


def export_runs(runs: Path, results: Path) -> Path:
    """results/runs.tar.gz: metrics.json and run.json of every run under `runs` that has both, as
    runs/MODEL/NAME. Written beside and renamed into place, so that a kill mid-write leaves the last one."""
    archive, partial = results / "runs.tar.gz", results / "runs.tar.gz.partial"
    with tarfile.open(partial, "w:gz") as tar:
        for run in sorted(path for path in (runs.iterdir() if runs.is_dir() else ()) if path.is_dir()):
            if all((run / name).is_file() for name in EXPORTED_RUN_FILES):
                for name in EXPORTED_RUN_FILES:
                    tar.add(run / name, arcname=f"runs/{run.name}/{name}")
    os.replace(partial, archive)
    return archive


def write_json(path: Path, value: dict) -> None:
    """`value` as indented JSON, renamed into place (a kill mid-write leaves the previous file)."""
    partial = path.with_name(path.name + ".partial")
    partial.write_text(json.dumps(value, indent=1) + "\n")
    os.replace(partial, path)


def junction_topo_lead(rows: list[dict]) -> str:
    """Which models have the highest Junction TOPO F1, as the table shows it (3 decimals): a tie reads as
    a tie (a smoke run's models often all score 0), one model with a score as no lead at all."""
    finite = [row for row in rows if math.isfinite(row["junction_topo"])]  # a diverged model's nan: no lead
    shown = {row["model"]: f"{row['junction_topo']:.3f}" for row in finite}
    if not shown:
        return "Junction TOPO F1: no model has a finite score, no lead to read"
    best = max(shown.values(), key=float)
    leaders = [model for model, value in shown.items() if value == best]
    if len(shown) == 1:
        lead = f"Junction TOPO F1 {best}: {leaders[0]} is the only model with a score, no lead to read"
    elif len(leaders) == len(shown):
        lead = f"Junction TOPO F1 is level: {', '.join(leaders)} at {best}"
    elif len(leaders) > 1:
        lead = f"Junction TOPO F1 is led by {', '.join(leaders[:-1])} and {leaders[-1]}, level at {best}"
    else:
        lead = f"Junction TOPO F1 is led by {leaders[0]} at {best}"
    unscored = [row["model"] for row in rows if row not in finite]
    lead += f" ({', '.join(unscored)}: no finite score)" if unscored else ""
    return (f"{lead} (the paper's claim: LaneGAP leads; the report's summary says whether a lead is beyond "
            "the bootstrap interval)")  # fmt: skip


def table_of(rows: list[dict], title: str) -> Table:
    """The per-model table that the check prints."""
    table = Table(title=title)
    columns = ("model", "TOPO F1", "J-TOPO F1", "sensor gap", "best constant", "over it", "s/step",
               "bench s/step", "samples/s", "GPU GiB", "FPS")  # fmt: skip
    for column in columns:
        table.add_column(column, justify="left" if column == "model" else "right")
    scores = ("topo", "junction_topo", "sensor_gap", "best_constant", "over_best_constant", "step_s",
              "bench_step_s")  # fmt: skip
    for row in rows:
        speed = (f"{row['samples_per_s']:.2f}", f"{row['gpu_memory_gib']:.1f}", f"{row['fps']:.1f}")
        table.add_row(row["model"], *(f"{row[key]:.3f}" for key in scores), *speed)
    return table


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("gpu_check"))
    parser.add_argument("--smoke", action="store_true", help="tiny data, one epoch per model, any device")
    parser.add_argument("--epochs", type=int, help="every model's epochs (default: the most that fit "
                        f"--train-seconds by --bench, else {FALLBACK_EPOCHS}; 1 with --smoke)")  # fmt: skip
    parser.add_argument("--bench", type=Path, help="bench_step.json of this GPU: size the epochs by it")
    parser.add_argument("--train-seconds", type=float, default=TRAIN_SECONDS, help="the four trainings' "
                        "steps together, for the epochs sized by --bench (the default fits gpu_setup.sh's "
                        "default LIMIT of 540 s)")  # fmt: skip
    parser.add_argument("--results", type=Path, help="copy each result here as its stage ends")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="cli synth's and prepare's "
                        "processes (default: one per core)")  # fmt: skip
    args = parser.parse_args()
    if args.bench is not None and not args.bench.is_file():
        parser.error(
            f"--bench {args.bench}: no such file (python -m tools.bench_step --preset gpu writes it)"
        )

    started, since = started_at()
    own_start = time.time()
    out = args.out.resolve()
    results = args.results.resolve() if args.results else None
    if results is not None:
        results.mkdir(parents=True, exist_ok=True)
    if out.exists():
        shutil.rmtree(out)
    bench = {row["model"]: row for row in json.loads(args.bench.read_text())} if args.bench else {}
    data = SMOKE_DATA if args.smoke else DATA
    workers = f"--workers={args.workers}"
    prepared, sensor = out / "prepared", out / "raw" / "av2" / "sensor"
    try:  # no model can run without the data
        cli("synth", "--out", str(out / "raw"), *(f"--{key}={value}" for key, value in data.items()), workers)
        cli("prepare", "--dataset", "av2", "--root", str(sensor), "--out", str(prepared), workers)
    except CommandFailed as error:
        console.print(f"[red]{error}: no model can run without its data[/red]")
        return 1
    epochs, why = schedule(args.epochs, args.smoke, args.bench, prepared, args.train_seconds)
    console.print(f"every model trains {epochs} epoch{'s' if epochs != 1 else ''}: {why}")

    def summary(rows: list[dict], checks: list[tuple[str, bool]], seconds: float, complete: bool) -> dict:
        return {"complete": complete, "seconds": seconds, "since": since,
                "gpu_check_seconds": time.time() - own_start, "epochs": epochs, "schedule": why,
                "proves": PROVES, "settings": SETTINGS, "rows": rows, "phases": PHASES,
                "failures": [asdict(failure) for failure in failures],
                "checks": [{"what": what, "passed": passed} for what, passed in checks]}  # fmt: skip

    finished: list[dict] = []
    failures: list[Failure] = []
    for model in MODELS:
        try:
            finished.append(check_model(model, out / "runs" / model, prepared, epochs, args.smoke, bench))
        except (CommandFailed, OSError, KeyError, TypeError, ValueError) as error:
            failures.append(failure_of(model, error))
            console.print(f"[red]{model} failed: {error}; the other models go on[/red]")
        if results is not None:
            export_runs(out / "runs", results)
            write_json(results / "summary.json", summary(finished, [], time.time() - started, complete=False))
    rows = finished
    if rows:  # the report of the models that finished
        runs = [f"--runs={out / 'runs' / row['model']}" for row in sorted(rows, key=lambda row: row["model"])]
        try:
            cli("report", *runs, "--out", str(out / "report"))
        except CommandFailed as error:
            failures.append(failure_of("report", error))
            console.print(f"[red]{error}[/red]")
    seconds = time.time() - started

    if rows:
        console.print(table_of(rows, f"gpu preset on synthetic data, {rows[0]['device']}, {epochs} epochs "
                                     f"each: {seconds:.0f} s since {since}"))  # fmt: skip
        console.print(junction_topo_lead(rows))
    console.print(PROVES)
    if rows:
        console.print(f"{SETTINGS}; here: {rows[0]['precision']} on {rows[0]['device']}")
    for command, phase_seconds in PHASES:
        console.print(f"{phase_seconds:7.1f} s  cli {command}")
    for failure in failures:
        console.print(f"[red]FAILED  {failure.stage}: {failure.what()}, its last lines:[/red]")
        for line in failure.last_lines:
            console.print(f"    {line}", markup=False, highlight=False)
    checks = [] if args.smoke else bars(rows, seconds, failures)
    final = summary(rows, checks, seconds, complete=True)
    write_json(out / "summary.json", final)
    if results is not None:
        write_json(results / "summary.json", final)
        if (out / "report" / "report.md").is_file():  # else the smoke's failures below say so
            shutil.copy(out / "report" / "report.md", results / "report.md")
    written = [path for path in (out / "runs", out / "report" / "report.md") if path.exists()]
    written = ", ".join(map(str, written + [out / "summary.json"]))  # what exists: no report without runs
    console.print(f"wrote {written}" + (f"; copied into {results}" if results else ""))
    if args.smoke:
        missing = smoke_failures(out, rows)
        for what in missing:
            console.print(f"[red]smoke: {what}[/red]")
        passed = not missing and not failures
        console.print("smoke: every output exists, every score is finite" if passed else "smoke FAILED")
        return 0 if passed else 1
    for what, passed in checks:
        console.print(f"{'PASS' if passed else 'FAIL'}  {what}")
    return 0 if all(passed for _, passed in checks) else 1


if __name__ == "__main__":
    sys.exit(main())
