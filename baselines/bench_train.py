"""Training benchmark (`make bench-train`): LaneGAP, tiny preset, per modality, on the synthetic world.

Writes the synthetic data, prepares it, trains one run per modality and evaluates it on the synthetic
validation logs; prints and writes a JSON table of directed TOPO F1, train steps/s and frame rates.

    python -m baselines.bench_train [--out bench_train] [--epochs 60] [--modalities camera,lidar,fusion]
        [--logs 10] [--frames-per-log 20] [--frame-period 1.0]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table


def prepare_synthetic(folder: Path, logs: int, frames_per_log: int, frame_period: float = 0.1) -> Path:
    """The synthetic world written and prepared (AV2 format) under folder; reused when present.
    A frame period of 1 s instead of 0.1 s spreads the same number of frames over ten times as much of
    each route: ten times as many different views, which is what a short training run learns from."""
    from pipeline.prepare import prepare
    from pipeline.synth import synth
    from pipeline.targets import TargetOptions

    raw, prepared = folder / "raw", folder / "prepared"
    if not (prepared / "manifest.json").is_file():
        synth(raw, logs=logs, frames_per_log=frames_per_log, seed=0, frame_period=frame_period)
        prepare("av2", raw / "av2" / "sensor", prepared, TargetOptions())
    return prepared


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench_train"))
    parser.add_argument("--epochs", type=int, default=60)
    parser.add_argument("--modalities", default="camera,lidar,fusion")
    parser.add_argument("--logs", type=int, default=10)
    parser.add_argument("--frames-per-log", type=int, default=20)
    parser.add_argument("--frame-period", type=float, default=1.0, help="seconds between frames")
    args = parser.parse_args()

    from baselines.config import resolve_config
    from baselines.evaluate import evaluate
    from baselines.train import train

    data = prepare_synthetic(args.out / "data", args.logs, args.frames_per_log, args.frame_period)
    results = []
    for modality in args.modalities.split(","):
        run = args.out / f"lanegap_tiny_{modality}"
        config = resolve_config("tiny", modality=modality, epochs=args.epochs)
        start = time.perf_counter()
        summary = train(config, data, run)
        metrics = evaluate(run, data, "val", device="cpu")
        results.append(
            {
                "modality": modality,
                "epochs": args.epochs,
                "directed_topo_f1": metrics["directed"]["topo"]["f1"],
                "undirected_topo_f1": metrics["undirected"]["topo"]["f1"],
                "train_steps_per_s": summary["steps_per_s"],
                "train_seconds": time.perf_counter() - start,
                "params": metrics["params"],
                "fps_net": metrics["fps_net"],
                "fps": metrics["fps"],
            }
        )
    (args.out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    table = Table(title=f"LaneGAP tiny on the synthetic world ({args.epochs} epochs)")
    for key in results[0]:
        table.add_column(key.replace("_", " "))
    for row in results:
        table.add_row(*(f"{v:.3f}" if isinstance(v, float) else str(v) for v in row.values()))
    Console().print(table)


if __name__ == "__main__":
    main()
