"""Sensor rigs: the nuScenes 6-camera rig and HDL-32E LiDAR, the AV2 7 ring cameras and two VLP-32C LiDARs.

Poses are in the ego frame of both datasets (x forward, y left, z up, origin on the ground under the
rear axle). Placements and fields of view follow the real rigs; image sizes are divided by 4 (nuScenes,
1600 x 900 -> 400 x 225) and 8 (AV2, 2048 x 1550 -> 256 x 194) with the intrinsics scaled alike. The
LiDARs keep their real lasers and azimuth steps, so that sweeps are as dense as the real ones.
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


def tilt_quaternion(yaw_deg: float, y_deg: float, x_deg: float) -> np.ndarray:
    """w, x, y, z of Rz(yaw) Ry(y) Rx(x): turned about z, then tilted about the turned axes y and x."""
    halves = [math.radians(a) / 2 for a in (yaw_deg, y_deg, x_deg)]
    turns = [np.array([math.cos(h), *(math.sin(h) * np.eye(3)[axis])]) for h, axis in zip(halves, (2, 1, 0))]
    return multiply_quaternions(multiply_quaternions(turns[0], turns[1]), turns[2])


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


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a w, x, y, z quaternion (here, not pipeline.geometry.pose_matrix: that module
    imports numba, and `cli synth` stays quick to start)."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


@dataclass(frozen=True)
class LidarSpec:
    """A spinning multi-laser LiDAR: one firing of every laser per azimuth step, one revolution per sweep."""

    name: str
    translation: tuple[float, float, float]  # in the ego frame
    quaternion: np.ndarray  # w, x, y, z: sensor axes -> ego frame
    elevations_deg: np.ndarray  # in the sensor frame, indexed by the sensor's own laser id
    first_laser: int  # laser numbers in the published sweep are first_laser + laser id
    azimuth_steps: int  # firings per revolution
    revolution_ns: int  # one revolution per sweep
    max_range: float  # m
    # w, x, y, z: the axes that the lasers' elevations and azimuths are in -> ego frame; None: the sensor's
    laser_quaternion: np.ndarray | None = None

    @property
    def rotation(self) -> np.ndarray:
        return quaternion_matrix(self.quaternion)

    @property
    def laser_rotation(self) -> np.ndarray:
        return quaternion_matrix(self.quaternion if self.laser_quaternion is None else self.laser_quaternion)


IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])
UPSIDE_DOWN = np.array([0.0, 1.0, 0.0, 0.0])  # turned 180 deg about x
YAW_RIGHT = np.array([math.cos(math.pi / 4), 0.0, 0.0, -math.sin(math.pi / 4)])  # turned -90 deg about z

# Velodyne HDL-32E as nuScenes runs it: 20 Hz, ~695,000 returns a second, so 1085 firings (0.33 deg) per
# revolution and at most 34,720 points per sweep; 32 lasers 1.33 deg apart (ids in elevation order, as
# the nuScenes ring index); usable returns up to ~70 m.
HDL32E_ELEVATIONS_DEG = np.linspace(-30.67, 10.67, 32)
# Velodyne VLP-32C as AV2 runs it: 10 Hz, 1800 firings (0.2 deg) per revolution, so at most 57,600
# points per sweep; lasers crowd near the horizon (VLP-32C manual, vertical angle by laser id, which is
# also the firing order); range 200 m.
VLP32C_ELEVATIONS_DEG = np.array([
    -25.0, -1.0, -1.667, -15.639, -11.31, 0.0, -0.667, -8.843, -7.254, 0.333, -0.333, -6.148, -5.333, 1.333,
    0.667, -4.0, -4.667, 1.667, 1.0, -3.667, -3.333, 3.333, 2.333, -2.667, -3.0, 7.0, 4.667, -2.333, -2.0,
    15.0, 10.333, -1.333,
])  # fmt: skip


def _vlp32c(name: str, translation: tuple, quaternion: np.ndarray, first_laser: int) -> LidarSpec:
    return LidarSpec(
        name, translation, quaternion, VLP32C_ELEVATIONS_DEG, first_laser, 1800, 100_000_000, 200.0
    )


# nuScenes LIDAR_TOP as the real rig mounts it: turned -90 deg about z (its axes are x right, y forward) and
# tilted on the ego, as v1.0-mini scene-0061's calibrated_sensor (../shared/data/nuscenes/keyframe_scene-0061/
# calibration.json, lidar2ego = Rz(-89.8835 deg) Ry(0.338027 deg) Rx(-1.3884 deg): the yaw is kept at -90
# here; the two tilts below make the ego's up axis in LIDAR_TOP coordinates, lidar2ego's last row, the real
# one). In LIDAR_TOP's frame, the BEV frame, the ego's ground then rises 2.4 % forward (frames.ground_slope).
NUSCENES_LIDAR_PITCH_DEG = -1.3884  # about the sensor's x axis (the ego's right): its front 1.39 deg down
NUSCENES_LIDAR_ROLL_DEG = 0.338027  # about its y axis (forward): its right side 0.34 deg down
# The lasers keep the level sensor's pattern in the ego frame (the same ray per firing as before the tilt):
# a frame's random draws follow the number of returns, and the log's one random stream goes on to the next
# frame's AV2 sensors, which stay byte for byte as they were. The sweep is written in the tilted LIDAR_TOP
# frame (nuscenes_writer.write_pcd_bin), so that its ground is the tilted plane, as in real sweeps; only the
# ring numbers then keep the ego frame's elevation order (the project does not read them).
LIDAR_TOP_TILTED = tilt_quaternion(-90.0, NUSCENES_LIDAR_ROLL_DEG, NUSCENES_LIDAR_PITCH_DEG)
NUSCENES_LIDAR = LidarSpec("LIDAR_TOP", (0.943, 0.0, 1.84), LIDAR_TOP_TILTED, HDL32E_ELEVATIONS_DEG, 0, 1085,
                           50_000_000, 70.0, laser_quaternion=YAW_RIGHT)  # fmt: skip
# AV2: two stacked VLP-32C, the lower one upside down; a sweep merges both, laser numbers 0-31 and 32-63
AV2_LIDARS = [
    _vlp32c("up_lidar", (0.943, 0.0, 1.84), IDENTITY, 0),
    _vlp32c("down_lidar", (0.943, 0.0, 1.72), UPSIDE_DOWN, 32),
]
