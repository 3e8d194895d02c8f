"""Speed of `cli prepare` on the real AV2 logs in ../shared/data: frames/s per worker, and peak memory.

The whole prepare is timed (map and pose reading, cropping, graph, paths, pieces, rasters, Parquet),
not the Python and devkit imports. The logs are repeated (--repeat) so that runs last long enough to
time and so that peak memory can be compared between a short and a long run.
Usage: python benchmark/bench_prepare.py [--root ../shared/data/av2/sensor] [--repeat 8]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def make_root(source: Path, repeat: int, folder: Path) -> Path:
    """A dataset root whose split folders hold each real log `repeat` times (symlinked copies)."""
    root = folder / "sensor"
    for log_dir in sorted(source.glob("*/*")):
        for k in range(repeat):
            target = root / log_dir.parent.name / f"{log_dir.name}-{k:03d}"
            target.parent.mkdir(parents=True, exist_ok=True)
            target.symlink_to(log_dir.resolve(), target_is_directory=True)
    return root


def run_once(root: Path, workers: int) -> dict:
    """One prepare in a fresh process (so peak RSS is this run's), imports excluded from the time."""
    code = f"""
import json, resource, sys, tempfile, time
from pathlib import Path
import av2.map.map_api, av2.utils.io  # imports are not part of the measured work
from pipeline.prepare import prepare
from pipeline.targets import TargetOptions
from pipeline.lane_graph import merge_labels  # warm the numba cache
out = Path(tempfile.mkdtemp())
t = time.perf_counter()
summary = prepare("av2", Path({str(root)!r}), out, TargetOptions(), workers={workers})
elapsed = time.perf_counter() - t
usage = [resource.getrusage(who).ru_maxrss for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
peak = max(usage)
print(json.dumps({{"frames": summary["frames"], "seconds": elapsed, "peak_mib": peak / 1024}}))
"""
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True
    )
    return json.loads(result.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--root", type=Path, default=REPO.parent / "shared" / "data" / "av2" / "sensor")
    parser.add_argument("--repeat", type=int, default=8)
    args = parser.parse_args()
    if not args.root.is_dir():
        sys.exit(f"no AV2 logs at {args.root}: pass --root")
    cores = os.cpu_count() or 1
    print(f"prepare on {args.root} (logs repeated x{args.repeat}), {cores} cores")
    print(f"{'workers':>8} {'frames':>7} {'seconds':>8} {'frames/s':>9} {'per worker':>11} {'peak MiB':>9}")
    with tempfile.TemporaryDirectory() as tmp:
        run_once(make_root(args.root, 1, Path(tmp) / "warm"), 1)  # numba compile cache
        for repeat, workers in [(1, 1), (args.repeat, 1)] + [(args.repeat, w) for w in range(2, cores + 1)]:
            root = make_root(args.root, repeat, Path(tmp) / f"r{repeat}w{workers}")
            r = run_once(root, workers)
            fps = r["frames"] / r["seconds"]
            per_worker = fps / workers
            row = f"{workers:>8} {r['frames']:>7} {r['seconds']:>8.2f} {fps:>9.1f} {per_worker:>11.1f}"
            print(f"{row} {r['peak_mib']:>9.0f}")
            shutil.rmtree(root.parent)


if __name__ == "__main__":
    main()
