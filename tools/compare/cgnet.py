"""`--metric cgnet` against CGNet's own evaluator (its topo_eval, unchanged, under its own Python) on the same
frames under seven kinds of prediction; prints the largest difference per kind (a check run by hand: CI has no
CGNet). Each frame's nine numbers (GEO / TOPO / JTOPO precision, recall, F1) are compared.

    python -m tools.compare.cgnet --cgnet CHECKOUT --cgnet-python PYTHON [--data DIR ...] [--seed 0]

CHECKOUT is a checkout of XiaoMi/CGNet, PYTHON a Python with its evaluator's packages (numpy 1.23, networkx,
scipy, shapely, opencv, Rtree 1.0.1, utm). Without --data it prepares, in a temporary folder, the real AV2
logs of ../shared/data (when they are there) and the synthetic world in both formats.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from benchmark.graph_table import graphs_from_table, read_graph_table
from benchmark.metric.cgnet import METRICS, STATS, cgnet_frame
from benchmark.metric.params import CGNetParams
from pipeline.lane_graph import LaneGraph
from tools.bench_cgnet import prepare_default

REFERENCE = Path(__file__).resolve().with_name("cgnet_one_frame.py")


def noise(g: LaneGraph, rng: np.random.Generator) -> LaneGraph:
    dx, dy = rng.normal(0.0, 0.1, (2, len(g.x))).astype(np.float32)
    return LaneGraph(g.x + dx, g.y + dy, g.src, g.dst)


def dropped_edges(g: LaneGraph, rng: np.random.Generator) -> LaneGraph:
    keep = rng.random(len(g.src)) >= 0.2
    return LaneGraph(g.x, g.y, g.src[keep], g.dst[keep])


def reversed_edges(g: LaneGraph, rng: np.random.Generator) -> LaneGraph:
    flip = rng.random(len(g.src)) < 0.3
    return LaneGraph(g.x, g.y, np.where(flip, g.dst, g.src), np.where(flip, g.src, g.dst))


def shifted(g: LaneGraph, rng: np.random.Generator) -> LaneGraph:
    dx, dy = rng.uniform(-0.6, 0.6, 2)
    return LaneGraph((g.x + dx).astype(np.float32), (g.y + dy).astype(np.float32), g.src, g.dst)


def extra_lanes(g: LaneGraph, rng: np.random.Generator) -> LaneGraph:
    """The ground truth and three false lanes of eight vertices 2 m apart, anywhere in the 30 x 60 m range."""
    xs, ys, srcs, dsts = [g.x], [g.y], [g.src], [g.dst]
    n = len(g.x)
    for _ in range(3):
        start, heading = rng.uniform((-15, -30), (15, 30)), rng.uniform(0, 2 * np.pi)
        turn = heading + np.cumsum(rng.normal(0.0, 0.1, 8))
        points = start + np.cumsum(2.0 * np.stack([np.cos(turn), np.sin(turn)], 1), 0)
        xs.append(points[:, 0].astype(np.float32))
        ys.append(points[:, 1].astype(np.float32))
        srcs.append(np.arange(n, n + 7, dtype=np.int32))
        dsts.append(np.arange(n + 1, n + 8, dtype=np.int32))
        n += 8
    return LaneGraph(*(np.concatenate(parts) for parts in (xs, ys, srcs, dsts)))


# name: (what it is, how it is made from a frame's ground truth)
KINDS: dict[str, tuple[str, Callable[[LaneGraph, np.random.Generator], LaneGraph]]] = {
    "itself": ("the ground truth", lambda g, rng: g),
    "noise": ("0.1 m noise on every vertex", noise),
    "dropped": ("20 % of edges dropped", dropped_edges),
    "reversed": ("30 % of edges reversed", reversed_edges),
    "shifted": ("shifted by up to 0.6 m", shifted),
    "extra": ("three false lanes added", extra_lanes),
    "empty": ("an empty prediction", lambda g, rng: LaneGraph.empty()),
}


def record(g: LaneGraph) -> dict:
    return {"pos": np.stack([g.x, g.y], 1).tolist(), "edges": np.stack([g.src, g.dst], 1).tolist()}


def reference(checkout: Path, python: Path, pairs: list[tuple[LaneGraph, LaneGraph]], folder: Path) -> list:
    """CGNet's numbers of each (pred, gt) pair, one process for all."""
    frames = folder / "frames.json"
    frames.write_text(json.dumps([{"pred": record(p), "gt": record(g)} for p, g in pairs]))
    run = subprocess.run([str(python), str(REFERENCE), str(checkout), str(frames), "topo"],
                         check=True, capture_output=True, text=True)  # fmt: skip
    return [json.loads(line) for line in run.stdout.splitlines()]


def differences(ours: dict, theirs: dict | None) -> dict[str, float]:
    """Per metric, the largest |ours - theirs| of its precision, recall and F1 (NaN against NaN is 0, NaN
    against a number is inf). A frame the evaluator could not score (no true node) is ours with NaN recall."""
    if theirs is None:
        return {m: 0.0 if math.isnan(ours["geo"]["recall"]) else math.inf for m in METRICS}
    out = {}
    for m in METRICS:
        worst = 0.0
        for stat, b in zip(("precision", "recall", "f1"), theirs[m]):
            a = ours[m][stat]
            if math.isnan(a) or math.isnan(b):
                worst = max(worst, 0.0 if math.isnan(a) and math.isnan(b) else math.inf)
            else:
                worst = max(worst, abs(a - b))
        out[m] = worst
    return out


def mean_of(frames: list, metric: str, stat: int) -> float:
    """The mean over frames with NaN skipped, as CGNet averages (a frame it could not score left out)."""
    values = [f[metric][stat] for f in frames if f is not None]
    values = [v for v in values if not math.isnan(v)]
    return float(np.mean(values)) if values else math.nan


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cgnet", type=Path, required=True, help="a checkout of XiaoMi/CGNet")
    parser.add_argument("--cgnet-python", type=Path, required=True, help="a Python with CGNet's packages")
    parser.add_argument("--data", type=Path, nargs="*", help="prepared datasets (default: prepare them)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the predictions")
    parser.add_argument("--kinds", nargs="*", choices=list(KINDS), default=list(KINDS), help="predictions")
    parser.add_argument("--out", type=Path, help="a JSON file for every frame's numbers, ours and CGNet's")
    args = parser.parse_args()
    evaluator = args.cgnet / "projects" / "mmdet3d_plugin" / "datasets" / "topo_eval" / "geotopo.py"
    if not evaluator.is_file():
        parser.error(f"--cgnet {args.cgnet}: no {evaluator.relative_to(args.cgnet)} there")
    if not args.cgnet_python.is_file():
        parser.error(f"--cgnet-python {args.cgnet_python}: no such file")
    params = CGNetParams()
    table = Table("data", "prediction", "frames", "GEO P/R/F1", "TOPO P/R/F1", "JTOPO P/R/F1",
                  "frames that differ", "TOPO P, R: ours / CGNet's (means)")  # fmt: skip
    worst, saved = 0.0, []
    with tempfile.TemporaryDirectory() as folder:
        tmp = Path(folder)
        datasets = {str(p): p for p in args.data} if args.data else prepare_default(tmp)
        for name, path in datasets.items():
            by_frame = graphs_from_table(read_graph_table(path), path)
            gts = [by_frame[f] for f in sorted(by_frame)]
            for kind in args.kinds:
                what, make = KINDS[kind]
                rng = np.random.default_rng([args.seed, list(KINDS).index(kind)])
                pairs = [(make(g, rng), g) for g in gts]
                ours = [cgnet_frame(p, g, params) for p, g in pairs]
                theirs = reference(args.cgnet, args.cgnet_python, pairs, tmp)
                diffs = [differences(a, b) for a, b in zip(ours, theirs)]
                largest = {m: max(d[m] for d in diffs) for m in METRICS}
                differ = sum(any(v > 0 for v in d.values()) for d in diffs)
                worst = max(worst, *largest.values())
                listed = [{m: [o[m][s] for s in STATS] for m in METRICS} for o in ours]
                means = " / ".join(f"{mean_of(f, 'topo', s):.4f}" for s in (0, 1) for f in (listed, theirs))
                saved.append({"data": name, "kind": kind, "frames": sorted(by_frame), "ours": listed,
                              "theirs": theirs})  # fmt: skip
                table.add_row(name, what, str(len(gts)), *(f"{largest[m]:.3g}" for m in METRICS), str(differ),
                              means)  # fmt: skip
    if args.out:
        args.out.write_text(json.dumps(saved))
    console = Console(width=200)
    console.print(table)
    console.print("each column: the largest |ours - CGNet's| over the frames of its precision, recall and F1")
    sys.exit(0 if worst == 0 else 1)


if __name__ == "__main__":
    main()
