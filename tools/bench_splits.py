"""What honest splits cost (`make bench`): the leakage measure and the split picture against the whole
`cli prepare` on the real AV2 logs in ../shared/data, and the measure, the geographic scheme and the
picture on 34,149 frames (the size of nuScenes trainval) in four cities.

Usage: python -m tools.bench_splits [--root ../shared/data/av2/sensor] [--repeat 8]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from tools.bench_prepare import make_root

REPO = Path(__file__).resolve().parents[1]
NUSCENES_FRAMES = 34_149


def timed(record: dict, name: str, function):
    def run(*args, **kwargs):
        start = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            record[name] = record.get(name, 0.0) + time.perf_counter() - start

    return run


def real_prepare(source: Path, repeat: int) -> dict:
    """Seconds of one prepare of the real logs (repeated), of its leakage measure and of its picture."""
    import pipeline.prepare as prepare_module
    from pipeline.lane_graph import merge_labels  # noqa: F401  (the numba cache warmed, not timed)
    from pipeline.targets import TargetOptions

    record: dict = {}
    prepare_module.read_and_measure = timed(record, "leakage", prepare_module.read_and_measure)
    prepare_module.draw_dataset_splits = timed(record, "picture", prepare_module.draw_dataset_splits)
    with tempfile.TemporaryDirectory() as folder:
        root = make_root(source, repeat, Path(folder))
        prepare_module.prepare("av2", root, Path(folder) / "warm", TargetOptions(), split="val")  # imports
        record.clear()
        start = time.perf_counter()
        summary = prepare_module.prepare("av2", root, Path(folder) / "out", TargetOptions())
        record["prepare"] = time.perf_counter() - start
    return {**record, "frames": summary["frames"]}


def roads(rng: np.random.Generator, frames: int, cities: int) -> tuple[list[str], np.ndarray]:
    """Frames 1 m apart along random curving roads of 400 m, the roads dealt to `cities` in turn."""
    xy, names = [], []
    while len(xy) < frames:
        start, heading = rng.uniform(0, 3000, 2), rng.uniform(0, 2 * np.pi)
        turns = np.cumsum(rng.normal(0, 0.01, 400)) + heading
        road = start + np.cumsum(np.stack([np.cos(turns), np.sin(turns)], 1), 0)
        names += [f"city{len(xy) // 400 % cities}"] * len(road)
        xy += list(road)
    return names[:frames], np.array(xy[:frames])


def nuscenes_size() -> dict:
    """Seconds of the measure, the geographic scheme and the picture on 34,149 frames in four cities."""
    from pipeline.splits.geographic import draw_split_map, geographic
    from pipeline.splits.leakage import measure

    rng = np.random.default_rng(0)
    cities, xy = roads(rng, NUSCENES_FRAMES, 4)
    original = rng.choice(["train", "val", "test"], len(xy), p=[0.7, 0.15, 0.15]).tolist()
    record: dict = {}
    timed(record, "leakage", measure)(original, cities, xy, 30.0)
    geo = timed(record, "geographic", geographic)(cities, xy, original)
    with tempfile.TemporaryDirectory() as folder:
        picture = timed(record, "picture", draw_split_map)
        picture(cities, xy, geo.split, Path(folder) / "splits.png", cells=geo.cells, cell_m=100.0)
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, default=REPO.parent / "shared" / "data" / "av2" / "sensor")
    parser.add_argument("--repeat", type=int, default=8, help="each real log this many times")
    args = parser.parse_args()
    table = Table("data", "frames", "prepare s", "leakage s", "share", "picture s", "share", "geographic s")
    if args.root.is_dir():
        real = real_prepare(args.root, args.repeat)
        share = {name: f"{100 * real[name] / real['prepare']:.1f} %" for name in ("leakage", "picture")}
        table.add_row(f"real AV2 x {args.repeat}", str(real["frames"]), f"{real['prepare']:.2f}",
                      f"{real['leakage']:.3f}", share["leakage"], f"{real['picture']:.2f}", share["picture"],
                      "-")  # fmt: skip
    else:
        Console(stderr=True).print(f"{args.root}: not found, the real AV2 row is left out")
    big = nuscenes_size()
    table.add_row("roads, 4 cities", f"{NUSCENES_FRAMES:,}", "-", f"{big['leakage']:.3f}", "-",
                  f"{big['picture']:.2f}", "-", f"{big['geographic']:.2f}")  # fmt: skip
    Console().print(table)


if __name__ == "__main__":
    main()
