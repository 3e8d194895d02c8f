"""Speed of scoring another codebase's result file (a benchmark, not a test).

6,019 frames (the nuScenes val set's size) of MapTRv2-format JSON: each frame's ground-truth paths with
0.1 m noise, resampled to MapTRv2's 20 points, scores 0.5-0.95, topped up to MapTRv2's 50 vectors with
low-scoring centerlines and other classes. `cli score --format maptrv2` on it (read, convert, score) is
timed against `cli score` on the graph table that conversion writes (the same graphs), alternately, each
in its own process, the same workers and bootstrap.

    python -m tools.bench_external [--frames 6019] [--workers 2] [--repeats 2]

The ground truth is the synthetic world's nuScenes frames, prepared here and repeated under new sample
tokens to the frame count, in a temporary folder.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from benchmark.roundtrip import polylines_by_frame
from pipeline.geometry import resample_polylines
from pipeline.io import SCHEMAS, read_table

VECTORS = 50  # MapTRv2's top 50 per sample (max_num)
OTHER_CLASSES = (("divider", 0), ("ped_crossing", 1), ("boundary", 2))


def ground_truth(tmp: Path, frames: int) -> tuple[Path, list[str], list[list[np.ndarray]]]:
    """(a prepared nuScenes dataset of `frames` frames, their sample tokens, each frame's paths)."""
    from pipeline.prepare import prepare
    from pipeline.synth import synth
    from pipeline.targets import TargetOptions

    synth(tmp / "raw", logs=4, frames_per_log=20, seed=0, frame_period=1.0, val_frames_per_log=20)
    base = tmp / "base"
    prepare("nuscenes", tmp / "raw" / "nuscenes", base, TargetOptions(), version="v1.0-mini")
    graphs = read_table(base, "graphs").sort_by("frame_id").to_pylist()
    paths = polylines_by_frame(base, "paths", "path_index")
    out = tmp / "prepared"
    (out / "frames").mkdir(parents=True)
    (out / "graphs").mkdir()
    shutil.copy(base / "manifest.json", out / "manifest.json")
    frame_rows, graph_rows, tokens, frame_paths = [], [], [], []
    for i in range(frames):
        source = graphs[i % len(graphs)]
        frame_id, token = f"nuscenes/scene-{i // 40:04d}/{i:08d}", f"{i:032x}"
        frame_rows.append(
            {"frame_id": frame_id, "dataset": "nuscenes", "split": "val", "sample_token": token}
        )
        graph_rows.append({**source, "frame_id": frame_id})
        tokens.append(token)
        frame_paths.append(paths.get(source["frame_id"], []))
    pq.write_table(pa.Table.from_pylist(frame_rows, SCHEMAS["frames"]), out / "frames" / "all.parquet")
    pq.write_table(pa.Table.from_pylist(graph_rows, SCHEMAS["graphs"]), out / "graphs" / "all.parquet")
    return out, tokens, frame_paths


def results_json(path: Path, tokens: list[str], frame_paths: list[list[np.ndarray]]) -> None:
    rng = np.random.default_rng(0)
    records = []
    for token, paths in zip(tokens, frame_paths):
        vectors = []
        if paths:
            xy = np.concatenate(paths).astype(np.float64)
            offsets = np.concatenate([[0], np.cumsum([len(p) for p in paths])])
            resampled, _ = resample_polylines(xy, offsets, 20)
            for pts in resampled + rng.normal(0, 0.1, resampled.shape):
                vectors.append(("centerline", 3, rng.uniform(0.5, 0.95), pts))
        while len(vectors) < VECTORS:
            name, kind = OTHER_CLASSES[len(vectors) % 3] if len(vectors) % 2 else ("centerline", 3)
            start = rng.uniform([-15, -30], [15, 30])
            pts = start + np.cumsum(rng.normal(0, 1.0, (20, 2)), axis=0)
            vectors.append((name, kind, rng.uniform(0.01, 0.45), pts))
        records.append({"sample_token": token, "vectors": [
            {"pts": pts.astype(np.float32).tolist(), "pts_num": 20, "cls_name": name, "type": kind,
             "confidence_level": float(np.float32(s))} for name, kind, s, pts in vectors]})  # fmt: skip
    path.write_text(json.dumps({"meta": {"use_camera": True}, "results": records}))


def timed(command: list[str]) -> tuple[float, float]:
    """(wall seconds, peak resident MiB) of a command, run under a fresh parent whose only child it is."""
    measure = (
        "import resource, subprocess, sys; subprocess.run(sys.argv[1:], check=True, capture_output=True); "
        "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)"
    )
    start = time.perf_counter()
    peak = subprocess.run(
        [sys.executable, "-c", measure, *command], check=True, capture_output=True, text=True
    )
    return time.perf_counter() - start, int(peak.stdout) / 1024


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=6019)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    cli = str(Path(sys.executable).parent / "cli")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        data, tokens, frame_paths = ground_truth(tmp, args.frames)
        results = tmp / "pts_bbox" / "nuscmap_results.json"
        results.parent.mkdir()
        results_json(results, tokens, frame_paths)
        common = ["--gt", str(data), "--workers", str(args.workers)]
        json_command = [cli, "score", "--pred", str(results), "--format", "maptrv2", *common]
        subprocess.run([*json_command, "--out", str(tmp / "run"), "--bootstrap", "0"], check=True,
                       capture_output=True)  # fmt: skip
        table_command = [cli, "score", "--pred", str(tmp / "run" / "predictions.parquet"), *common]
        times: dict[str, list[float]] = {"json": [], "table": []}
        peaks: dict[str, float] = {"json": 0.0, "table": 0.0}
        for _ in range(args.repeats):  # alternately: the machine's speed drifts within minutes
            for name, command in (("table", table_command), ("json", json_command)):
                seconds, peak = timed(command)
                times[name].append(seconds)
                peaks[name] = max(peaks[name], peak)
        metrics = json.loads((tmp / "run" / "metrics.json").read_text())
        size = results.stat().st_size / 2**20
    best = {k: min(v) for k, v in times.items()}
    print(f"{args.frames} frames, {metrics['external']['vectors_read']} vectors ({size:.0f} MiB of JSON), "
          f"{metrics['external']['vectors_kept']} centerlines kept, directed TOPO F1 "
          f"{metrics['directed']['topo']['f1']:.3f}; {args.workers} workers, bootstrap 1000")  # fmt: skip
    for name, label in (("table", "cli score, graph table"), ("json", "cli score --format maptrv2")):
        print(f"{label}: {', '.join(f'{t:.1f}' for t in times[name])} s, peak {peaks[name]:.0f} MiB")
    print(f"ratio (best of each): {best['json'] / best['table']:.2f} x")


if __name__ == "__main__":
    main()
