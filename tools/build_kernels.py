"""Compile the kernels that `cli score` calls ahead of time (pipeline/kernels.py says why and how they are
found): pipeline/_aot_kernels.*.so and pipeline/_aot_kernels.json. `make kernels` runs it when a module
changed, and so do `make test` and `make bench`.

    python -m tools.build_kernels

The argument types are those of real calls: in a temporary folder a tiny synthetic nuScenes world is
prepared, then `cli score`'s scoring (benchmark.score.score) scores a graph table, a MapTRv2 file and a CGNet
file of it under every metric, every kernel under numba and its calls recorded; each recorded (kernel,
argument types) is exported. numba.pycc builds them for any x86-64 CPU, into a temporary folder; then every
earlier compiled module beside pipeline/kernels.py (of this Python or any other) is removed, the new one moved
there, and the index written last with its file name and sha256: the loader loads that file alone, and only
when its bytes are those the index records.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from benchmark.graph_table import graph_row, graphs_from_table, read_graph_table
from benchmark.metric.table import METRICS
from pipeline import kernels
from pipeline.io import read_table
from tools.bench_cgnet import noisy


def results_file(path: Path, data: Path, table: str, cls: tuple[str, int]) -> Path:
    """A MapTRv2 (table "paths") or CGNet (table "pieces") result file of the val frames: each line with 0.1 m
    of noise at a score in 0.5-0.95, plus one low-scoring line (nuScenes: our frame is the codebase's)."""
    rng = np.random.default_rng(0)
    frames = read_table(data, "frames", ["frame_id", "split", "sample_token"]).to_pylist()
    lines: dict[str, list] = {}
    for row in read_table(data, table, ["frame_id", "x", "y"]).to_pylist():
        lines.setdefault(row["frame_id"], []).append(np.stack([row["x"], row["y"]], axis=1))
    records = []
    for frame in (f for f in frames if f["split"].endswith("val")):
        xys = [xy + rng.normal(0.0, 0.1, xy.shape) for xy in lines.get(frame["frame_id"], [])]
        xys.append(np.array([[-14.0, 29.0], [14.0, -29.0]]))
        vectors = [
            {"pts": xy.tolist(), "pts_num": len(xy), "cls_name": cls[0], "type": cls[1],
             "confidence_level": 0.25 if i == len(xys) - 1 else float(rng.uniform(0.5, 0.95))}
            for i, xy in enumerate(xys)
        ]  # fmt: skip
        records.append({"sample_token": frame["sample_token"], "vectors": vectors})
    path.write_text(json.dumps({"meta": {"use_camera": True}, "results": records}))
    return path


def install_module(built: Path, folder: Path) -> dict[str, str]:
    """Move the compiled module `built` into `folder` once every earlier one there is removed; the index's
    record of it: {"file": its name, "sha256": its digest}."""
    for earlier in kernels.compiled_modules(folder):
        earlier.unlink()
    target = folder / built.name
    shutil.move(built, target)
    return {"file": target.name, "sha256": kernels.file_digest(target)}


def workload(tmp: Path) -> None:
    """What `cli score` runs on a graph table, a MapTRv2 file and a CGNet file, every metric."""
    from benchmark.metric.bootstrap import DRAWS
    from benchmark.score import score
    from pipeline.prepare import prepare
    from pipeline.synth import synth
    from pipeline.targets import TargetOptions

    synth(tmp / "raw", logs=2, frames_per_log=4, seed=0, frame_period=1.0, val_frames_per_log=4)
    data = tmp / "prepared"
    prepare("nuscenes", tmp / "raw" / "nuscenes", data, TargetOptions(), version="v1.0-mini")
    rng = np.random.default_rng(0)
    graphs = graphs_from_table(read_graph_table(data), data)
    rows = [graph_row(frame_id, noisy(g, rng)) for frame_id, g in sorted(graphs.items())]
    pq.write_table(pa.Table.from_pylist(rows), tmp / "pred.parquet")
    runs = {
        "graph": tmp / "pred.parquet",
        "maptrv2": results_file(tmp / "maptrv2.json", data, "paths", ("centerline", 3)),
        "cgnet": results_file(tmp / "cgnet.json", data, "pieces", ("centerline", 0)),
    }
    for fmt, pred in runs.items():
        score(pred, data, fmt=fmt, bootstrap=DRAWS, metrics=METRICS)


def main() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numba.pycc's pending deprecation: it is what builds them today
        from numba.pycc import CC

    start = time.perf_counter()
    sources = kernels.source_hashes()
    kernels.AOT_INDEX.unlink(missing_ok=True)  # a build cut short leaves no index, so none is used
    recorded = kernels.record_calls()
    with tempfile.TemporaryDirectory() as tmp:
        workload(Path(tmp))
    if kernels.source_hashes() != sources:
        raise SystemExit("tools.build_kernels: a module changed while it ran; run it again")
    folder = kernels.AOT_INDEX.parent
    index: dict[str, list] = {}
    with tempfile.TemporaryDirectory() as tmp:
        cc = CC(kernels.AOT_NAME)
        cc.output_dir = tmp
        for k, calls in sorted(recorded.items(), key=lambda item: item[0].key):
            for types, numba_types in calls.items():
                if numba_types not in k.dispatcher.overloads:
                    k.dispatcher.compile(numba_types)
                name = f"k{sum(map(len, index.values()))}"
                cc.export(name, k.dispatcher.overloads[numba_types].signature)(k.py_func)
                index.setdefault(k.key, []).append([types, name])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # numba.pycc's pending deprecation: it is what builds them today
            cc.compile()
        module = install_module(Path(cc.output_dir, cc.output_file), folder)
    kernels.AOT_INDEX.write_text(
        json.dumps(
            {"numpy": np.__version__, "sources": sources, "module": module, "kernels": index}, indent=1
        ) + "\n"
    )  # fmt: skip
    versions = sum(map(len, index.values()))
    print(
        f"compiled {versions} versions of {len(index)} kernels ahead of time in "
        f"{time.perf_counter() - start:.0f} s: {folder / module['file']}, {kernels.AOT_INDEX}"
    )


if __name__ == "__main__":
    main()
