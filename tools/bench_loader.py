"""Can one machine feed a GPU? Samples/s of the training data path on full-size camera images.

The synthetic images are 1/4 (nuScenes, 400 x 225) and 1/8 (AV2, 256 x 194) of the real sizes, so
their timings say nothing about real loading. This writes, into a temporary copy of a prepared
synthetic dataset, full-size JPEGs of the same scenes: each synthetic image scaled back up (6 cameras
at 1600 x 900, 7 at 2048 x 1552 of which the front one portrait) with the intrinsics scaled alike
(the calibration the synthetic rig divided), and fresh sensor noise at full size (sigma --noise grey
levels) so that the JPEGs (quality --quality) carry real-looking high-frequency content; their size
per image is printed. The LiDAR sweeps are the synthetic ones (already of real density).

Then it times baselines/data.py as `cli train` runs it (PreparedDataset.__getitem__ + collate, the
paper preset: resize by data.image_scale_nuscenes 0.5 / image_scale_av2 0.3, normalise, pad, LiDAR
for fusion), batches of --batch-size: on one core in one process (the cost of a worker), in a
DataLoader with 1 and with 2 worker processes (what `cli train` gets, transfer to the main process
included). The files are read once beforehand, so the page cache holds them: decoding is measured,
not the disk. Beside it, the paper's forward rate (16.5 FPS on one RTX 3090) gives the cores that
one GPU needs. A cProfile of the one-core run says where the time goes.

    python -m tools.bench_loader [--data DIR ...] [--frames 48] [--batch-size 4]

Without --data it writes and prepares the synthetic world (`cli synth`, `cli prepare`) in a temporary
folder.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from rich.console import Console
from rich.progress import track
from rich.table import Table

REPO = Path(__file__).resolve().parents[1]


PAPER_FPS = 16.5  # LaneGAP's forward rate on one RTX 3090 (paper, Tab. 1)
FACTOR = {"nuscenes": 4, "av2": 8}  # real size / synthetic size (pipeline/synth/rig.py)
SPLIT = "bench"  # the split of the frames that the copy keeps


def full_size_copy(prepared: Path, out: Path, frames: int, noise: float, quality: int) -> dict:
    """Copy a prepared dataset into `out`, keeping its first `frames` frames (split SPLIT) with full-size
    JPEGs in `out/raw`; returns what was written."""
    manifest = json.loads((prepared / "manifest.json").read_text())
    dataset, raw = manifest["dataset"], Path(manifest["root"])
    factor = FACTOR[dataset]
    shutil.copytree(prepared, out / "prepared")
    shards = sorted((out / "prepared" / "frames").glob("*.parquet"))
    ids = sorted(
        f for shard in shards for f in pq.read_table(shard, columns=["frame_id"])["frame_id"].to_pylist()
    )
    keep = set(ids[:frames])
    rng = np.random.default_rng(0)
    bank = rng.normal(0.0, noise, (2200, 2200, 3)).astype(np.float32)  # noise crops, cheap per image
    rows_by_shard = {}
    for shard in shards:
        table = pq.read_table(shard)
        rows_by_shard[shard] = (table.schema, [r for r in table.to_pylist() if r["frame_id"] in keep])
    cameras = [c for _, rows in rows_by_shard.values() for r in rows for c in r["cameras"]]
    sizes = []
    for camera in track(cameras, description=f"{dataset}: full-size JPEGs"):
        image = cv2.imread(str(raw / camera["image_path"]), cv2.IMREAD_COLOR)
        width, height = camera["width"] * factor, camera["height"] * factor
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_LINEAR).astype(np.float32)
        y, x = rng.integers(0, bank.shape[0] - height), rng.integers(0, bank.shape[1] - width)
        image = np.clip(image + bank[y : y + height, x : x + width], 0, 255).astype(np.uint8)
        ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
        path = out / "raw" / camera["image_path"]
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data.tobytes())
        sizes.append(len(data))
        k = np.array(camera["intrinsics"]).reshape(3, 3)
        k[:2] *= factor  # the rig divided focal lengths and principal point by the factor
        camera.update(width=width, height=height, intrinsics=k.ravel().tolist())
    for shard, (schema, rows) in rows_by_shard.items():
        shard.unlink()
        if rows:
            for row in rows:
                row["split"] = SPLIT
                lidar = out / "raw" / row["lidar_path"]
                lidar.parent.mkdir(parents=True, exist_ok=True)
                lidar.symlink_to(raw / row["lidar_path"])
            pq.write_table(pa.Table.from_pylist(rows, schema=schema), shard)
    manifest["root"] = str(out / "raw")
    (out / "prepared" / "manifest.json").write_text(json.dumps(manifest, indent=2))
    sizes_by_camera = {(c["width"], c["height"]) for c in cameras}
    return {
        "dataset": dataset,
        "data": str(out / "prepared"),
        "frames": len(keep),
        "cameras": len(cameras) // max(1, len(keep)),
        "sizes": sorted(sizes_by_camera, reverse=True),
        "kib": float(np.mean(sizes)) / 1024,
    }


def measure(data: str, modality: str, workers: int, batch_size: int, profile: bool) -> dict:
    """Samples/s of one pass over the split (workers 0: in this process, pinned to one core); the first
    batch (worker start) is not counted."""
    import torch
    from torch.utils.data import DataLoader

    from baselines.data import PreparedDataset, collate
    from baselines.models import resolve_config
    from pipeline.manifest import PreparedData

    config = resolve_config("paper")
    config.encoder.modality = modality
    dataset = PreparedDataset(PreparedData.open(data), SPLIT, config)
    for frame in dataset.frames:  # into the page cache: the disk is not measured
        for camera in frame["cameras"]:
            (dataset.sensor_root / camera["image_path"]).read_bytes()
    if workers == 0:
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
        torch.set_num_threads(1)
    loader = DataLoader(dataset, batch_size=batch_size, num_workers=workers, collate_fn=collate)
    profiler = cProfile.Profile() if profile else None
    batches = iter(loader)
    next(batches)
    start, samples = time.perf_counter(), 0
    if profiler:
        profiler.enable()
    for batch in batches:
        samples += len(batch.frame_ids)
    seconds = time.perf_counter() - start
    result = {"samples": samples, "seconds": seconds, "rate": samples / seconds}
    if profiler:
        profiler.disable()
        stats = pstats.Stats(profiler).stats
        rows = sorted(stats.items(), key=lambda item: -item[1][2])[:10]
        result["profile"] = [(pstats.func_std_string(f), v[1], v[2], v[3]) for f, v in rows]
    return result


def run(data: str, modality: str, workers: int, batch_size: int, profile: bool = False) -> dict:
    """measure() in a fresh process (its own core affinity, threads and memory)."""
    args = json.dumps([data, modality, workers, batch_size, profile])
    result = subprocess.run(
        [sys.executable, "-m", "tools.bench_loader", "--measure", args],
        capture_output=True, text=True, cwd=REPO
    )
    if result.returncode:
        sys.exit(f"{modality} with {workers} workers on {data} failed:\n{result.stderr[-4000:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def prepare_default(tmp: Path) -> list[Path]:
    cli = Path(sys.executable).parent / "cli"
    raw = tmp / "raw"
    steps = [
        [cli, "synth", "--out", raw],
        [cli, "prepare", "--dataset", "nuscenes", "--root", raw / "nuscenes", "--version", "v1.0-trainval",
         "--out", tmp / "nus"],
        [cli, "prepare", "--dataset", "av2", "--root", raw / "av2" / "sensor", "--out", tmp / "av2"],
    ]  # fmt: skip
    for step in steps:
        subprocess.run([str(s) for s in step], check=True, capture_output=True)
    return [tmp / "nus", tmp / "av2"]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--data", type=Path, nargs="*", help="prepared synthetic datasets (default: made here)"
    )
    parser.add_argument("--frames", type=int, default=48)
    parser.add_argument("--batch-size", type=int, default=4, help="per GPU: the paper's 32 over 8 GPUs")
    parser.add_argument("--modalities", default="camera,fusion")
    parser.add_argument("--noise", type=float, default=3.0, help="sensor noise at full size, grey levels")
    parser.add_argument("--quality", type=int, default=90, help="JPEG quality of the full-size images")
    parser.add_argument("--measure", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(measure(*json.loads(args.measure))))
        return
    console = Console()
    cores = len(os.sched_getaffinity(0))
    with tempfile.TemporaryDirectory() as tmp:
        sources = args.data or prepare_default(Path(tmp))
        copies = [
            full_size_copy(source, Path(tmp) / f"full{i}", args.frames, args.noise, args.quality)
            for i, source in enumerate(sources)
        ]
        images = Table(title=f"full-size JPEGs (quality {args.quality}, noise sigma {args.noise})")
        for name in ("dataset", "frames", "cameras", "sizes (w x h)", "KiB / image"):
            images.add_column(name, justify="right")
        for c in copies:
            sizes = ", ".join(f"{w}x{h}" for w, h in c["sizes"])
            images.add_row(c["dataset"], str(c["frames"]), str(c["cameras"]), sizes, f"{c['kib']:.0f}")
        console.print(images)
        rates = Table(title=f"training data path, paper preset, batch {args.batch_size}, {cores} cores here")
        columns = ("dataset", "modality", "1 core s/s", "ms / sample", "1 worker s/s", "2 workers s/s")
        for name in columns + (f"cores for {PAPER_FPS} FPS",):
            rates.add_column(name, justify="right")
        profiles = {}
        for c in copies:
            for modality in args.modalities.split(","):
                console.log(f"{c['dataset']} {modality}: 1 core, 1 worker, 2 workers")
                one = run(c["data"], modality, 0, args.batch_size)
                w1, w2 = (run(c["data"], modality, w, args.batch_size)["rate"] for w in (1, 2))
                rates.add_row(
                    c["dataset"], modality, f"{one['rate']:.1f}", f"{1000 / one['rate']:.0f}",
                    f"{w1:.1f}", f"{w2:.1f}", f"{PAPER_FPS / one['rate']:.1f}",
                )  # fmt: skip
            profiles[c["dataset"]] = run(c["data"], "camera", 0, args.batch_size, profile=True)
        console.print(rates)
        for dataset, result in profiles.items():
            table = Table(
                title=f"{dataset} camera, 1 core: cProfile, top by own time ({result['seconds']:.1f} s)"
            )
            for name in ("function", "calls", "own s", "share", "cumulative s"):
                table.add_column(name, justify="left" if name == "function" else "right")
            for function, calls, own, cumulative in result["profile"]:
                share = f"{100 * own / result['seconds']:.0f} %"
                table.add_row(function[-70:], str(calls), f"{own:.2f}", share, f"{cumulative:.2f}")
            console.print(table)
    console.print(
        f"'1 core': __getitem__ + collate in one process pinned to one core (a worker's cost); 'N workers': "
        f"a DataLoader, batches received by the main process. Cores for {PAPER_FPS} FPS = {PAPER_FPS} / the "
        "1-core rate (a training step is slower than the forward pass, so training needs fewer)."
    )


if __name__ == "__main__":
    main()
