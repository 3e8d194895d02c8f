"""nuScenes tables (`<root>/v1.0-mini/*.json`; v1.0-trainval beyond mini's 8 training scenes): one log and
one scene per synthetic log, one sample per frame.

Every table that nuscenes-devkit 1.2.0 loads is written. Each sample has key-frame sample_data for
LIDAR_TOP (and the cameras when sensors are on), each with its own ego_pose, like the real tables.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path

import numpy as np

from pipeline.synth.av2_writer import yaw_quaternion
from pipeline.synth.ids import token
from pipeline.synth.lidar import Sweep
from pipeline.synth.logs import Cuboid, LogPlan, frame_cuboids, nuscenes_version
from pipeline.synth.rig import NUSCENES_CAMERAS, NUSCENES_LIDAR
from pipeline.synth.world import World

BOSTON = timezone(timedelta(hours=-4))  # nuScenes log names carry the local time


@dataclass(frozen=True)
class Channel:
    """A sensor as calibrated_sensor holds it: pose in the ego frame and, for cameras, the intrinsics."""

    name: str
    modality: str  # "lidar" or "camera"
    translation: list[float]
    rotation: list[float]  # w, x, y, z
    intrinsic: list[list[float]] = field(default_factory=list)
    width: int = 0
    height: int = 0
    offset_us: int = 0  # when its sample_data is taken, relative to the sample (the LiDAR's key time)

    @property
    def extension(self) -> str:
        return ".pcd.bin" if self.modality == "lidar" else ".jpg"


# the real rig: LIDAR_TOP turned -90 deg about z, so its axes are x right, y forward, and tilted on the ego
# (rig.NUSCENES_LIDAR_PITCH_DEG and ROLL_DEG)
LIDAR_TOP = Channel(
    NUSCENES_LIDAR.name, "lidar", list(NUSCENES_LIDAR.translation), NUSCENES_LIDAR.quaternion.tolist()
)


# When each camera's image is taken, relative to the LIDAR_TOP key time: the real rig triggers a camera as
# the 20 Hz sweep crosses its view, clockwise from CAM_FRONT_LEFT, so that the images precede the LiDAR by
# 0.5-43 ms, each with its own ego pose (v1.0-mini scene-0061's first sample: ../shared/data/nuscenes/
# keyframe_scene-0061). At 10 m/s the ego moves 0.4 m in 43 ms: tens of pixels unless a projection goes
# from the LiDAR's ego pose to the camera's through the global frame.
CAMERA_OFFSET_US = {
    "CAM_FRONT_LEFT": -43_100,
    "CAM_FRONT": -35_500,
    "CAM_FRONT_RIGHT": -27_600,
    "CAM_BACK_RIGHT": -20_100,
    "CAM_BACK": -10_400,
    "CAM_BACK_LEFT": -500,
}


def camera_channels() -> list[Channel]:
    return [
        Channel(
            c.name,
            "camera",
            list(c.translation),
            c.quaternion.tolist(),
            c.intrinsics.tolist(),
            c.width,
            c.height,
            CAMERA_OFFSET_US[c.name],
        )
        for c in NUSCENES_CAMERAS
    ]


def channels(sensors: bool) -> list[Channel]:
    """The sample_data channels of a sample: LIDAR_TOP (its pose keys the frame), cameras with sensors."""
    return [LIDAR_TOP] + (camera_channels() if sensors else [])


def write_pcd_bin(path: Path, sweep: Sweep) -> None:
    """float32 x, y, z, intensity, ring per point, in the LIDAR_TOP frame (x right, y forward; tilted on the
    ego as its calibration says, so that the flat ground lies on a plane rising 2.4 % forward)."""
    to_sensor = NUSCENES_LIDAR.rotation.T  # rows: the sensor axes in the ego frame
    xyz = (sweep.xyz - np.array(NUSCENES_LIDAR.translation)) @ to_sensor.T
    points = np.column_stack([xyz, sweep.intensity, sweep.laser]).astype(np.float32)
    path.write_bytes(points.tobytes())


CATEGORIES = [
    (
        "vehicle.car",
        "Vehicle designed primarily for personal use, e.g. sedans, hatch-backs, wagons, vans, SUVs.",
    ),
    (
        "vehicle.truck",
        "Vehicles primarily designed to haul cargo including pick-ups, lorrys, trucks and semi-tractors.",
    ),
    ("human.pedestrian.adult", "Adult subcategory."),
    ("movable_object.trafficcone", "All types of traffic cone."),
]
ATTRIBUTES = [
    ("vehicle.moving", "Vehicle is moving."),
    (
        "vehicle.stopped",
        "Vehicle, with a driver/rider in/on it, is currently stationary but has an intent to move.",
    ),
    (
        "vehicle.parked",
        "Vehicle is stationary (usually for longer duration) with no immediate intent to move.",
    ),
]
VISIBILITY = [("1", "v0-40"), ("2", "v40-60"), ("3", "v60-80"), ("4", "v80-100")]


def logfile_name(plan: LogPlan) -> str:
    local = datetime.fromtimestamp(int(plan.frame_ns[0]) // 10**9, UTC).astimezone(BOSTON)
    return f"n008-{local:%Y-%m-%d-%H-%M-%S}-0400"


def sample_filename(plan: LogPlan, channel: Channel, ns: int) -> str:
    """Where a sensor file lies relative to the dataset root, named like the real ones."""
    return f"samples/{channel.name}/{logfile_name(plan)}__{channel.name}__{ns // 1000}{channel.extension}"


TABLES = (  # every table NuScenes() loads
    "category attribute visibility instance sensor calibrated_sensor ego_pose log scene sample sample_data "
    "sample_annotation map"
).split()


class _Tables:
    def __init__(self, seed: int):
        self.seed = seed
        self.records: dict[str, list[dict]] = {name: [] for name in TABLES}

    def token(self, *parts: object) -> str:
        return token(self.seed, "nuscenes", *parts)

    def add(self, table: str, **fields) -> None:
        self.records[table].append(fields)


def _chain(tokens: list[str], i: int) -> dict[str, str]:
    """The prev / next fields of record i of a time-ordered list."""
    return {"prev": tokens[i - 1] if i else "", "next": tokens[i + 1] if i + 1 < len(tokens) else ""}


def write_tables(
    root: Path,
    worlds: list[World],
    plans: list[LogPlan],
    channels: list[Channel],
    prior_filenames: dict[int, str],
) -> None:
    """The tables of every log; each world is a map location with its own semantic prior
    (prior_filenames: world index -> file, for the worlds that logs drive in)."""
    t = _Tables(worlds[0].seed)
    for name, description in CATEGORIES:
        t.add("category", token=t.token("category", name), name=name, description=description)
    for name, description in ATTRIBUTES:
        t.add("attribute", token=t.token("attribute", name), name=name, description=description)
    for v, level in VISIBILITY:
        between = level[1:].replace("-", " and ")
        t.add(
            "visibility",
            description=f"visibility of whole object is between {between}%",
            token=v,
            level=level,
        )
    for c in channels:
        t.add("sensor", token=t.token("sensor", c.name), channel=c.name, modality=c.modality)
    for plan in plans:
        _add_scene(t, plan, channels, worlds[plan.world].nuscenes_map)
        _add_annotations(t, worlds[plan.world], plan)
    for w, filename in sorted(prior_filenames.items()):
        log_tokens = [t.token("log", plan.index) for plan in plans if plan.world == w]
        t.add(
            "map",
            category="semantic_prior",
            token=t.token("map", w),
            filename=filename,
            log_tokens=log_tokens,
        )
    version = root / nuscenes_version(plans)
    version.mkdir(parents=True, exist_ok=True)
    for name, records in t.records.items():
        (version / f"{name}.json").write_text(json.dumps(records, indent=0))


def _add_scene(t: _Tables, plan: LogPlan, channels: list[Channel], map_name: str) -> None:
    """One log's records: its log and scene, one calibration per log and sensor (as in the real tables),
    and its samples with each channel's ego pose and sample_data."""
    samples = [t.token("sample", plan.index, k) for k in range(len(plan.frame_ns))]
    _add_log_and_scene(t, plan, map_name, samples)
    for c in channels:
        t.add(
            "calibrated_sensor",
            token=t.token("calibrated_sensor", plan.index, c.name),
            sensor_token=t.token("sensor", c.name),
            translation=c.translation,
            rotation=c.rotation,
            camera_intrinsic=c.intrinsic,
        )
    _add_samples(t, plan, channels, samples)


def _add_log_and_scene(t: _Tables, plan: LogPlan, map_name: str, samples: list[str]) -> None:
    i = plan.index
    log_token, logfile = t.token("log", i), logfile_name(plan)
    t.add(
        "log",
        token=log_token,
        logfile=logfile,
        vehicle="n008",
        date_captured=logfile[5:15],
        location=map_name,
    )
    t.add(
        "scene",
        token=t.token("scene", i),
        log_token=log_token,
        nbr_samples=len(samples),
        first_sample_token=samples[0],
        last_sample_token=samples[-1],
        name=plan.scene_name,
        description=f"Synthetic, route {plan.route.name}",
    )


def _add_samples(t: _Tables, plan: LogPlan, channels: list[Channel], samples: list[str]) -> None:
    """One sample per key frame and, per channel, its ego pose and sample_data, chained in time."""
    i = plan.index
    # each sensor's ego poses at its own times (the cameras' precede the sample's: CAMERA_OFFSET_US)
    sensor_ns = {c.name: plan.frame_ns + c.offset_us * 1000 for c in channels}
    ego = {name: plan.ego_at(ns) for name, ns in sensor_ns.items()}
    rotations = {name: yaw_quaternion(poses[:, 2]) for name, poses in ego.items()}
    data = {c.name: [t.token("sample_data", i, c.name, j) for j in range(len(samples))] for c in channels}
    for k, ns in enumerate(plan.frame_ns):
        t.add(
            "sample",
            token=samples[k],
            timestamp=int(ns) // 1000,
            **_chain(samples, k),
            scene_token=t.token("scene", i),
        )
        for c in channels:
            pose = t.token("ego_pose", i, c.name, k)
            us, xy = int(sensor_ns[c.name][k]) // 1000, ego[c.name][k, :2]
            t.add(
                "ego_pose",
                token=pose,
                timestamp=us,
                rotation=rotations[c.name][k].tolist(),
                translation=[float(xy[0]), float(xy[1]), 0.0],
            )
            t.add(
                "sample_data",
                token=data[c.name][k],
                sample_token=samples[k],
                ego_pose_token=pose,
                calibrated_sensor_token=t.token("calibrated_sensor", i, c.name),
                timestamp=us,
                fileformat="pcd" if c.modality == "lidar" else "jpg",
                is_key_frame=True,
                height=c.height,
                width=c.width,
                filename=sample_filename(plan, c, int(sensor_ns[c.name][k])),
                **_chain(data[c.name], k),
            )


def _add_annotations(t: _Tables, world: World, plan: LogPlan) -> None:
    """One instance per car seen in the scene, its annotations chained in time through prev / next."""
    samples = [t.token("sample", plan.index, k) for k in range(len(plan.frame_ns))]
    seen: dict[str, list[tuple[int, Cuboid]]] = {}
    for k, cuboids in enumerate(frame_cuboids(world, plan)):
        for c in cuboids:
            seen.setdefault(c.track, []).append((k, c))
    for track, sightings in seen.items():
        instance = t.token("instance", plan.index, track)
        anns = [t.token("sample_annotation", plan.index, track, k) for k, _ in sightings]
        t.add(
            "instance",
            token=instance,
            category_token=t.token("category", "vehicle.car"),
            nbr_annotations=len(anns),
            first_annotation_token=anns[0],
            last_annotation_token=anns[-1],
        )
        for j, (k, c) in enumerate(sightings):
            attribute = t.token("attribute", "vehicle.moving" if c.moving else "vehicle.parked")
            t.add(
                "sample_annotation",
                token=anns[j],
                sample_token=samples[k],
                instance_token=instance,
                visibility_token="4",
                attribute_tokens=[attribute],
                translation=[c.x, c.y, c.height / 2],
                size=[c.width, c.length, c.height],
                rotation=yaw_quaternion(c.heading).tolist(),
                **_chain(anns, j),
                num_lidar_pts=int(3000 / (1 + c.distance)),
                num_radar_pts=0,
            )
