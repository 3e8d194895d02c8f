"""What honest splits cost (`make bench`): the leakage measure (distances, and each window's overlap with
the training windows) and the split picture against the whole `cli prepare` on the real AV2 logs in
../shared/data, once with the dataset's own splits and once with split files that put every second frame
of the training log in val (each val window then overlaps hundreds of training windows); and the measure,
the geographic scheme and the picture on 34,149 frames (the size of nuScenes trainval) in four cities,
against the time `cli prepare` would take for them at the real rows' frames per second.

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


def warm_kernels() -> None:
    """The numba kernels compiled (or loaded from numba's cache) before any time is taken."""
    from pipeline.geometry import Range
    from pipeline.lane_graph import merge_labels  # noqa: F401
    from pipeline.splits.leakage import measure

    measure(["train", "val"], ["a", "a"], np.zeros((2, 2)), np.zeros(2), Range())


def interleaved_split_files(root: Path, folder: Path) -> dict[str, Path]:
    """Split files over a make_root root: the frames of every copy of each training log alternately in
    train and val (frame ids, `av2/<log>/<timestamp_ns>`), every other log whole in val."""
    from pipeline.adapters.av2 import frame_timestamps

    lines: dict[str, list[str]] = {"train": [], "val": []}
    for log_dir in sorted(root.glob("*/*")):
        if log_dir.parent.name != "train":
            lines["val"].append(log_dir.name)
            continue
        for i, t in enumerate(frame_timestamps(log_dir).tolist()):
            lines["train" if i % 2 == 0 else "val"].append(f"av2/{log_dir.name}/{t}")
    files = {}
    for split, names in lines.items():
        files[split] = folder / f"{split}.txt"
        files[split].write_text("\n".join(names) + "\n")
    return files


def real_prepare(source: Path, repeat: int, interleaved: bool) -> dict:
    """Seconds of one prepare of the real logs (repeated), of its leakage measure and of its picture."""
    import pipeline.prepare as prepare_module
    from pipeline.targets import TargetOptions

    warm_kernels()
    record: dict = {}
    prepare_module.read_and_measure = timed(record, "leakage", prepare_module.read_and_measure)
    prepare_module.draw_dataset_splits = timed(record, "picture", prepare_module.draw_dataset_splits)
    with tempfile.TemporaryDirectory() as folder:
        root = make_root(source, repeat, Path(folder))
        files = interleaved_split_files(root, Path(folder)) if interleaved else None
        prepare_module.prepare("av2", root, Path(folder) / "warm", TargetOptions(), split="val")  # imports
        record.clear()
        start = time.perf_counter()
        out = Path(folder) / "out"
        summary = prepare_module.prepare("av2", root, out, TargetOptions(), split_files=files)
        record["prepare"] = time.perf_counter() - start
    val = summary["leakage"]["splits"]["val"]
    return {**record, "frames": summary["frames"], "overlapping": val["overlapping"],
            "covered": val["covered"]}  # fmt: skip


def roads(rng: np.random.Generator, frames: int, cities: int) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Frames 1 m apart along random curving roads of 400 m, the roads dealt to `cities` in turn: city
    names, positions and yaws (the BEV x axis: the road's heading less 90 deg)."""
    xy, yaw, names = [], [], []
    while len(xy) < frames:
        start, heading = rng.uniform(0, 3000, 2), rng.uniform(0, 2 * np.pi)
        turns = np.cumsum(rng.normal(0, 0.01, 400)) + heading
        road = start + np.cumsum(np.stack([np.cos(turns), np.sin(turns)], 1), 0)
        names += [f"city{len(xy) // 400 % cities}"] * len(road)
        xy += list(road)
        yaw += list(turns - np.pi / 2)
    return names[:frames], np.array(xy[:frames]), np.array(yaw[:frames])


def nuscenes_size() -> dict:
    """Seconds of the measure of a random 70/15/15 split (every val window on training ground) and of the
    geographic scheme's split, of the scheme and of the picture, on 34,149 frames in four cities."""
    from pipeline.geometry import Range
    from pipeline.splits.geographic import draw_split_map, geographic
    from pipeline.splits.leakage import measure

    warm_kernels()
    rng = np.random.default_rng(0)
    cities, xy, yaw = roads(rng, NUSCENES_FRAMES, 4)
    original = rng.choice(["train", "val", "test"], len(xy), p=[0.7, 0.15, 0.15]).tolist()
    record: dict = {}
    random = timed(record, "leakage", measure)(original, cities, xy, yaw, Range())
    geo = timed(record, "geographic", geographic)(cities, xy, original)
    kept = np.flatnonzero([s is not None for s in geo.split])  # a prepared dataset holds these alone
    names = [cities[i] for i in kept]
    by_place = timed(record, "leakage_geographic", measure)([geo.split[i] for i in kept], names, xy[kept],
                                                            yaw[kept], Range())  # fmt: skip
    # no buffer: val and test windows along the borders partly on training ground, the measure's slowest
    bordering = geographic(cities, xy, original, buffer_m=0.0).split
    unbuffered = timed(record, "leakage_unbuffered", measure)(bordering, cities, xy, yaw, Range())
    with tempfile.TemporaryDirectory() as folder:
        picture = timed(record, "picture", draw_split_map)
        picture(cities, xy, geo.split, Path(folder) / "splits.png", cells=geo.cells, cell_m=100.0)
    record["overlapping"] = random["splits"]["val"]["overlapping"]
    record["covered"] = random["splits"]["val"]["covered"]
    record["geo_overlapping"] = max(by_place["splits"][s]["overlapping"] for s in ("val", "test"))
    record["left_out"] = sum(geo.left_out.values())
    record["unbuffered_overlapping"] = unbuffered["splits"]["val"]["overlapping"]
    record["unbuffered_covered"] = unbuffered["splits"]["val"]["covered"]
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, default=REPO.parent / "shared" / "data" / "av2" / "sensor")
    parser.add_argument("--repeat", type=int, default=8, help="each real log this many times")
    args = parser.parse_args()
    table = Table("data", "frames", "prepare s", "leakage s", "share", "val windows overlapping, covered",
                  "picture s", "share", "geographic s")  # fmt: skip
    seconds_per_frame = []
    if args.root.is_dir():
        for interleaved in (False, True):
            real = real_prepare(args.root, args.repeat, interleaved)
            seconds_per_frame.append(real["prepare"] / real["frames"])
            share = {name: f"{100 * real[name] / real['prepare']:.1f} %" for name in ("leakage", "picture")}
            name = "every 2nd training frame in val" if interleaved else "own splits"
            table.add_row(f"real AV2 x {args.repeat}, {name}", str(real["frames"]), f"{real['prepare']:.2f}",
                          f"{real['leakage']:.3f}", share["leakage"],
                          f"{100 * real['overlapping']:.1f} %, {100 * real['covered']:.1f} %",
                          f"{real['picture']:.2f}", share["picture"], "-")  # fmt: skip
    else:
        Console(stderr=True).print(f"{args.root}: not found, the real AV2 rows are left out")
    big = nuscenes_size()
    # cli prepare of as many frames, at the real rows' mean speed (the roads have no maps to prepare)
    estimate = NUSCENES_FRAMES * float(np.mean(seconds_per_frame)) if seconds_per_frame else None
    prepare_s = f"{estimate:.0f} (at the real rows' speed)" if estimate else "-"
    random = f"{100 * big['overlapping']:.1f} %, {100 * big['covered']:.1f} %"
    by_place = f"{100 * big['geo_overlapping']:.1f} %, {big['left_out']:,} frames left out"
    bordering = f"{100 * big['unbuffered_overlapping']:.1f} %, {100 * big['unbuffered_covered']:.1f} %"
    for name, key, overlap in (("random 70/15/15", "leakage", random),
                               ("geographic (default)", "leakage_geographic", by_place),
                               ("geographic, --geo-buffer 0", "leakage_unbuffered", bordering)):  # fmt: skip
        share = f"{100 * big[key] / estimate:.1f} %" if estimate else "-"
        table.add_row(f"roads, 4 cities, {name}", f"{NUSCENES_FRAMES:,}", prepare_s, f"{big[key]:.3f}", share,
                      overlap, f"{big['picture']:.2f}" if key == "leakage" else "-", "-",
                      f"{big['geographic']:.2f}" if key == "leakage" else "-")  # fmt: skip
    Console(width=200).print(table)


if __name__ == "__main__":
    main()
