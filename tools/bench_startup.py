"""Start-up of `cli score` (a benchmark, not a test): one frame scored as a whole process, with the kernels'
ahead-of-time build (pipeline/kernels.py), under numba's JIT with its cache warm (LANEGRAPH_JIT=1), and beside
CGNet's evaluator on the same frame when a CGNet checkout and a Python with its packages are given
(tools/compare/cgnet_one_frame.py). The commands run in turn, one run of each per round; a ratio is the median
over rounds of that round's pair.

    python -m tools.bench_startup [--runs 9] [--cgnet CHECKOUT --cgnet-python PYTHON]

The frame: the real AV2 frame of median size of ../shared/data's logs (else the synthetic world's), and a
prediction of it with 0.1 m of noise on every vertex and one edge in ten dropped.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from rich.console import Console
from rich.table import Table

from benchmark.graph_table import graph_row, graphs_from_table, read_graph_table
from pipeline.kernels import aot_status
from tools.bench_cgnet import noisy, prepare_default

REPO = Path(__file__).resolve().parents[1]


def one_frame(tmp: Path) -> tuple[str, Path, Path, Path, int]:
    """(data's name, prediction file, ground-truth file, the frame for CGNet, its vertices)."""
    name, data = next(iter(prepare_default(tmp / "data").items()))
    graphs = graphs_from_table(read_graph_table(data), data)
    frame_id = sorted(graphs, key=lambda f: (len(graphs[f].x), f))[len(graphs) // 2]
    gt = graphs[frame_id]
    pred = noisy(gt, np.random.default_rng(0))
    files = {}
    for kind, g in (("gt", gt), ("pred", pred)):
        files[kind] = tmp / f"{kind}.parquet"
        pq.write_table(pa.Table.from_pylist([graph_row(frame_id, g)]), files[kind])
    record = {
        kind: {"pos": np.stack([g.x, g.y], 1).tolist(), "edges": np.stack([g.src, g.dst], 1).tolist()}
        for kind, g in (("gt", gt), ("pred", pred))
    }
    (tmp / "frame.json").write_text(json.dumps(record))
    return name, files["pred"], files["gt"], tmp / "frame.json", len(gt.x)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=9, help="rounds; each command runs once a round")
    parser.add_argument("--cgnet", type=Path, help="a checkout of XiaoMi/CGNet")
    parser.add_argument("--cgnet-python", type=Path, help="a Python with CGNet's evaluator's packages")
    args = parser.parse_args()
    cli = Path(sys.executable).with_name("cli")
    with tempfile.TemporaryDirectory() as folder:
        tmp = Path(folder)
        name, pred, gt, frame, vertices = one_frame(tmp)
        commands: dict[str, tuple[list[str], dict]] = {}
        for metric in ("cgnet", "lanegap"):
            score = [str(cli), "score", "--pred", str(pred), "--gt", str(gt), "--metric", metric, "--json"]
            commands[f"cli score --metric {metric}"] = (score, {"LANEGRAPH_JIT": "0"})
            commands[f"cli score --metric {metric}, LANEGRAPH_JIT=1"] = (score, {"LANEGRAPH_JIT": "1"})
        if args.cgnet and args.cgnet_python:
            script = str(REPO / "tools" / "compare" / "cgnet_one_frame.py")
            for mode in ("topo", "full"):
                run = [str(args.cgnet_python), script, str(args.cgnet), str(frame), mode]
                commands[f"CGNet's evaluator, {mode}"] = (run, {})
        seconds = {key: [] for key in commands}
        for round_ in range(args.runs + 1):  # the first round warms the caches and is not counted
            for key, (command, env) in commands.items():
                start = time.perf_counter()
                subprocess.run(command, env={**os.environ, **env}, check=True, capture_output=True)
                if round_:
                    seconds[key].append(time.perf_counter() - start)
    yardstick = next(
        k for k in ("CGNet's evaluator, topo", "cli score --metric cgnet, LANEGRAPH_JIT=1") if k in seconds
    )
    table = Table("command", "median s", "min s", "max s", f"÷ {yardstick} (median of pairs)")
    for key, values in seconds.items():
        ratio = np.median(np.array(values) / seconds[yardstick])
        table.add_row(
            key, f"{np.median(values):.3f}", f"{min(values):.3f}", f"{max(values):.3f}", f"{ratio:.2f}"
        )
    console = Console()
    console.print(table)
    console.print(f"one frame of {name} ({vertices} vertices), {args.runs} rounds")
    if not args.cgnet:
        console.print("--cgnet CHECKOUT --cgnet-python PYTHON adds CGNet's evaluator on the same frame")
    console.print(f"the kernels' ahead-of-time build: {aot_status()}")


if __name__ == "__main__":
    main()
