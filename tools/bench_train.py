"""Training benchmark (`make bench-train`): every model, tiny preset, the same data and epochs.

Writes the synthetic data, prepares it, trains one run per model and modality and evaluates it on the
synthetic validation logs; prints one comparison table (directed and undirected Junction TOPO / TOPO
P, R, F1, the blind floor, params, GFLOPs, train steps/s, FPS) and writes it as JSON.

    python -m tools.bench_train [--out bench_train] [--epochs N] [--models lanegap,hdmapnet,maptr,stsu]
        [--modalities camera] [--worlds 4] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table


def prepare_synthetic(folder: Path, worlds: int = 4, seed: int = 0) -> Path:
    """`cli synth`'s default data (16 training logs x 10 frames 2 s apart, 2 validation logs x 20 frames
    1 s apart; with 4 worlds validation drives in a world of its own, with 1 on the training roads)
    written and prepared (AV2 format) under folder; reused when present."""
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
    parser.add_argument("--epochs", type=int, help="default: the tiny preset's (the learning checks')")
    parser.add_argument("--models", default="lanegap,hdmapnet,maptr,stsu")
    parser.add_argument("--modalities", default="camera")
    parser.add_argument("--worlds", type=int, default=4, help="4: validation on unseen roads; 1: the same")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    from baselines.evaluate import evaluate
    from baselines.models import resolve_config
    from baselines.train import train

    data = prepare_synthetic(args.out / f"data_w{args.worlds}_s{args.seed}", args.worlds, args.seed)
    results = []
    for model in args.models.split(","):
        for modality in args.modalities.split(","):
            run = args.out / f"{model}_tiny_{modality}"
            config = resolve_config("tiny", modality=modality, epochs=args.epochs, model=model)
            start = time.perf_counter()
            summary = train(config, data, run, overwrite=True)
            metrics = evaluate(run, data, "val", device="cpu")
            row = {"model": model, "modality": modality, "epochs": config.train.epochs}
            names = {"junction_topo": "J-TOPO", "topo": "TOPO"}
            for mode, short in (("directed", "dir"), ("undirected", "undir")):
                for metric, name in names.items():
                    for key in ("precision", "recall", "f1"):
                        row[f"{short} {name} {key[0].upper()}"] = metrics[mode][metric][key]
            floor = metrics["floor"]["f1"]["directed"] if metrics.get("floor") else {}
            row |= {
                "floor TOPO F1": floor.get("topo", float("nan")),
                "params (M)": metrics["params"] / 1e6,
                "GFLOPs": metrics["gflops"],
                "train steps/s": summary["steps_per_s"],
                "FPS": metrics["fps"],
                "seconds": time.perf_counter() - start,
            }
            results.append(row)
    (args.out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    # one column per run, so that four models fit a terminal
    epochs = results[0]["epochs"]
    title = f"tiny preset on the synthetic data ({epochs} epochs, {args.worlds} worlds, seed {args.seed})"
    table = Table(title=title)
    table.add_column("")
    for row in results:
        table.add_column(f"{row['model']} {row['modality']}", justify="right")
    for key in list(results[0])[3:]:
        table.add_row(key, *(f"{row[key]:.3f}" for row in results))
    Console().print(table)


if __name__ == "__main__":
    main()
