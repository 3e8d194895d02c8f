"""Sensor data of every frame in both formats: camera images (nuScenes 6-camera rig, AV2 ring cameras) and
LiDAR sweeps (nuScenes HDL-32E, AV2 two VLP-32C merged), all of the same world at the frame's time, but for
the nuScenes cameras, taken 0.5-43 ms before it as on the real rig (nuscenes_writer.CAMERA_OFFSET_US)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

from pipeline.synth import av2_writer, nuscenes_writer
from pipeline.synth.camera_render import (
    VIEW_RANGE_M,
    CameraModel,
    Noise,
    camera_model,
    draw_lighting,
    encode_jpeg,
    render,
)
from pipeline.synth.lidar import Rays, Sweep, cast, lidar_rays
from pipeline.synth.logs import LogPlan, frame_cuboids
from pipeline.synth.rig import AV2_CAMERAS, AV2_LIDARS, NUSCENES_CAMERAS, NUSCENES_LIDAR
from pipeline.synth.texture import ground_texture
from pipeline.synth.world import Box, World

POLE_SIZE = (0.3, 0.3, 5.0)  # length, width, height of a street light, m
# the ground drawn around the trajectory: what cameras see, and LiDAR returns out to ~70 m (the rare
# farther ones, only from the AV2 sensors' lasers near the horizon, read as grass)
GROUND_EXTENT_M = max(VIEW_RANGE_M, NUSCENES_LIDAR.max_range) + 5.0


@dataclass(frozen=True)
class Rig:
    """The per-pixel ground points of every camera and the LiDAR rays: the same for every frame."""

    nuscenes_cameras: list[CameraModel]
    av2_cameras: list[CameraModel]
    nuscenes_lidar: Rays
    av2_lidars: list[Rays]


@cache
def sensor_rig() -> Rig:
    return Rig(
        [camera_model(s) for s in NUSCENES_CAMERAS],
        [camera_model(s) for s in AV2_CAMERAS],
        lidar_rays(NUSCENES_LIDAR),
        [lidar_rays(s) for s in AV2_LIDARS],
    )


def write_sensors(world: World, plan: LogPlan, av2_log_dir: Path, nuscenes_root: Path) -> None:
    rng = np.random.default_rng([world.seed, 3, plan.index])
    lighting = draw_lighting(rng)  # one light and camera response for the whole log
    noise = Noise(rng, lighting.noise_sigma)
    rig = sensor_rig()
    poses = plan.ego_at(plan.frame_ns)
    texture = ground_texture(world, poses[:, :2], GROUND_EXTENT_M, rng)
    av2_writer.write_calibration(av2_log_dir)
    for model in rig.av2_cameras:
        (av2_log_dir / "sensors" / "cameras" / model.spec.name).mkdir(parents=True, exist_ok=True)
    (av2_log_dir / "sensors" / "lidar").mkdir(parents=True, exist_ok=True)
    for channel in nuscenes_writer.channels(sensors=True):
        (nuscenes_root / "samples" / channel.name).mkdir(parents=True, exist_ok=True)
    poles = [Box(x, y, 0.0, *POLE_SIZE) for x, y in world.poles]
    camera_channels = nuscenes_writer.camera_channels()
    for ns, pose, cuboids in zip(plan.frame_ns, poses, frame_cuboids(world, plan), strict=True):
        ns = int(ns)
        for model, channel in zip(rig.nuscenes_cameras, camera_channels, strict=True):
            taken = ns + channel.offset_us * 1000  # before the LiDAR's key time, from the ego pose then
            path = nuscenes_root / nuscenes_writer.sample_filename(plan, channel, taken)
            path.write_bytes(
                encode_jpeg(render(model, texture, plan.ego_at(np.array([taken]))[0], lighting, noise))
            )
        for model in rig.av2_cameras:
            path = av2_log_dir / "sensors" / "cameras" / model.spec.name / f"{ns}.jpg"
            path.write_bytes(encode_jpeg(render(model, texture, pose, lighting, noise)))
        obstacles = [Box(c.x, c.y, c.heading, c.length, c.width, c.height) for c in cuboids] + poles
        obstacles += world.buildings
        sweep = Sweep.merge([cast(rays, texture, pose, obstacles, rng) for rays in rig.av2_lidars])
        av2_writer.write_sweep(av2_log_dir / "sensors" / "lidar" / f"{ns}.feather", sweep)
        sweep = cast(rig.nuscenes_lidar, texture, pose, obstacles, rng)
        lidar_path = nuscenes_root / nuscenes_writer.sample_filename(plan, nuscenes_writer.LIDAR_TOP, ns)
        nuscenes_writer.write_pcd_bin(lidar_path, sweep)
