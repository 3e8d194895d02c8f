"""Logs: which route each log drives, when, and the ego poses along it.

Timestamps are shared by both formats (AV2 nanoseconds = nuScenes microseconds * 1000): frames (AV2
sweeps and annotations, nuScenes samples) at 10 Hz, ego poses at 50 Hz so that every frame time has
a pose at exactly that time. The ego's reference point (AV2 egovehicle, nuScenes ego_pose) follows
the route's lane centerline at constant speed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.synth.geometry import Path
from pipeline.synth.ids import uuid_like
from pipeline.synth.world import Route, World

FRAME_PERIOD_NS = 100_000_000  # 10 Hz
POSE_PERIOD_NS = 20_000_000  # 50 Hz; five poses per frame period
POSE_MARGIN_NS = FRAME_PERIOD_NS  # poses start before the first frame and end after the last, like real logs
FIRST_LOG_S = 1_533_124_800  # 2018-08-01 12:00 UTC
LEAD_GAP_M = 15.0  # a car drives this far ahead of the ego on its route, so that every frame has a cuboid

# the official nuScenes split names (nuscenes.utils.splits), so that its split machinery applies: the
# v1.0-mini ones while they suffice, else the first of v1.0-trainval's
MINI_TRAIN = [
    "scene-0061",
    "scene-0553",
    "scene-0655",
    "scene-0757",
    "scene-0796",
    "scene-1077",
    "scene-1094",
    "scene-1100",
]
MINI_VAL = ["scene-0103", "scene-0916"]
TRAINVAL_TRAIN = [f"scene-{n:04d}" for n in (*range(1, 3), *range(4, 12), *range(19, 35), *range(41, 47))]
TRAINVAL_VAL = ["scene-0003", "scene-0012"]
VAL_LOGS = 2  # at most; a dataset of 8 logs or more has 2
# Validation logs drive the route of their index, but no further than the default's (routes 8 and 9: a
# junction from an inner lane and the ring), so that more training logs leave validation where it is.
VAL_ROUTES = (8, 9)


def nuscenes_names(train_logs: int) -> tuple[str, list[str], list[str]]:
    """The nuScenes version and the train and val scene names of a dataset of train_logs training logs."""
    if train_logs <= len(MINI_TRAIN):
        return "v1.0-mini", MINI_TRAIN, MINI_VAL
    return "v1.0-trainval", TRAINVAL_TRAIN, TRAINVAL_VAL


def nuscenes_version(plans: list[LogPlan]) -> str:
    return nuscenes_names(sum(plan.split == "train" for plan in plans))[0]


MAX_LOGS = len(TRAINVAL_TRAIN) + VAL_LOGS


@dataclass(frozen=True)
class LogPlan:
    index: int
    split: str  # "train" or "val"
    world: int  # index of the world it drives in
    log_id: str  # AV2 log id
    scene_name: str  # nuScenes scene name
    route: Route
    path: Path  # the route's centerline
    speed: float  # m/s
    start_station: float  # metres along path at pose_ns[0]
    pose_ns: np.ndarray  # (n,) int64
    frame_ns: np.ndarray  # (frames,) int64, a subset of pose_ns

    def ego_at(self, ns: np.ndarray) -> np.ndarray:
        """(n, 3) ego x, y, heading in the world at the given times."""
        return self.path.at(self.station(ns))

    def lead_at(self, ns: np.ndarray) -> np.ndarray:
        """(n, 3) pose of the car driving LEAD_GAP_M ahead (it waits at the route's end if it runs out)."""
        return self.path.at(self.station(ns) + LEAD_GAP_M)

    def station(self, ns: np.ndarray) -> np.ndarray:
        return self.start_station + self.speed * (np.asarray(ns) - self.pose_ns[0]) * 1e-9


def split_of_logs(logs: int) -> list[str]:
    """3/4 train, the rest (1 or 2) val; at most MAX_LOGS (the scene names held here)."""
    val = 0 if logs < 2 else min(VAL_LOGS, max(1, logs // 4))
    if not 1 <= logs <= MAX_LOGS:
        raise ValueError(f"logs must be 1 to {MAX_LOGS} (the nuScenes scene names held here)")
    return ["train"] * (logs - val) + ["val"] * val


def worlds_of_logs(splits: list[str], worlds: int, val_worlds: int) -> list[int]:
    """The world of each log: training logs take turns over the first worlds - val_worlds worlds,
    validation logs over the last val_worlds, so that validation is on geography training never sees."""
    if not 1 <= val_worlds < worlds:
        raise ValueError(f"val_worlds must be at least 1 and fewer than worlds ({worlds}), not {val_worlds}")
    train_worlds = worlds - val_worlds
    counts = {"train": 0, "val": 0}
    out = []
    for split in splits:
        k = counts[split]
        out.append(k % train_worlds if split == "train" else train_worlds + k % val_worlds)
        counts[split] += 1
    return out


def plan_logs(
    worlds: list[World],
    logs: int,
    frames_per_log: int,
    seed: int,
    frame_period_ns: int = FRAME_PERIOD_NS,
    val_worlds: int = 1,
    val_frames_per_log: int | None = None,
    val_frame_period_ns: int | None = None,
) -> list[LogPlan]:
    """frame_period_ns: time between frames, a multiple of the pose period (10 Hz by default; longer
    periods spread the same number of frames over more of each route); the val_ pair is the validation
    logs' own (None: as the training logs'). With one world, training and validation logs share it;
    with more, the last val_worlds hold the validation logs alone."""
    shape = {"train": (frames_per_log, frame_period_ns)}
    shape["val"] = (val_frames_per_log or frames_per_log, val_frame_period_ns or frame_period_ns)
    for frames, period_ns in shape.values():
        if frames < 1:
            raise ValueError("frames_per_log must be at least 1")
        if period_ns <= 0 or period_ns % POSE_PERIOD_NS:
            raise ValueError(f"the frame period must be a positive multiple of {POSE_PERIOD_NS / 1e9} s")
    rng = np.random.default_rng([seed, 2])
    splits = split_of_logs(logs)
    world_of = worlds_of_logs(splits, len(worlds), val_worlds) if len(worlds) > 1 else [0] * logs
    _, train_names, val_names = nuscenes_names(splits.count("train"))
    plans, names = [], {"train": iter(train_names), "val": iter(val_names)}
    for index, (split, w) in enumerate(zip(splits, world_of, strict=True)):
        world = worlds[w]
        frames, period_ns = shape[split]
        # a different kind of route for every log
        route_index = min(index, VAL_ROUTES[index - splits.index("val")]) if split == "val" else index
        route = world.routes[route_index % len(world.routes)]
        path = Path(tuple(p for lane in route.lanes for p in world.lanes[lane].path.pieces))
        duration_s = ((frames - 1) * period_ns + 2 * POSE_MARGIN_NS) * 1e-9
        # slow down rather than run out of road
        speed = max(0.5, min(route.speed, (path.length - LEAD_GAP_M) / duration_s))
        stations = np.linspace(0.0, path.length, int(path.length / 0.25) + 1)
        focus = stations[np.hypot(*(path.at(stations)[:, :2] - np.array(route.focus)).T).argmin()]
        start = float(
            np.clip(
                focus - speed * duration_s / 2, 0.0, max(0.0, path.length - LEAD_GAP_M - speed * duration_s)
            )
        )
        first_ns = (FIRST_LOG_S + 3600 * index) * 10**9 + int(
            rng.integers(0, 10**9)
        ) * 1000  # whole microseconds
        pose_ns = first_ns + POSE_PERIOD_NS * np.arange(
            round(duration_s * 1e9 / POSE_PERIOD_NS) + 1, dtype=np.int64
        )
        frame_ns = first_ns + POSE_MARGIN_NS + period_ns * np.arange(frames, dtype=np.int64)
        plans.append(
            LogPlan(
                index,
                split,
                w,
                uuid_like(seed, "av2 log", index),
                next(names[split]),
                route,
                path,
                speed,
                start,
                pose_ns,
                frame_ns,
            )
        )
    return plans


@dataclass(frozen=True)
class Cuboid:
    """A car near the ego at one frame, in world coordinates."""

    track: str  # uuid of the object, the same in every frame
    moving: bool
    x: float
    y: float
    heading: float
    length: float
    width: float
    height: float
    distance: float  # from the ego


def frame_cuboids(world: World, plan: LogPlan, max_distance: float = 50.0) -> list[list[Cuboid]]:
    """Per frame: the lead car, then the parked cars within max_distance of the ego."""
    frames = []
    for ego, lead in zip(plan.ego_at(plan.frame_ns), plan.lead_at(plan.frame_ns), strict=True):
        objects = [(uuid_like(world.seed, "lead car", plan.index), True, *lead, 4.6, 1.9, 1.6)]
        objects += [
            (
                uuid_like(world.seed, "parked car", world.index, i),
                False,
                c.x,
                c.y,
                c.heading,
                c.length,
                c.width,
                c.height,
            )
            for i, c in enumerate(world.parked_cars)
        ]
        cuboids = [
            Cuboid(*obj, distance=float(np.hypot(obj[2] - ego[0], obj[3] - ego[1]))) for obj in objects
        ]
        frames.append([c for c in cuboids if c.distance <= max_distance])
    return frames
