"""Speed of the `openlanev2` metric variant (DET_l and TOP_ll, benchmark/metric/openlanev2.py), a benchmark,
not a test: milliseconds per frame in one process, on prepared real AV2 frames and synthetic ones.

Predictions are the ground truth with 0.1 m of noise on every vertex and one edge in ten dropped (as
tools/bench_metrics.py makes them), scored with no confidences and again with a random score per edge.

    python -m tools.bench_openlanev2 [--data DIR ...] [--repeat 3]

Without --data it writes and prepares the synthetic world, and prepares ../shared/data's AV2 logs when they
are there (`cli prepare --dataset av2 --root ../shared/data/av2/sensor`), in a temporary folder.
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
from benchmark.metric.openlanev2 import lanes_of, openlanev2_frame, openlanev2_result
from benchmark.metric.params import OpenLaneV2Params
from pipeline.lane_graph import LaneGraph
from pipeline.manifest import PreparedData
from tools.bench_metrics import noisy, prepare_default


def best_seconds(function, repeat: int) -> float:
    """The fastest of `repeat` runs, in seconds (this machine is shared: the best is the least disturbed)."""
    best = float("inf")
    for _ in range(repeat):
        start = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - start)
    return best


def measure(data: Path, repeat: int) -> list[dict]:
    """One row per kind of confidence: the times per frame of the conversion, the frame and the result."""
    gt = graphs_from_table(read_graph_table(data), data)
    rng = np.random.default_rng(0)
    pairs = [(noisy(gt[f], rng), gt[f]) for f in sorted(gt)]
    params = OpenLaneV2Params(bev_range=PreparedData.open(data).bev_range)
    rows = []
    for label, scores in (
        ("1.0", [None] * len(pairs)),
        ("random", [rng.random(len(p.src)) for p, _ in pairs]),
    ):
        n = len(pairs)
        frames = [openlanev2_frame(p, g, params, s) for (p, g), s in zip(pairs, scores)]
        result = openlanev2_result(frames)
        conversion = best_seconds(lambda: [(lanes_of(p), lanes_of(g)) for p, g in pairs], repeat)
        frame = best_seconds(
            lambda scores=scores: [openlanev2_frame(p, g, params, s) for (p, g), s in zip(pairs, scores)],
            repeat,
        )
        total = best_seconds(lambda frames=frames: openlanev2_result(frames), repeat)
        rows.append({
            "data": data.name,
            "confidences": label,
            "frames": n,
            "gt_lanes": result["lanes"]["gt"] / n,
            "pred_lanes": result["lanes"]["pred"] / n,
            "lanes_of": 1e3 * conversion / n,
            "frame": 1e3 * frame / n,
            "result": 1e3 * total / n,
            "det_l": result["det_l"],
            "top_ll": result["top_ll"],
        })  # fmt: skip
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, nargs="*", help="prepared datasets (default: build them)")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each timing; the best is shown")
    args = parser.parse_args()

    # load (or compile) the numba kernels before timing
    fork = LaneGraph(np.array([0.0, 0, 0, 3]), np.array([0.0, 10, 20, 20]), np.array([0, 1, 1], np.int32),
                     np.array([1, 2, 3], np.int32))  # fmt: skip
    openlanev2_result([openlanev2_frame(fork, fork)])
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for data in args.data or prepare_default(Path(tmp)):
            rows += measure(Path(data), args.repeat)

    table = Table(title="openlanev2 (DET_l, TOP_ll): per frame, 1 process, best of --repeat runs")
    for name in ("data", "conf.", "frames", "GT lanes", "pred lanes", "lanes_of ms", "frame ms", "result ms",
                 "DET_l", "TOP_ll"):  # fmt: skip
        table.add_column(name, justify="left" if name in ("data", "conf.") else "right")
    for r in rows:
        table.add_row(r["data"], r["confidences"], str(r["frames"]), f"{r['gt_lanes']:.1f}",
                      f"{r['pred_lanes']:.1f}", f"{r['lanes_of']:.3f}", f"{r['frame']:.3f}",
                      f"{r['result']:.3f}", f"{r['det_l']:.4f}", f"{r['top_ll']:.4f}")  # fmt: skip
    Console().print(table)
    print(
        "All per frame. conf.: the lanes' confidences, 1.0 (no score) or a random score per edge. lanes_of: "
        "both graphs to lanes; frame: openlanev2_frame (lanes_of, the Fréchet distances, the matching at "
        "each threshold, the lanes' link APs); result: openlanev2_result (the APs over all frames). "
        "Predictions: the ground truth, 0.1 m noise on every vertex, one edge in ten dropped (a dropped edge "
        "splits a lane, whose parts then match nothing)."
    )


if __name__ == "__main__":
    main()
