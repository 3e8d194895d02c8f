"""Train/validation leakage of a prepared dataset (Lilja et al., "Localization Is All You Evaluate", CVPR
2024): how close each non-training frame lies to the nearest training frame of its city, whether its BEV
window shares ground with a training frame's window, and how much of it they cover; and its line."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from pipeline import io
from pipeline.geometry import Range
from pipeline.kernels import kernel

NEAR_M = 5.0  # the paper's radius: a frame this close to a training frame sees much the same map
# The covered share is counted at the points of a Fibonacci lattice in the window (F(20) points, F(19) their
# step). Each coordinate takes each of its COVER_POINTS values once, so an edge parallel to the window's sides
# (a training frame on the same heading) is placed to 1/COVER_POINTS of the window; a regular grid's rows
# would bias the share by up to half a row at every such edge.
COVER_POINTS, COVER_STEP = 6765, 4181
NO_TRAINING_NOTE = "no training frames: leakage not measured"
UNKNOWN = "unknown"  # the name of a frame's split or city when the table holds none
# candidate pairs listed at a time: where a city's logs drive the same streets again and again, a query
# can have thousands of training frames within reach, and all of them at once would not fit in memory
MAX_CANDIDATES = 1_000_000


def is_training(split: str) -> bool:
    """A training split is named "train" or ends with "_train" (nuScenes mini's "mini_train")."""
    return split == "train" or split.endswith("_train")


def reach(window: Range) -> float:
    """The farthest apart two poses can be while their windows still share ground, whatever the headings:
    twice the distance from the pose to the window's farthest corner (the diagonal of a centred window)."""
    return 2.0 * window.radius


def half_length(window: Range) -> float:
    """Half the window's longer side: the radius of `within_range`."""
    return max(window.x_max - window.x_min, window.y_max - window.y_min) / 2


@dataclass
class Places:
    """Where a prepared dataset's frames are: per frame its split, city, world x, y of the BEV origin and
    yaw (the angle of the BEV x axis, to the right of the heading, from the world x axis, radians)."""

    splits: list[str | None]
    cities: list[str | None]
    xy: np.ndarray  # (N, 2) float64
    yaw: np.ndarray  # (N,) float64


def window_centres(xy: np.ndarray, yaw: np.ndarray, window: Range) -> np.ndarray:
    """World x, y of the centre of each frame's window (the pose itself for a window centred on it)."""
    cx, cy = (window.x_min + window.x_max) / 2, (window.y_min + window.y_max) / 2
    c, s = np.cos(yaw), np.sin(yaw)
    return xy + np.stack([c * cx - s * cy, s * cx + c * cy], axis=1)


def window_corners(xy: np.ndarray, yaw: np.ndarray, window: Range) -> np.ndarray:
    """(N, 4, 2) world corners of each frame's window, counter-clockwise."""
    local = np.array([[window.x_min, window.y_min], [window.x_max, window.y_min],
                      [window.x_max, window.y_max], [window.x_min, window.y_max]])  # fmt: skip
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    x, y = local[:, 0], local[:, 1]
    return np.asarray(xy)[:, None, :] + np.stack([c * x - s * y, s * x + c * y], axis=-1)


@kernel
def _overlap_cover(query_c, query_u, train_c, train_u, starts, candidates, hx, hy, samples):
    """Per query window (centre, unit x axis): whether it intersects any of its candidate training windows
    (the separating-axis test of two rectangles of half-sides hx, hy; touching counts), and the share of its
    sample points (window coordinates about its centre) that those intersecting windows cover."""
    n = len(query_c)
    overlapping = np.zeros(n, dtype=np.bool_)
    covered = np.zeros(n)
    hits = np.empty(len(candidates), dtype=np.int64)
    for q in range(n):
        qu_x, qu_y = query_u[q, 0], query_u[q, 1]  # the window's x axis; its y axis is (-qu_y, qu_x)
        n_hits = 0
        for k in range(starts[q], starts[q + 1]):
            t = candidates[k]
            tu_x, tu_y = train_u[t, 0], train_u[t, 1]
            dx, dy = train_c[t, 0] - query_c[q, 0], train_c[t, 1] - query_c[q, 1]
            # |cos| and |sin| of the angle between the windows: each one's half-widths along the other's axes
            cos_a = abs(qu_x * tu_x + qu_y * tu_y)
            sin_a = abs(qu_x * tu_y - qu_y * tu_x)
            apart = (
                abs(dx * qu_x + dy * qu_y) > hx + hx * cos_a + hy * sin_a
                or abs(-dx * qu_y + dy * qu_x) > hy + hx * sin_a + hy * cos_a
                or abs(dx * tu_x + dy * tu_y) > hx + hx * cos_a + hy * sin_a
                or abs(-dx * tu_y + dy * tu_x) > hy + hx * sin_a + hy * cos_a
            )
            if not apart:
                hits[n_hits] = t
                n_hits += 1
        if n_hits == 0:
            continue
        overlapping[q] = True
        count, last = 0, 0
        for s in range(len(samples)):
            px = query_c[q, 0] + samples[s, 0] * qu_x - samples[s, 1] * qu_y
            py = query_c[q, 1] + samples[s, 0] * qu_y + samples[s, 1] * qu_x
            # the window that covered the previous point first: neighbouring points mostly share one
            for step in range(n_hits):
                h = last + step if last + step < n_hits else last + step - n_hits
                t = hits[h]
                dx, dy = px - train_c[t, 0], py - train_c[t, 1]
                if (
                    abs(dx * train_u[t, 0] + dy * train_u[t, 1]) <= hx
                    and abs(dy * train_u[t, 0] - dx * train_u[t, 1]) <= hy
                ):
                    count += 1
                    last = h
                    break
        covered[q] = count / len(samples)
    return overlapping, covered


def cover_samples(window: Range) -> np.ndarray:
    """(COVER_POINTS, 2) points of the Fibonacci lattice spread over the window, about its centre, in bands
    across it so that consecutive points lie near each other (the kernel tries first the training window
    that covered the point before)."""
    i = np.arange(COVER_POINTS)
    u = (i + 0.5) / COVER_POINTS
    v = ((i * COVER_STEP) % COVER_POINTS + 0.5) / COVER_POINTS
    bands = round(math.sqrt(COVER_POINTS))
    band = np.floor(v * bands).astype(np.int64)
    order = np.lexsort((np.where(band % 2 == 0, u, -u), band))  # back and forth
    width, length = window.x_max - window.x_min, window.y_max - window.y_min
    return np.stack([(u[order] - 0.5) * width, (v[order] - 0.5) * length], axis=1)


def window_overlap(
    query_xy: np.ndarray, query_yaw: np.ndarray, train_xy: np.ndarray, train_yaw: np.ndarray, window: Range
) -> tuple[np.ndarray, np.ndarray]:
    """Per query frame: whether its window intersects any training frame's window (exact), and the share
    of its area that they cover (at the points of cover_samples). Candidates: the training frames whose
    window centre lies within `reach` (a KD-tree); the exact test runs on those alone, a chunk of queries
    with at most MAX_CANDIDATES candidates at a time."""
    overlapping, covered = np.zeros(len(query_xy), dtype=bool), np.zeros(len(query_xy))
    if not len(query_xy) or not len(train_xy):
        return overlapping, covered
    query_c = np.ascontiguousarray(window_centres(query_xy, query_yaw, window), dtype=np.float64)
    train_c = np.ascontiguousarray(window_centres(train_xy, train_yaw, window), dtype=np.float64)
    query_u, train_u = unit(query_yaw), unit(train_yaw)
    hx, hy = (window.x_max - window.x_min) / 2, (window.y_max - window.y_min) / 2
    samples = cover_samples(window)
    tree, radius = cKDTree(train_c), np.nextafter(reach(window), np.inf)
    before = np.cumsum(tree.query_ball_point(query_c, radius, return_length=True))
    first = 0
    while first < len(query_c):
        done = before[first - 1] if first else 0
        last = max(first + 1, int(np.searchsorted(before, done + MAX_CANDIDATES, side="right")))
        near = tree.query_ball_point(query_c[first:last], radius)
        starts = np.concatenate([[0], before[first:last] - done]).astype(np.int64)
        candidates = np.fromiter((t for ts in near for t in ts), dtype=np.int64, count=int(starts[-1]))
        overlapping[first:last], covered[first:last] = _overlap_cover(
            query_c[first:last], query_u[first:last], train_c, train_u, starts, candidates, float(hx),
            float(hy), samples,
        )  # fmt: skip
        first = last
    return overlapping, covered


def unit(yaw: np.ndarray) -> np.ndarray:
    """(N, 2) float64 unit vectors at the angles yaw."""
    yaw = np.asarray(yaw, dtype=np.float64)
    return np.ascontiguousarray(np.stack([np.cos(yaw), np.sin(yaw)], axis=1))


def _share(values: np.ndarray) -> float:
    return round(float(np.mean(values)), 4) if len(values) else 0.0


def _shares(distance: np.ndarray, overlapping: np.ndarray, covered: np.ndarray, range_m: float) -> dict:
    """frames, within_5m, within_range and median_m (over the finite distances; None without any), and the
    share of the windows that overlap a training window and the mean share of a window covered."""
    finite = distance[np.isfinite(distance)]
    return {
        "frames": int(len(distance)),
        "within_5m": _share(distance <= NEAR_M),
        "within_range": _share(distance <= range_m),
        "median_m": round(float(np.median(finite)), 2) if len(finite) else None,
        "overlapping": _share(overlapping),
        "covered": _share(covered),
    }


@dataclass
class _Proximity:
    """Per frame, against the training frames of its city: the distance to the nearest one's position
    (inf: none), whether its window intersects one's window, and the share of it theirs cover; and the
    cities whose non-training frames have no training frame to be measured against."""

    distance: np.ndarray
    overlapping: np.ndarray
    covered: np.ndarray
    untrained_cities: set[str]

    def shares(self, members: np.ndarray, range_m: float) -> dict:
        return _shares(self.distance[members], self.overlapping[members], self.covered[members], range_m)


def measure(
    splits: Sequence[str | None], cities: Sequence[str | None], xy: np.ndarray, yaw: np.ndarray, window: Range
) -> dict:
    """For each frame of each non-training split, against the training frames of the same city: the
    distance from its position (xy: (N, 2) world x, y in metres) to the nearest one's, whether its window
    (`window` placed at its position, turned by its yaw: the angle of its BEV x axis in the world, radians)
    intersects one's window, and the share of its window's area that theirs cover. Per split and per city
    of it: frames, the shares within 5 m and within half the window's longer side (`range_m`), the median
    distance, `overlapping` (the share of frames whose window intersects a training window) and `covered`
    (the mean covered share). A city without a training frame gives infinite distances and no overlap
    (median None, "no_training_frames_in_city": true)."""
    names = np.array([UNKNOWN if s is None else str(s) for s in splits], dtype=object)
    places = np.array([UNKNOWN if c is None else str(c) for c in cities], dtype=object)
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    yaw = np.asarray(yaw, dtype=np.float64).reshape(-1)
    _check_frames(names, places, xy, yaw, window)
    range_m = half_length(window)
    head = {"range_m": float(range_m), "window": window.text, "cover_points": COVER_POINTS}
    split_names, split_of = np.unique(names.astype(str), return_inverse=True)
    training = np.array([is_training(s) for s in split_names], dtype=bool)
    train_splits = [str(s) for s, t in zip(split_names, training) if t]
    if not train_splits:
        return {"train_splits": [], **head, "splits": {}, "note": NO_TRAINING_NOTE}
    city_names, city_of = np.unique(places.astype(str), return_inverse=True)
    proximity = _proximity(city_names, city_of, training[split_of], xy, yaw, window)
    result = {"train_splits": train_splits, **head, "splits": {}}
    for s, split in enumerate(split_names):
        if not training[s]:
            entry = _split_entry(split_of == s, city_names, city_of, proximity, range_m)
            result["splits"][str(split)] = entry
    return result


def _check_frames(
    names: np.ndarray, places: np.ndarray, xy: np.ndarray, yaw: np.ndarray, window: Range
) -> None:
    """One split, city, position and heading per frame, all finite, and a window of positive sides."""
    if not len(names) == len(places) == len(xy) == len(yaw):
        raise ValueError(
            f"{len(names)} splits, {len(places)} cities, {len(xy)} positions and {len(yaw)} headings: "
            "not one each"
        )
    if not np.isfinite(xy).all():
        raise ValueError(f"{int((~np.isfinite(xy).all(axis=1)).sum())} frame positions are not finite")
    if not np.isfinite(yaw).all():
        raise ValueError(f"{int((~np.isfinite(yaw)).sum())} frame headings are not finite")
    sides = (window.x_max - window.x_min, window.y_max - window.y_min)
    if not all(math.isfinite(side) and side > 0 for side in sides):
        raise ValueError(f"the window must have positive, finite sides, not {sides[0]} x {sides[1]} m")


def _proximity(
    city_names: np.ndarray,
    city_of: np.ndarray,
    is_train: np.ndarray,
    xy: np.ndarray,
    yaw: np.ndarray,
    window: Range,
) -> _Proximity:
    """Each non-training frame measured against the training frames of its city, a city at a time."""
    proximity = _Proximity(np.full(len(xy), np.inf), np.zeros(len(xy), dtype=bool), np.zeros(len(xy)), set())
    for c, city in enumerate(city_names):
        in_city = city_of == c
        queries, trains = np.flatnonzero(in_city & ~is_train), np.flatnonzero(in_city & is_train)
        if not len(queries):
            continue
        if not len(trains):
            proximity.untrained_cities.add(str(city))
            continue
        proximity.distance[queries] = cKDTree(xy[trains]).query(xy[queries], k=1)[0]
        proximity.overlapping[queries], proximity.covered[queries] = window_overlap(
            xy[queries], yaw[queries], xy[trains], yaw[trains], window
        )
    return proximity


def _split_entry(
    members: np.ndarray, city_names: np.ndarray, city_of: np.ndarray, proximity: _Proximity, range_m: float
) -> dict:
    """One non-training split's shares (members: its frames' mask), then per city of it its own."""
    entry = proximity.shares(members, range_m)
    entry["cities"] = {}
    for c in np.unique(city_of[members]):
        city, here = str(city_names[c]), members & (city_of == c)
        entry["cities"][city] = proximity.shares(here, range_m)
        if city in proximity.untrained_cities:
            entry["cities"][city]["no_training_frames_in_city"] = True
    return entry


def yaw_of(rotation_wxyz: np.ndarray) -> np.ndarray:
    """(N,) the angle from the world x axis of the BEV x axis turned by each (w, x, y, z) quaternion
    (frames.pose_rotation, BEV to world): the yaw of its projection on the ground."""
    w, x, y, z = np.asarray(rotation_wxyz, dtype=np.float64).reshape(-1, 4).T
    return np.arctan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))


def frame_places(data: Path) -> Places:
    """Split, city, world x, y and yaw of every frame of a prepared dataset (its `frames` table)."""
    columns = ["split", "city", "pose_translation", "pose_rotation"]
    table = io.read_table(Path(data), "frames", columns=columns)
    poses = table.column("pose_translation").combine_chunks()
    offsets, values = io.numbers(poses.offsets), io.numbers(poses.values)
    short = np.flatnonzero(np.diff(offsets) < 2)
    if len(short):
        raise ValueError(f"{data}/frames: {len(short)} frames have no x, y in pose_translation")
    xy = np.stack([values[offsets[:-1]], values[offsets[:-1] + 1]], axis=1)
    rotations = table.column("pose_rotation").combine_chunks()
    offsets, values = io.numbers(rotations.offsets), io.numbers(rotations.values)
    if len(wrong := np.flatnonzero(np.diff(offsets) != 4)):
        raise ValueError(f"{data}/frames: {len(wrong)} frames have no (w, x, y, z) in pose_rotation")
    yaw = yaw_of(values[offsets[0] : offsets[-1]])
    return Places(table.column("split").to_pylist(), table.column("city").to_pylist(), xy, yaw)


def read_and_measure(data: Path, window: Range) -> dict:
    """`measure` of a prepared dataset's frames (frame_places) with the window it was cropped to."""
    places = frame_places(data)
    return measure(places.splits, places.cities, places.xy, places.yaw, window)


def _metres(value: float) -> str:
    return f"{value:g}"


def _frames(count: int) -> str:
    return f"{count} frame" if count == 1 else f"{count} frames"


def leakage_line(leakage: dict | None, scheme: str | None) -> str:
    """One line for people: the split scheme, and per non-training split the share of its frames within
    5 m and within the range of a training frame of the same city, the median distance, and the share of
    its windows that overlap a training window and how much of them those cover on average."""
    head = f"split scheme {scheme or UNKNOWN}"
    if leakage is None:
        return f"{head}; leakage not measured (prepared before leakage was recorded)"
    if leakage.get("not_measured"):  # OpenLane-V2 without --cities: no city to measure within
        return f"{head}; leakage not measured: {leakage['not_measured']}"
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
        if "overlapping" in entry:  # measured since issue 59
            window = f"{leakage['window']} m " if leakage.get("window") else ""
            text += (
                f", {100 * entry['overlapping']:.1f} % of the {window}windows overlap a training window, "
                f"{100 * entry['covered']:.1f} % of their area covered on average"
            )
        cities = (entry.get("cities") or {}).values()
        alone = sum(city["frames"] for city in cities if city.get("no_training_frames_in_city"))
        if alone:
            text += f" ({_frames(alone)} in a city without training frames)"
        parts.append(text)
    return f"{head}; leakage: " + "; ".join(parts)
