"""LiDAR sweeps by ray casting: a spinning multi-laser sensor over the flat ground, cars and poles.

Ground returns take their intensity from the ground material, so lane paint shines (retroreflective
beads) against dark asphalt, as in real sweeps. Points are in the ego frame (x forward, y left, z up)
at the sweep time, motion compensated as AV2 and nuScenes publish them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.synth.rig import LidarSpec
from pipeline.synth.texture import ASPHALT, GRASS, WHITE, YELLOW, GroundTexture
from pipeline.synth.world import Box

SWEEP_NS = 100_000_000  # one revolution per frame, 10 Hz
INTENSITY_MEAN = np.zeros(4)
INTENSITY_MEAN[[GRASS, ASPHALT, WHITE, YELLOW]] = 25.0, 9.0, 110.0, 80.0  # by ground material
OBJECT_INTENSITY = 40.0
RANGE_NOISE_M = 0.02
SPURIOUS_FRACTION = 0.005  # returns from dust, rain, multipath: at a random range along their ray


@dataclass(frozen=True)
class Sweep:
    xyz: np.ndarray  # (n, 3) float64, ego frame
    intensity: np.ndarray  # (n,) uint8
    laser: np.ndarray  # (n,) uint8, 0 is the lowest beam
    offset_ns: np.ndarray  # (n,) uint32, firing time after the sweep timestamp


@dataclass(frozen=True)
class Rays:
    origin: np.ndarray  # (3,) ego frame
    directions: np.ndarray  # (n, 3) unit vectors, ego frame
    laser: np.ndarray
    offset_ns: np.ndarray


def lidar_rays(spec: LidarSpec) -> Rays:
    azimuth = np.arange(spec.azimuth_steps) * (2 * np.pi / spec.azimuth_steps)
    elevation = np.radians(spec.elevations_deg)
    az, el = np.meshgrid(azimuth, elevation, indexing="ij")  # firing order: azimuth, then laser
    directions = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)
    laser = np.broadcast_to(np.arange(len(elevation)), az.shape).reshape(-1).astype(np.uint8)
    offset = (az.reshape(-1) / (2 * np.pi) * SWEEP_NS).astype(np.uint32)
    return Rays(np.array(spec.translation), directions.reshape(-1, 3), laser, offset)


def cast(rays: Rays, max_range: float, texture: GroundTexture, pose: np.ndarray, obstacles: list[Box],
         rng: np.random.Generator) -> Sweep:  # fmt: skip
    """The returns of one sweep with the ego at pose (x, y, heading) in the world."""
    d, o = rays.directions, rays.origin
    down = d[:, 2] < -1e-9
    t = np.where(down, -o[2] / np.where(down, d[:, 2], -1.0), np.inf)
    x, y, heading = pose
    c, s = np.cos(heading), np.sin(heading)
    hit_object = np.zeros(len(d), bool)
    for box in obstacles:
        dx, dy = box.x - x, box.y - y
        centre = np.array([c * dx + s * dy, -s * dx + c * dy, box.height / 2])  # in the ego frame
        half_size = np.array([box.length, box.width, box.height]) / 2
        t_box = _ray_box(o - centre, d, box.heading - heading, half_size)
        closer = t_box < t
        t[closer], hit_object[closer] = t_box[closer], True
    t = t + rng.normal(0.0, RANGE_NOISE_M, len(t))
    spurious = rng.random(len(t)) < SPURIOUS_FRACTION
    t[spurious] = rng.uniform(1.0, max_range, spurious.sum())
    keep = (t > 0.5) & (t < max_range)
    xyz = o + t[keep, None] * d[keep]
    world_x, world_y = x + c * xyz[:, 0] - s * xyz[:, 1], y + s * xyz[:, 0] + c * xyz[:, 1]
    intensity = INTENSITY_MEAN[texture.material_at(world_x, world_y)]
    intensity[hit_object[keep] | spurious[keep]] = OBJECT_INTENSITY
    intensity = np.clip(intensity * rng.lognormal(0.0, 0.25, len(intensity)), 0, 255).astype(np.uint8)
    return Sweep(xyz, intensity, rays.laser[keep], rays.offset_ns[keep])


def _ray_box(origin: np.ndarray, d: np.ndarray, yaw: float, half: np.ndarray) -> np.ndarray:
    """Distance along each ray (origin relative to the box centre) to an upright box turned by yaw, or inf."""
    c, s = np.cos(yaw), np.sin(yaw)
    to_box = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    o, d = to_box @ origin, d @ to_box.T
    d = np.where(np.abs(d) < 1e-12, 1e-12, d)  # parallel to a slab: it never crosses it
    t1, t2 = (-half - o) / d, (half - o) / d
    near, far = np.minimum(t1, t2).max(axis=1), np.maximum(t1, t2).min(axis=1)
    return np.where((far >= near) & (near > 0), near, np.inf)
