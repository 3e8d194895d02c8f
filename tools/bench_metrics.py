"""Speed of the metric and of Path2Graph (a benchmark, not a test).

Scores 6,019 frames (the size of the nuScenes val set): the prepared synthetic and real AV2 ground
truth, repeated, against realistic predictions (the ground truth with 0.1 m noise on every vertex
and one edge in ten dropped). Then `cli score` on the same 6,019 frames written as graph tables, in its own
process, for its peak memory (resident set), and Path2Graph on the paths of the same frames.

    python -m tools.bench_metrics [--data DIR ...] [--frames 6019] [--workers 2]

Without --data it writes and prepares the synthetic world, and prepares ../shared/data's AV2 logs
when they are there, in a temporary folder.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmark.graph_table import graph_row, graphs_from_table
from benchmark.graphs.path2graph import path2graph
from benchmark.metric.params import MetricParams
from benchmark.roundtrip import polylines_by_frame
from benchmark.score import score_pairs
from pipeline.io import SCHEMAS, read_table
from pipeline.lane_graph import LaneGraph

SHARED_AV2 = Path(__file__).resolve().parents[2] / "shared" / "data" / "av2" / "sensor"


def prepare_default(tmp: Path) -> list[Path]:
    from pipeline.prepare import prepare
    from pipeline.synth import synth
    from pipeline.targets import TargetOptions

    synth(tmp / "raw", logs=4, frames_per_log=20, seed=0, frame_period=1.0, val_frames_per_log=20)
    prepare("av2", tmp / "raw" / "av2" / "sensor", tmp / "synth", TargetOptions())
    out = [tmp / "synth"]
    if SHARED_AV2.is_dir():
        prepare("av2", SHARED_AV2, tmp / "av2", TargetOptions())
        out.append(tmp / "av2")
    return out


def noisy(g: LaneGraph, rng: np.random.Generator) -> LaneGraph:
    keep = rng.random(len(g.src)) >= 0.1
    dx, dy = rng.normal(0.0, 0.1, (2, len(g.x))).astype(np.float32)
    return LaneGraph(g.x + dx, g.y + dy, g.src[keep], g.dst[keep])


def cli_score_peak_mib(pairs: list[tuple[LaneGraph, LaneGraph]], folder: Path) -> tuple[float, float]:
    """Write the pairs as prediction and ground-truth graph tables, run `cli score` on them in a child
    process; returns (its peak resident memory in MiB, the two tables' size on disk in MiB)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    files = []
    for name, side in (("pred", 0), ("gt", 1)):
        rows = [graph_row(f"frame{i:05d}", pair[side]) for i, pair in enumerate(pairs)]
        files.append(folder / f"{name}.parquet")
        pq.write_table(pa.Table.from_pylist(rows, SCHEMAS["graphs"]), files[-1])
    cli = str(Path(sys.executable).parent / "cli")
    command = [cli, "score", "--pred", str(files[0]), "--gt", str(files[1])]
    # A fresh parent whose only child is `cli score`: this process's own children (the metric's worker
    # pool, forked from a process holding all frames) would count in RUSAGE_CHILDREN.
    measure = (
        "import resource, subprocess, sys; subprocess.run(sys.argv[1:], check=True, capture_output=True); "
        "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)"
    )
    peak_kib = subprocess.run([sys.executable, "-c", measure, *command], check=True, capture_output=True,
                              text=True).stdout  # fmt: skip
    return int(peak_kib) / 1024, sum(f.stat().st_size for f in files) / 2**20


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, nargs="*", help="prepared datasets (default: build them)")
    parser.add_argument("--frames", type=int, default=6019)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        datasets = args.data or prepare_default(Path(tmp))
        graphs, paths = [], []
        for data in datasets:
            gt = graphs_from_table(read_table(data, "graphs"), data)
            by_frame = polylines_by_frame(data, "paths", "path_index")
            graphs += [gt[f] for f in sorted(gt)]
            paths += [by_frame.get(f, []) for f in sorted(gt)]
    rng = np.random.default_rng(0)
    frames = [graphs[i % len(graphs)] for i in range(args.frames)]
    pairs = [(noisy(g, rng), g) for g in frames]
    n_vertices = np.mean([len(g.x) for g in graphs])
    print(
        f"{len(graphs)} distinct frames from {len(datasets)} dataset(s), {n_vertices:.0f} vertices per frame"
    )

    score_pairs(pairs[:2], MetricParams())  # compile (or load) the numba kernels
    for workers in sorted({1, args.workers}):
        count = len(pairs) if workers == args.workers else min(len(pairs), 600)
        start, cpu = time.perf_counter(), time.process_time()
        result = score_pairs(pairs[:count], MetricParams(), workers)
        seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
        print(
            f"metric, {workers} process(es): {count} frames in {seconds:.1f} s = "
            f"{1e3 * seconds / count:.2f} ms per frame"
            + (f" ({1e3 * cpu / count:.2f} ms of CPU)" if workers == 1 else "")
            + f", directed TOPO F1 {result['directed']['topo']['f1']:.4f}"
        )

    with tempfile.TemporaryDirectory() as tmp:
        peak, size = cli_score_peak_mib(pairs, Path(tmp))
    print(f"cli score, {len(pairs)} frames ({size:.0f} MiB of Parquet): peak memory {peak:.0f} MiB")

    path2graph(paths[0])
    for merge_radius in (0.15, 0.0):
        start = time.process_time()
        for p in paths:
            path2graph(p, merge_radius=merge_radius)
        seconds = time.process_time() - start
        n_paths = np.mean([len(p) for p in paths])
        print(
            f"Path2Graph (merge_radius {merge_radius}): {len(paths)} frames, {n_paths:.1f} paths each, "
            f"{1e3 * seconds / len(paths):.2f} ms of CPU per frame"
        )


if __name__ == "__main__":
    main()
