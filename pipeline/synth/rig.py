"""Sensor rigs: the nuScenes 6-camera rig, the AV2 7 ring cameras and the roof LiDAR, at reduced resolution.

Poses are in the ego frame of both datasets (x forward, y left, z up, origin on the ground under the
rear axle). Placements and fields of view follow the real rigs; image sizes are divided by 4 (nuScenes,
1600 x 900 -> 400 x 225) and 8 (AV2, 2048 x 1550 -> 256 x 194) with the intrinsics scaled alike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# camera axes (x right, y down, z forward) in the ego frame for a camera looking straight ahead
CAMERA_AXES = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
CAMERA_AXES_QUATERNION = np.array([0.5, -0.5, 0.5, -0.5])  # w, x, y, z of CAMERA_AXES


def multiply_quaternions(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ])  # fmt: skip


def yaw_matrix(degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class CameraSpec:
    name: str
    yaw_deg: float  # where it looks, counter-clockwise from straight ahead
    translation: tuple[float, float, float]  # in the ego frame
    width: int
    height: int
    focal: float  # pixels
    cx: float
    cy: float

    @property
    def intrinsics(self) -> np.ndarray:
        return np.array([[self.focal, 0.0, self.cx], [0.0, self.focal, self.cy], [0.0, 0.0, 1.0]])

    @property
    def rotation(self) -> np.ndarray:
        """Camera axes -> ego frame."""
        return yaw_matrix(self.yaw_deg) @ CAMERA_AXES

    @property
    def quaternion(self) -> np.ndarray:
        half = math.radians(self.yaw_deg) / 2
        yaw = np.array([math.cos(half), 0.0, 0.0, math.sin(half)])
        q = multiply_quaternions(yaw, CAMERA_AXES_QUATERNION)
        return q if q[0] >= 0 else -q  # the same rotation; w >= 0 by convention


def _nuscenes(name: str, yaw: float, translation: tuple, focal: float, cx: float, cy: float) -> CameraSpec:
    return CameraSpec(name, yaw, translation, 400, 225, focal / 4, cx / 4, cy / 4)


NUSCENES_CAMERAS = [
    _nuscenes("CAM_FRONT", 0.0, (1.70, 0.016, 1.51), 1266.4, 816.3, 491.5),
    _nuscenes("CAM_FRONT_RIGHT", -55.0, (1.55, -0.49, 1.50), 1260.8, 807.9, 495.3),
    _nuscenes("CAM_BACK_RIGHT", -110.0, (1.04, -0.48, 1.56), 1259.5, 807.3, 501.2),
    _nuscenes("CAM_BACK", 180.0, (0.03, 0.004, 1.58), 809.2, 829.2, 481.8),
    _nuscenes("CAM_BACK_LEFT", 110.0, (1.05, 0.48, 1.56), 1256.7, 817.8, 451.9),
    _nuscenes("CAM_FRONT_LEFT", 55.0, (1.52, 0.49, 1.51), 1272.6, 826.6, 479.8),
]


def _av2(name: str, yaw: float, translation: tuple, portrait: bool = False) -> CameraSpec:
    width, height = (194, 256) if portrait else (256, 194)
    return CameraSpec(name, yaw, translation, width, height, 1686.0 / 8, width / 2, height / 2)


AV2_CAMERAS = [
    _av2("ring_front_center", 0.0, (1.63, 0.0, 1.43), portrait=True),
    _av2("ring_front_left", 45.0, (1.55, 0.26, 1.43)),
    _av2("ring_front_right", -45.0, (1.55, -0.26, 1.43)),
    _av2("ring_side_left", 99.0, (0.93, 0.40, 1.43)),
    _av2("ring_side_right", -99.0, (0.93, -0.40, 1.43)),
    _av2("ring_rear_left", 153.0, (-0.12, 0.37, 1.43)),
    _av2("ring_rear_right", -153.0, (-0.12, -0.37, 1.43)),
]


@dataclass(frozen=True)
class LidarSpec:
    translation: tuple[float, float, float]  # in the ego frame
    elevations_deg: np.ndarray  # one per laser, laser 0 lowest
    azimuth_steps: int  # firings per revolution
    max_range: float


# one 32-laser roof LiDAR (HDL-32E-like) serves both datasets: nuScenes LIDAR_TOP sits here too
ROOF_LIDAR = LidarSpec((0.943, 0.0, 1.84), np.linspace(-30.67, 10.67, 32), 180, 40.0)
AV2_LIDARS = {  # AV2 names two stacked lidars, the lower one upside down; the sweeps come from the upper one
    "up_lidar": (ROOF_LIDAR.translation, np.array([1.0, 0.0, 0.0, 0.0])),
    "down_lidar": ((0.943, 0.0, 1.72), np.array([0.0, 1.0, 0.0, 0.0])),
}
