"""Speed of CGNet's GEO / TOPO / JTOPO (benchmark/metric/cgnet.py; a benchmark, not a test): ms per frame in
one process on prepared frames, each scored against itself and against a realistic prediction (0.1 m of
noise on every vertex, one edge in ten dropped), with the averaged scores.

    python -m tools.bench_cgnet [--data DIR ...] [--repeat 1]

Without --data it prepares, in a temporary folder, the real AV2 logs of ../shared/data (when they are there)
and the synthetic world in both formats.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from benchmark.graph_table import graphs_from_table, read_graph_table
from benchmark.metric.cgnet import cgnet_frame, cgnet_result, interpolated
from benchmark.metric.params import CGNetParams
from pipeline.lane_graph import LaneGraph

SHARED_AV2 = Path(__file__).resolve().parents[2] / "shared" / "data" / "av2" / "sensor"


def prepare_default(tmp: Path) -> dict[str, Path]:
    from pipeline.prepare import prepare
    from pipeline.synth import synth
    from pipeline.targets import TargetOptions

    out = {}
    if SHARED_AV2.is_dir():
        prepare("av2", SHARED_AV2, tmp / "av2", TargetOptions())
        out["real AV2"] = tmp / "av2"
    else:
        Console(stderr=True).print(f"{SHARED_AV2}: not found, the real AV2 rows are left out")
    synth(tmp / "raw", logs=4, frames_per_log=20, seed=0, frame_period=1.0, val_frames_per_log=20)
    prepare("av2", tmp / "raw" / "av2" / "sensor", tmp / "synth_av2", TargetOptions())
    options = TargetOptions()
    prepare("nuscenes", tmp / "raw" / "nuscenes", tmp / "synth_nuscenes", options, version="v1.0-mini")
    out["synthetic, AV2 format"] = tmp / "synth_av2"
    out["synthetic, nuScenes format"] = tmp / "synth_nuscenes"
    return out


def noisy(g: LaneGraph, rng: np.random.Generator) -> LaneGraph:
    keep = rng.random(len(g.src)) >= 0.1
    dx, dy = rng.normal(0.0, 0.1, (2, len(g.x))).astype(np.float32)
    return LaneGraph(g.x + dx, g.y + dy, g.src[keep], g.dst[keep])


def timed(pairs: list[tuple[LaneGraph, LaneGraph]], params: CGNetParams, repeat: int):
    """Each frame's scores and its best time of `repeat` runs, in ms."""
    frames, ms = [], np.empty(len(pairs))
    for i, (pred, gt) in enumerate(pairs):
        best = np.inf
        for _ in range(repeat):
            start = time.perf_counter()
            scores = cgnet_frame(pred, gt, params)
            best = min(best, time.perf_counter() - start)
        frames.append(scores)
        ms[i] = 1e3 * best
    return frames, ms


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, nargs="*", help="prepared datasets (default: prepare them)")
    parser.add_argument("--repeat", type=int, default=1, help="times each frame is timed (the best kept)")
    args = parser.parse_args()
    params = CGNetParams()
    table = Table("data", "frames", "nodes", "prediction", "ms / frame", "p95 ms", "GEO F1", "TOPO F1",
                  "JTOPO F1")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        datasets = {str(p): p for p in args.data} if args.data else prepare_default(Path(tmp))
        graphs = {name: graphs_from_table(read_graph_table(path), path) for name, path in datasets.items()}
    first = next(iter(graphs.values()))
    some = first[sorted(first)[0]]
    cgnet_frame(noisy(some, np.random.default_rng(0)), some, params)  # compile (or load) the numba kernels
    rng = np.random.default_rng(0)
    for name, by_frame in graphs.items():
        gts = [by_frame[f] for f in sorted(by_frame)]
        nodes = np.mean([len(interpolated(g, params)[0]) for g in gts])
        kinds = {"itself": [(g, g) for g in gts], "0.1 m noise": [(noisy(g, rng), g) for g in gts]}
        for kind, pairs in kinds.items():
            frames, ms = timed(pairs, params, args.repeat)
            result = cgnet_result(frames, params)
            f1 = [result[m]["f1"] for m in ("geo", "topo", "jtopo")]
            f1 = ["-" if v is None else f"{v:.4f}" for v in f1]
            table.add_row(name, str(len(gts)), f"{nodes:.0f}", kind, f"{ms.mean():.2f}",
                          f"{np.percentile(ms, 95):.2f}", *f1)  # fmt: skip
    Console().print(table)
    Console().print("nodes: the ground truth's interpolated nodes per frame (2.5 dm parts); one process")


if __name__ == "__main__":
    main()
