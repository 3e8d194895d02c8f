"""Train/validation leakage of a prepared dataset: how close each non-training frame lies to the nearest
training frame of its city (Lilja et al., "Localization Is All You Evaluate", CVPR 2024), and its line."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from pipeline import io

NEAR_M = 5.0  # the paper's radius: a frame this close to a training frame sees much the same map
NO_TRAINING_NOTE = "no training frames: leakage not measured"
UNKNOWN = "unknown"  # the name of a frame's split or city when the table holds none


def is_training(split: str) -> bool:
    """A training split is named "train" or ends with "_train" (nuScenes mini's "mini_train")."""
    return split == "train" or split.endswith("_train")


def _shares(distances: np.ndarray, range_m: float) -> dict:
    """frames, within_5m, within_range and median_m (over the finite distances; None without any)."""
    finite = distances[np.isfinite(distances)]
    return {
        "frames": int(len(distances)),
        "within_5m": round(float(np.mean(distances <= NEAR_M)), 4) if len(distances) else 0.0,
        "within_range": round(float(np.mean(distances <= range_m)), 4) if len(distances) else 0.0,
        "median_m": round(float(np.median(finite)), 2) if len(finite) else None,
    }


def measure(splits: Sequence[str], cities: Sequence[str], xy: np.ndarray, range_m: float) -> dict:
    """For each frame of each non-training split, the distance from its position (xy: (N, 2) world x, y
    in metres) to the nearest training frame's in the same city; per split and per city of it: frames,
    the shares within 5 m and within range_m, and the median distance. A city without a training frame
    gives infinite distances (shares 0, median None, "no_training_frames_in_city": true)."""
    names = np.array([UNKNOWN if s is None else str(s) for s in splits], dtype=object)
    places = np.array([UNKNOWN if c is None else str(c) for c in cities], dtype=object)
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if not len(names) == len(places) == len(xy):
        raise ValueError(f"{len(names)} splits, {len(places)} cities and {len(xy)} positions: not one each")
    if not (math.isfinite(range_m) and range_m > 0):
        raise ValueError(f"range_m must be a positive number of metres, not {range_m}")
    if not np.isfinite(xy).all():
        raise ValueError(f"{int((~np.isfinite(xy).all(axis=1)).sum())} frame positions are not finite")
    split_names, split_of = np.unique(names.astype(str), return_inverse=True)
    training = np.array([is_training(s) for s in split_names], dtype=bool)
    train_splits = [str(s) for s, t in zip(split_names, training) if t]
    if not train_splits:
        return {"train_splits": [], "range_m": float(range_m), "splits": {}, "note": NO_TRAINING_NOTE}
    is_train = training[split_of]
    city_names, city_of = np.unique(places.astype(str), return_inverse=True)
    distance = np.full(len(xy), np.inf)
    untrained_cities = set()
    for c, city in enumerate(city_names):
        in_city = city_of == c
        queries = in_city & ~is_train
        if not queries.any():
            continue
        train_xy = xy[in_city & is_train]
        if not len(train_xy):
            untrained_cities.add(str(city))
            continue
        distance[queries] = cKDTree(train_xy).query(xy[queries], k=1)[0]
    result = {"train_splits": train_splits, "range_m": float(range_m), "splits": {}}
    for s, split in enumerate(split_names):
        if training[s]:
            continue
        members = split_of == s
        entry = _shares(distance[members], range_m)
        entry["cities"] = {}
        for c in np.unique(city_of[members]):
            city = str(city_names[c])
            entry["cities"][city] = _shares(distance[members & (city_of == c)], range_m)
            if city in untrained_cities:
                entry["cities"][city]["no_training_frames_in_city"] = True
        result["splits"][str(split)] = entry
    return result


def frame_places(data: Path) -> tuple[list[str], list[str], np.ndarray]:
    """(split, city, world x y) of every frame of a prepared dataset (its `frames` table)."""
    table = io.read_table(Path(data), "frames", columns=["split", "city", "pose_translation"])
    poses = table.column("pose_translation").combine_chunks()
    offsets, values = io.numbers(poses.offsets), io.numbers(poses.values)
    short = np.flatnonzero(np.diff(offsets) < 2)
    if len(short):
        raise ValueError(f"{data}/frames: {len(short)} frames have no x, y in pose_translation")
    xy = np.stack([values[offsets[:-1]], values[offsets[:-1] + 1]], axis=1)
    return table.column("split").to_pylist(), table.column("city").to_pylist(), xy


def read_and_measure(data: Path, range_m: float) -> dict:
    """`measure` of a prepared dataset's frames (frame_places)."""
    splits, cities, xy = frame_places(data)
    return measure(splits, cities, xy, range_m)


def _metres(value: float) -> str:
    return f"{value:g}"


def _frames(count: int) -> str:
    return f"{count} frame" if count == 1 else f"{count} frames"


def leakage_line(leakage: dict | None, scheme: str | None) -> str:
    """One line for people: the split scheme, and per non-training split the share of its frames within
    5 m and within the range of a training frame of the same city, and the median distance."""
    head = f"split scheme {scheme or UNKNOWN}"
    if leakage is None:
        return f"{head}; leakage not measured (prepared before leakage was recorded)"
    if leakage.get("note") or not leakage.get("train_splits"):
        return f"{head}; leakage: not measured (no training frames)"
    splits = leakage.get("splits") or {}
    if not splits:
        return f"{head}; leakage: no split but the training splits ({', '.join(leakage['train_splits'])})"
    range_m = _metres(float(leakage.get("range_m", 0.0)))
    parts = []
    for name, entry in splits.items():
        near, within = 100 * entry["within_5m"], 100 * entry["within_range"]
        text = (
            f"{name} {near:.1f} % of {_frames(entry['frames'])} within {_metres(NEAR_M)} m of a training "
            f"frame (the same city), {within:.1f} % within {range_m} m, "
        )
        text += "median –" if entry.get("median_m") is None else f"median {entry['median_m']:.1f} m"
        cities = (entry.get("cities") or {}).values()
        alone = sum(city["frames"] for city in cities if city.get("no_training_frames_in_city"))
        if alone:
            text += f" ({_frames(alone)} in a city without training frames)"
        parts.append(text)
    return f"{head}; leakage: " + "; ".join(parts)
