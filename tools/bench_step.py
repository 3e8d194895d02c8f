"""Training step time of each model under one preset on this machine's device, before a long run: how
long its schedule will take (`make gpu-check` must fit 10 minutes on one GPU).

Synthesises and prepares a small dataset (in child processes, as `cli` would: rendering threads in this
process slow its training steps), then per model: the first epoch (it fills the sample cache), the
median of the timed steps after it, samples/s, peak GPU memory and the network's time on one frame.
Measured under the settings that `cli train` and `cli eval` use (baselines.train.setup: bf16 autocast,
and on CUDA cuDNN benchmark and TF32 by baselines.device.cuda_settings); each row records them. A
failing `cli synth` or `cli prepare` prints the tail of its output and ends the run (exit 1), so that
gpu_setup.sh's log says why.

    python -m tools.bench_step [--preset gpu] [--models lanegap,hdmapnet,maptr,stsu] [--steps 10]
        [--out bench_step]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from contextlib import nullcontext
from pathlib import Path

from rich.console import Console
from rich.table import Table

ROOT = Path(__file__).resolve().parent.parent
# 4 logs (3 for training) x 12 frames: at batch 8, 4 steps an epoch
DATA = {
    "logs": 4,
    "frames-per-log": 12,
    "frame-period": 0.4,
    "val-frames-per-log": 12,
    "val-frame-period": 0.4,
}

console = Console()


def prepared_data(folder: Path) -> Path:
    """The small dataset under folder, written by `cli synth` and `cli prepare`; reused when present. A
    command that fails prints the last lines of its output and ends the run."""
    prepared = folder / "prepared"
    if not (prepared / "manifest.json").is_file():
        for args in (
            ["synth", "--out", str(folder / "raw"), *(f"--{key}={value}" for key, value in DATA.items())],
            ["prepare", "--dataset", "av2", "--root", str(folder / "raw" / "av2" / "sensor"), "--out",
             str(prepared)],
        ):  # fmt: skip
            # captured: their progress bars would fill the log; shown when they fail
            command = [sys.executable, "-m", "cli", *args]
            done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
            if done.returncode:
                raise SystemExit(failure_message(args, done))
    return prepared


def failure_message(args: list[str], done: subprocess.CompletedProcess, lines: int = 30) -> str:
    """What a failed `cli` command printed: the last `lines` of its stderr (of its stdout when stderr is
    empty), under one line naming the command and its exit status."""
    tail = (done.stderr or done.stdout or "").rstrip().splitlines()[-lines:]
    return "\n".join([f"bench_step: cli {' '.join(args)} failed (exit {done.returncode}):", *tail])


def time_model(preset: str, model: str, data: Path, steps: int) -> dict:
    """Train `model` for one epoch and then `steps` more steps; time them and one frame's inference."""
    import torch

    from baselines.data import collate
    from baselines.models import resolve_config
    from baselines.train import setup
    from pipeline.manifest import PreparedData

    cuda = torch.cuda.is_available()
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    config = resolve_config(preset, model=model)
    s = setup(config, PreparedData.open(data))
    trainer = s.trainer

    def synchronise() -> None:  # a step returns before the GPU has run it
        if cuda:
            torch.cuda.synchronize(s.device)

    start = time.perf_counter()
    for batches in s.batches():
        trainer.train_step(batches)
    synchronise()
    first_epoch = time.perf_counter() - start
    times: list[float] = []
    while len(times) < steps:
        for batches in s.batches():
            start = time.perf_counter()
            trainer.train_step(batches)
            synchronise()
            times.append(time.perf_counter() - start)
            if len(times) == steps:
                break
    step = statistics.median(times)
    model_, device, dtype = trainer.model.eval(), s.device, trainer.autocast_dtype
    sensors = collate([s.dataset[0]]).sensors.to(device)
    inference = []
    for _ in range(7):
        if cuda:
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        with torch.no_grad(), torch.autocast(device.type, dtype=dtype) if dtype else nullcontext():
            model_(sensors)
        if cuda:
            torch.cuda.synchronize(device)
        inference.append(time.perf_counter() - start)
    return {
        "model": model,
        "device": torch.cuda.get_device_name(device) if cuda else "cpu",
        "first_epoch_s": first_epoch,
        "steps_per_epoch": s.steps_per_epoch,
        "step_s": step,
        "samples_per_s": config.train.batch_size / step,
        "s_per_1000_steps": 1000 * step,
        "peak_gpu_gib": torch.cuda.max_memory_allocated(device) / 2**30 if cuda else float("nan"),
        "inference_ms": 1000 * statistics.median(inference[2:]),
        # the settings the times were taken under, as read here (cli train and cli eval set the same)
        "autocast": str(dtype).removeprefix("torch.") if dtype else "none",
        "cudnn_benchmark": torch.backends.cudnn.benchmark,
        "tf32": torch.backends.cuda.matmul.allow_tf32 and torch.backends.cudnn.allow_tf32,
    }


def model_rows(table: Table, rows: list[dict], columns: dict[str, str]) -> Table:
    """`table` with a row per model: its name, then each of `columns` (key: title) to 3 digits."""
    table.add_column("model")
    for title in columns.values():
        table.add_column(title, justify="right")
    for row in rows:
        table.add_row(row["model"], *(f"{row[key]:.3g}" for key in columns))
    return table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="gpu")
    parser.add_argument("--models", default="lanegap,hdmapnet,maptr,stsu")
    parser.add_argument("--steps", type=int, default=10, help="timed steps after the first epoch")
    parser.add_argument("--out", type=Path, default=Path("bench_step"))
    args = parser.parse_args()
    start = time.perf_counter()
    data = prepared_data(args.out.resolve())
    rows = []
    for model in args.models.split(","):
        rows.append(time_model(args.preset, model, data, args.steps))
        console.print(json.dumps(rows[-1]))
    first = rows[0]
    settings = (
        f"{first['autocast']} autocast, cuDNN benchmark {first['cudnn_benchmark']}, TF32 {first['tf32']}"
    )
    table = Table(
        title=f"{args.preset} preset, {first['device']} ({settings}): median of {args.steps} steps each"
    )
    columns = {"first_epoch_s": "first epoch s", "step_s": "s/step", "samples_per_s": "samples/s",
               "s_per_1000_steps": "s / 1000 steps", "peak_gpu_gib": "GPU GiB",
               "inference_ms": "1 frame ms"}  # fmt: skip
    console.print(model_rows(table, rows, columns))
    (args.out / "bench_step.json").write_text(json.dumps(rows, indent=1) + "\n")
    console.print(f"{time.perf_counter() - start:.0f} s in all; wrote {args.out / 'bench_step.json'}")


if __name__ == "__main__":
    main()
