"""What a long run's safety costs (`make bench-long-run`), per model of one preset on this machine's device:
a validation frame against a training frame, and a checkpoint's stall of the step against its whole write.

Per model: the median seconds of a training step per frame (after two warm-up steps), of a validation
frame (the network, the post-processing to a lane graph and the metric, as `cli train --eval-every` runs
it), and of a checkpoint: the copy of the full state to the host (what the step waits for) and the hash
and write that the writer's thread does meanwhile (what it would wait for, written in the loop).
`val/train` is the validation frame's cost in training frames: a validation of V frames every E epochs of T
frames costs val/train x V / (E x T) of the training time.

    python -m tools.bench_long_run [--preset tiny] [--models lanegap,hdmapnet] [--data PREPARED]
        [--steps 6] [--frames 8] [--batch-size B] [--out bench_long_run]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table

console = Console()


def synchronise(device) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def measure(preset: str, model: str, data: Path, steps: int, frames: int, batch_size: int = 0) -> dict:
    import torch

    from baselines.checkpoint import on_host, save_checkpoint
    from baselines.models import resolve_config
    from baselines.train import all_rng_states, setup
    from baselines.validate import Validation
    from pipeline.manifest import PreparedData

    config = resolve_config(preset, model=model, from_scratch=preset == "paper")
    config.train.eval_frames = frames
    config.train.batch_size = batch_size or config.train.batch_size  # a frame's cost, at fewer frames a step
    prepared = PreparedData.open(data)
    s = setup(config, prepared)
    trainer, per_step = s.trainer, config.train.batch_size
    times = []
    for group in s.batches():
        start = time.perf_counter()
        trainer.train_step(group)
        synchronise(s.device)
        times.append(time.perf_counter() - start)
        if len(times) == steps + 2:
            break
    train_frame = statistics.median(times[2:]) / per_step
    validation = Validation(config, prepared, s.built.needs, s.device, trainer.autocast_dtype)
    validation(s.built)  # warm-up: the loader's first reads, cuDNN's choice of kernels
    record = validation(s.built)
    val_frame = record["seconds"] / record["frames"]
    state = trainer.state(1, 0, config, all_rng_states(False), {})
    start = time.perf_counter()
    on_host(state)
    copy_seconds = time.perf_counter() - start
    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        save_checkpoint(state, Path(folder) / "checkpoint.pt")
        write_seconds = time.perf_counter() - start
        size = (Path(folder) / "checkpoint.pt").stat().st_size
    return {
        "model": model,
        "preset": preset,
        "device": torch.cuda.get_device_name(s.device) if s.device.type == "cuda" else "cpu",
        "train_frame_s": train_frame,
        "val_frame_s": val_frame,
        "val_per_train": val_frame / train_frame,
        "val_frames": record["frames"],
        "checkpoint_mib": size / 2**20,
        "checkpoint_copy_s": copy_seconds,
        "checkpoint_write_s": write_seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--models", default="lanegap,hdmapnet")
    parser.add_argument("--data", type=Path, help="a prepared dataset (default: cli synth's, written once)")
    parser.add_argument("--steps", type=int, default=6, help="timed training steps after two warm-up steps")
    parser.add_argument("--frames", type=int, default=8, help="validation frames timed")
    parser.add_argument("--batch-size", type=int, default=0, help="frames per step (default: the preset's)")
    parser.add_argument("--out", type=Path, default=Path("bench_long_run"))
    args = parser.parse_args()
    from tools.bench_step import model_rows
    from tools.bench_train import prepare_synthetic

    data = args.data or prepare_synthetic(args.out / "data")
    rows = [measure(args.preset, model, data, args.steps, args.frames, args.batch_size)
            for model in args.models.split(",")]  # fmt: skip
    table = Table(title=f"{args.preset} preset, {rows[0]['device']}: a validation frame and a checkpoint")
    columns = {"train_frame_s": "train s/frame", "val_frame_s": "val s/frame", "val_per_train": "val/train",
               "checkpoint_mib": "checkpoint MiB", "checkpoint_copy_s": "copy s (stall)",
               "checkpoint_write_s": "hash+write s"}  # fmt: skip
    console.print(model_rows(table, rows, columns))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_long_run.json").write_text(json.dumps(rows, indent=1) + "\n")
    console.print(f"wrote {args.out / 'bench_long_run.json'}")


if __name__ == "__main__":
    main()
