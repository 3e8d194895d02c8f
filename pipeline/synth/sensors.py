"""Sensor data of every frame in both formats: camera images (nuScenes 6-camera rig, AV2 ring cameras) and
the roof LiDAR's sweep, all of the same world at the same time."""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np

from pipeline.synth import av2_writer, nuscenes_writer
from pipeline.synth.camera_render import VIEW_RANGE_M, CameraModel, Noise, camera_model, encode_jpeg, render
from pipeline.synth.lidar import Rays, cast, lidar_rays
from pipeline.synth.logs import LogPlan, frame_cuboids
from pipeline.synth.rig import AV2_CAMERAS, NUSCENES_CAMERAS, ROOF_LIDAR
from pipeline.synth.texture import ground_texture
from pipeline.synth.world import Box, World

POLE_SIZE = (0.3, 0.3, 5.0)  # length, width, height of a street light, m


@cache
def _rig() -> tuple[list[CameraModel], list[CameraModel], Rays]:
    """The per-pixel ground points of every camera and the LiDAR rays: the same for every frame."""
    return (
        [camera_model(s) for s in NUSCENES_CAMERAS],
        [camera_model(s) for s in AV2_CAMERAS],
        lidar_rays(ROOF_LIDAR),
    )


def write_sensors(world: World, plan: LogPlan, av2_log_dir: Path, nuscenes_root: Path) -> None:
    rng = np.random.default_rng([world.seed, 3, plan.index])
    noise = Noise(rng)
    nuscenes_cameras, av2_cameras, rays = _rig()
    poses = plan.ego_at(plan.frame_ns)
    texture = ground_texture(world, poses[:, :2], max(VIEW_RANGE_M, ROOF_LIDAR.max_range) + 5.0, rng)
    av2_writer.write_calibration(av2_log_dir)
    for model in av2_cameras:
        (av2_log_dir / "sensors" / "cameras" / model.spec.name).mkdir(parents=True, exist_ok=True)
    (av2_log_dir / "sensors" / "lidar").mkdir(parents=True, exist_ok=True)
    for channel in nuscenes_writer.channels(sensors=True):
        (nuscenes_root / "samples" / channel.name).mkdir(parents=True, exist_ok=True)
    poles = [Box(x, y, 0.0, *POLE_SIZE) for x, y in world.poles]
    camera_channels = nuscenes_writer.camera_channels()
    for ns, pose, cuboids in zip(plan.frame_ns, poses, frame_cuboids(world, plan), strict=True):
        ns = int(ns)
        for model, channel in zip(nuscenes_cameras, camera_channels, strict=True):
            path = nuscenes_root / nuscenes_writer.sample_filename(plan, channel, ns)
            path.write_bytes(encode_jpeg(render(model, texture, pose, noise)))
        for model in av2_cameras:
            path = av2_log_dir / "sensors" / "cameras" / model.spec.name / f"{ns}.jpg"
            path.write_bytes(encode_jpeg(render(model, texture, pose, noise)))
        cars = [Box(c.x, c.y, c.heading, c.length, c.width, c.height) for c in cuboids]
        near = [p for p in poles if np.hypot(p.x - pose[0], p.y - pose[1]) < ROOF_LIDAR.max_range]
        sweep = cast(rays, ROOF_LIDAR.max_range, texture, pose, cars + near, rng)
        av2_writer.write_sweep(av2_log_dir / "sensors" / "lidar" / f"{ns}.feather", sweep)
        lidar_path = nuscenes_root / nuscenes_writer.sample_filename(plan, nuscenes_writer.LIDAR_TOP, ns)
        nuscenes_writer.write_pcd_bin(lidar_path, sweep)
