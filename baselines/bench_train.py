"""Training benchmark (`make bench-train`): LaneGAP, tiny preset, per modality, on the synthetic world.

Writes the synthetic data, prepares it, trains one run per modality and evaluates it on the synthetic
validation logs; prints and writes a JSON table of directed TOPO F1, train steps/s and frame rates.

    python -m baselines.bench_train [--out bench_train] [--epochs 60] [--modalities camera,lidar,fusion]
        [--worlds 4] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table


def prepare_synthetic(folder: Path, worlds: int = 4, seed: int = 0) -> Path:
    """`cli synth`'s default data (10 logs x 20 frames 1 s apart; with 4 worlds validation drives in a
    world of its own, with 1 on the training roads) written and prepared (AV2 format) under folder;
    reused when present."""
    from pipeline.prepare import prepare
    from pipeline.synth import synth
    from pipeline.targets import TargetOptions

    raw, prepared = folder / "raw", folder / "prepared"
    if not (prepared / "manifest.json").is_file():
        synth(raw, seed=seed, worlds=worlds)
        prepare("av2", raw / "av2" / "sensor", prepared, TargetOptions())
    return prepared


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench_train"))
    parser.add_argument("--epochs", type=int, default=60)
    parser.add_argument("--modalities", default="camera,lidar,fusion")
    parser.add_argument("--worlds", type=int, default=4, help="4: validation on unseen roads; 1: the same")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    from baselines.config import resolve_config
    from baselines.evaluate import evaluate
    from baselines.train import train

    data = prepare_synthetic(args.out / f"data_w{args.worlds}_s{args.seed}", args.worlds, args.seed)
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
                "directed_junction_topo_f1": metrics["directed"]["junction_topo"]["f1"],
                "undirected_topo_f1": metrics["undirected"]["topo"]["f1"],
                "floor_topo_f1": metrics["floor"]["f1"]["directed"]["topo"],
                "floor_junction_topo_f1": metrics["floor"]["f1"]["directed"]["junction_topo"],
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
