"""Speed of `cli prepare` on the real AV2 logs in ../shared/data: frames/s per worker, and peak memory.

The whole prepare is timed (map and pose reading, cropping, graph, paths, pieces, rasters, Parquet),
not the Python and devkit imports. The logs are repeated (--repeat) so that runs last long enough to
time and so that peak memory can be compared between a short and a long run.
`--executor ray` compares, in one run, the local executor (1 and 2 workers) with the Ray executor on a
local instance of 2 CPUs; Ray's start (`ray.init`) is timed apart, the start of its worker processes
(imports, numba cache) is in the prepare time. "worker MiB" is the peak resident memory of the process
that prepared the logs, measured in it (for Ray: the largest of its workers); "peak MiB" is the driver's
and its child processes'.
Usage: python -m tools.bench_prepare [--root ../shared/data/av2/sensor] [--repeat 8] [--executor ray]
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


def run_once(root: Path, workers: int, executor: str = "local") -> dict:
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
if {executor!r} == "ray":  # started here so that its start is timed apart; prepare uses it as it is
    import ray
    ray.init("local", num_cpus={workers}, log_to_driver=False)
start = time.perf_counter() - t
t = time.perf_counter()
summary = prepare("av2", Path({str(root)!r}), out, TargetOptions(), workers={workers}, executor={executor!r})
elapsed = time.perf_counter() - t
usage = [resource.getrusage(who).ru_maxrss for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
peak = max(usage)
print(json.dumps({{"frames": summary["frames"], "seconds": elapsed, "start": start, "peak_mib": peak / 1024,
                  "worker_mib": summary["peak_worker_mib"]}}))
"""
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO)
    if result.returncode:
        sys.exit(f"the {executor} run with {workers} workers failed:\n{result.stderr[-4000:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--root", type=Path, default=REPO.parent / "shared" / "data" / "av2" / "sensor")
    parser.add_argument("--repeat", type=int, default=8)
    parser.add_argument("--executor", choices=["local", "ray"], default="local")
    args = parser.parse_args()
    if not args.root.is_dir():
        sys.exit(f"no AV2 logs at {args.root}: pass --root")
    cores = os.cpu_count() or 1
    print(f"prepare on {args.root} (logs repeated x{args.repeat}), {cores} cores")
    header = f"{'executor':>8} {'workers':>8} {'frames':>7} {'start s':>8} {'seconds':>8} {'frames/s':>9}"
    print(f"{header} {'per worker':>11} {'peak MiB':>9} {'worker MiB':>11}")
    if args.executor == "ray":  # 2 CPUs: local with 1 and 2 workers beside Ray with 2
        runs = [("local", 1, 1)] + [(e, args.repeat, w) for e, w in (("local", 1), ("local", 2), ("ray", 2))]
    else:
        runs = [("local", 1, 1)] + [("local", args.repeat, w) for w in range(1, cores + 1)]
    with tempfile.TemporaryDirectory() as tmp:
        run_once(make_root(args.root, 1, Path(tmp) / "warm"), 1)  # numba compile cache
        for executor, repeat, workers in runs:
            root = make_root(args.root, repeat, Path(tmp) / f"{executor}r{repeat}w{workers}")
            r = run_once(root, workers, executor)
            fps = r["frames"] / r["seconds"]
            row = f"{executor:>8} {workers:>8} {r['frames']:>7} {r['start']:>8.2f} {r['seconds']:>8.2f}"
            print(f"{row} {fps:>9.1f} {fps / workers:>11.1f} {r['peak_mib']:>9.0f} {r['worker_mib']:>11.0f}")
            shutil.rmtree(root.parent)


if __name__ == "__main__":
    main()
