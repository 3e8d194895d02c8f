"""LiDAR sweeps by ray casting: spinning multi-laser sensors over the flat ground, cars, poles, buildings.

Every firing of a real sensor is one ray (the HDL-32E of nuScenes, 34,720 a sweep; the two VLP-32C of
AV2, 57,600 each). The ego is level and the ground flat, so where each ray meets the ground never changes:
that is computed once per sensor, and a frame only tests the rays that point at an obstacle (a window of
azimuths per box) before the slab test. Ground returns take their intensity from the ground material, so
lane paint shines (retroreflective beads) against dark asphalt, as in real sweeps. Points are in the ego
frame (x forward, y left, z up) at the sweep time, motion compensated as AV2 and nuScenes publish them.
The buildings along the roads return the lasers that point up: a sweep holds ~31,000 points (nuScenes)
and ~97,000 (AV2), as a real city sweep (~34,000 and ~100,000); without them ~24,000 and ~53,000.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.synth.rig import LidarSpec
from pipeline.synth.texture import ASPHALT, GRASS, WHITE, YELLOW, GroundTexture
from pipeline.synth.world import Box

INTENSITY_MEAN = np.zeros(4)
INTENSITY_MEAN[[GRASS, ASPHALT, WHITE, YELLOW]] = 25.0, 9.0, 110.0, 80.0  # by ground material
OBJECT_INTENSITY = 40.0
INTENSITY_SPREAD = 0.25  # sigma of the log of the intensity about its mean
RANGE_NOISE_M = 0.02
MIN_RANGE_M = 0.5  # closer echoes are cut, as the sensors do
SPURIOUS_FRACTION = 0.005  # returns from dust, rain, multipath: at a random range along their ray


@dataclass(frozen=True)
class Sweep:
    xyz: np.ndarray  # (n, 3) float64, ego frame
    intensity: np.ndarray  # (n,) uint8
    laser: np.ndarray  # (n,) uint8, the laser number as the dataset publishes it
    offset_ns: np.ndarray  # (n,) uint32, firing time after the sweep timestamp

    @staticmethod
    def merge(sweeps: list[Sweep]) -> Sweep:
        """One sweep of several sensors, as AV2 publishes its two LiDARs."""
        return Sweep(*(np.concatenate([getattr(s, f) for s in sweeps]) for f in Sweep.__dataclass_fields__))


@dataclass(frozen=True)
class Rays:
    """Every firing of one sensor in a revolution, in the ego frame and in firing order."""

    origin: np.ndarray  # (3,)
    directions: np.ndarray  # (n, 3) unit vectors
    laser: np.ndarray  # (n,) uint8
    offset_ns: np.ndarray  # (n,) uint32
    max_range: float
    ground_range: np.ndarray  # (n,) distance to the ground along each ray; inf if up or beyond max_range
    by_azimuth: np.ndarray  # (n,) ray indices sorted by azimuth in the ego frame
    sorted_azimuth: np.ndarray  # (n,) those azimuths, ascending in [-pi, pi]

    def within_azimuth(self, low: float, high: float) -> np.ndarray:
        """Indices of the rays with azimuth in [low, high] (radians, high - low < 2 pi, any turn)."""
        width = high - low
        low = (low + np.pi) % (2 * np.pi) - np.pi
        high = low + width
        start = np.searchsorted(self.sorted_azimuth, low)
        if high <= np.pi:
            return self.by_azimuth[start : np.searchsorted(self.sorted_azimuth, high, "right")]
        wrapped = np.searchsorted(self.sorted_azimuth, high - 2 * np.pi, "right")
        return np.concatenate([self.by_azimuth[start:], self.by_azimuth[:wrapped]])


def lidar_rays(spec: LidarSpec) -> Rays:
    azimuth = np.arange(spec.azimuth_steps) * (2 * np.pi / spec.azimuth_steps)
    elevation = np.radians(spec.elevations_deg)
    az, el = np.meshgrid(azimuth, elevation, indexing="ij")  # firing order: azimuth, then laser id
    in_sensor = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)
    directions = in_sensor.reshape(-1, 3) @ spec.laser_rotation.T
    laser = (spec.first_laser + np.broadcast_to(np.arange(len(elevation)), az.shape)).reshape(-1)
    offset = (az.reshape(-1) / (2 * np.pi) * spec.revolution_ns).astype(np.uint32)
    origin = np.array(spec.translation, np.float64)
    down = directions[:, 2] < -1e-9
    ground = np.where(down, -origin[2] / np.where(down, directions[:, 2], -1.0), np.inf)
    ground[ground >= spec.max_range] = np.inf
    ego_azimuth = np.arctan2(directions[:, 1], directions[:, 0])
    by_azimuth = np.argsort(ego_azimuth, kind="stable")
    return Rays(origin, directions, laser.astype(np.uint8), offset, spec.max_range, ground, by_azimuth,
                ego_azimuth[by_azimuth])  # fmt: skip


def trace(rays: Rays, pose: np.ndarray, obstacles: list[Box]) -> tuple[np.ndarray, np.ndarray]:
    """Distance along each ray to what it meets first (inf: nothing within range) and whether that is an
    obstacle rather than the ground, with the ego at pose (x, y, heading) in the world."""
    distance = rays.ground_range.copy()
    hit_object = np.zeros(len(distance), bool)
    x, y, heading = pose
    c, s = np.cos(heading), np.sin(heading)
    for box in obstacles:
        dx, dy = box.x - x, box.y - y
        # the box centre from the sensor, in the ego axes
        centre = np.array([c * dx + s * dy, -s * dx + c * dy, box.height / 2]) - rays.origin
        half_size = np.array([box.length, box.width, box.height]) / 2
        if np.hypot(centre[0], centre[1]) - np.hypot(half_size[0], half_size[1]) >= rays.max_range:
            continue
        yaw = box.heading - heading
        window = _azimuth_window(centre[:2], yaw, half_size[:2])
        candidates = rays.within_azimuth(*window) if window else np.arange(len(distance))
        t_box = ray_box(-centre, rays.directions[candidates], yaw, half_size)
        closer = t_box < distance[candidates]
        distance[candidates[closer]] = t_box[closer]
        hit_object[candidates[closer]] = True
    return distance, hit_object


def cast(rays: Rays, texture: GroundTexture, pose: np.ndarray, obstacles: list[Box],
         rng: np.random.Generator) -> Sweep:  # fmt: skip
    """The returns of one sensor's sweep with the ego at pose (x, y, heading) in the world."""
    distance, hit_object = trace(rays, pose, obstacles)
    spurious = rng.integers(0, len(distance), rng.binomial(len(distance), SPURIOUS_FRACTION))
    distance[spurious] = rng.uniform(MIN_RANGE_M, rays.max_range, len(spurious))
    hit_object[spurious] = True  # dust and rain return like objects, not like the ground's paint
    hit = np.flatnonzero(distance < rays.max_range)
    measured = distance[hit] + RANGE_NOISE_M * rng.standard_normal(len(hit), np.float32)
    keep = measured > MIN_RANGE_M
    hit, measured = hit[keep], measured[keep]
    xyz = rays.origin + measured[:, None] * rays.directions[hit]
    x, y, heading = pose
    c, s = np.cos(heading), np.sin(heading)
    world_x, world_y = x + c * xyz[:, 0] - s * xyz[:, 1], y + s * xyz[:, 0] + c * xyz[:, 1]
    ground = INTENSITY_MEAN[texture.material_at(world_x, world_y)]
    intensity = np.where(hit_object[hit], OBJECT_INTENSITY, ground)
    intensity *= np.exp(INTENSITY_SPREAD * rng.standard_normal(len(hit), np.float32))  # log-normal
    return Sweep(xyz, np.clip(intensity, 0, 255).astype(np.uint8), rays.laser[hit], rays.offset_ns[hit])


def _azimuth_window(centre: np.ndarray, yaw: float, half: np.ndarray) -> tuple[float, float] | None:
    """The azimuths (from the sensor, ego axes) that an upright box centred at centre (x, y) from the
    sensor covers; None when the sensor stands inside its footprint and it surrounds it."""
    c, s = np.cos(yaw), np.sin(yaw)
    sensor_x, sensor_y = -centre  # the sensor from the box centre
    if abs(c * sensor_x + s * sensor_y) <= half[0] and abs(-s * sensor_x + c * sensor_y) <= half[1]:
        return None
    u, v = np.array([1, 1, -1, -1]) * half[0], np.array([1, -1, 1, -1]) * half[1]
    corners_x, corners_y = centre[0] + c * u - s * v, centre[1] + s * u + c * v
    middle = np.arctan2(centre[1], centre[0])
    # the footprint does not hold the sensor, so its corners lie within half a turn of its centre's azimuth
    spread = (np.arctan2(corners_y, corners_x) - middle + np.pi) % (2 * np.pi) - np.pi
    return middle + spread.min(), middle + spread.max()


def ray_box(origin: np.ndarray, d: np.ndarray, yaw: float, half: np.ndarray) -> np.ndarray:
    """Distance along each ray (origin relative to the box centre) to an upright box turned by yaw, or inf."""
    c, s = np.cos(yaw), np.sin(yaw)
    to_box = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    o, d = to_box @ origin, d @ to_box.T
    d = np.where(np.abs(d) < 1e-12, 1e-12, d)  # parallel to a slab: it never crosses it
    t1, t2 = (-half - o) / d, (half - o) / d
    near, far = np.minimum(t1, t2).max(axis=1), np.maximum(t1, t2).min(axis=1)
    return np.where((far >= near) & (near > 0), near, np.inf)
