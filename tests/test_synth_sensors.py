"""Synthetic sensors: LiDAR sweeps as dense as the real sensors (nuScenes HDL-32E, AV2 two VLP-32C),
paint bright in LiDAR intensity, ray casting that agrees with brute force, per-log camera lighting.

A small hand-made ground (asphalt with painted lines) keeps these fast and independent of the world
generator; the devkit round trips of whole datasets are in test_synth.py."""

from __future__ import annotations

import cv2
import numpy as np
import pyarrow.feather as feather
import pytest

from pipeline.synth import av2_writer, nuscenes_writer
from pipeline.synth.camera_render import Noise, camera_model, draw_lighting, render
from pipeline.synth.lidar import MIN_RANGE_M, Sweep, cast, lidar_rays, ray_box, trace
from pipeline.synth.rig import AV2_CAMERAS, AV2_LIDARS, NUSCENES_LIDAR
from pipeline.synth.texture import ASPHALT, COLOURS_BGR, MIP_LEVELS, RESOLUTION_M, WHITE, GroundTexture
from pipeline.synth.world import Box

POSE = np.array([3.0, -2.0, 0.4])  # the ego in the world: x, y, heading
CARS = [  # x, y (world), heading, length, width, height
    Box(14.0, 2.0, 0.4, 4.6, 1.9, 1.6),
    Box(-6.0, -6.5, 0.1, 4.4, 1.8, 1.5),  # behind the ego: its azimuths wrap around +-180 deg
    Box(6.0, 8.0, 1.2, 4.0, 1.8, 1.4),
    Box(20.0, -10.0, 2.0, 0.3, 0.3, 5.0),  # a pole
]


@pytest.fixture(scope="module")
def texture() -> GroundTexture:
    """200 x 200 m of asphalt around the world origin, with a 15 cm white line every 3.5 m along x."""
    size = round(200 / RESOLUTION_M)
    material = np.full((size, size), ASPHALT, np.uint8)
    y = -100.0 + np.arange(size) * RESOLUTION_M
    material[np.abs((y + 1.75) % 3.5 - 1.75) < 0.075] = WHITE
    colour = COLOURS_BGR[material].astype(np.uint8)
    pyramid = [colour]
    for _ in range(MIP_LEVELS - 1):
        pyramid.append(cv2.pyrDown(pyramid[-1]))
    return GroundTexture(-100.0, -100.0, material, pyramid)


@pytest.fixture(scope="module")
def sweeps(texture) -> dict[str, Sweep]:
    rng = np.random.default_rng(0)
    av2 = Sweep.merge([cast(lidar_rays(spec), texture, POSE, CARS, rng) for spec in AV2_LIDARS])
    return {"av2": av2, "nuscenes": cast(lidar_rays(NUSCENES_LIDAR), texture, POSE, CARS, rng)}


def in_crop(xyz: np.ndarray) -> np.ndarray:
    """Within the 30 x 60 m BEV range: 15 m either side, 30 m ahead and behind (ego frame, x forward)."""
    return (np.abs(xyz[:, 0]) < 30.0) & (np.abs(xyz[:, 1]) < 15.0)


def test_sweeps_have_the_real_sensors_density_and_columns(sweeps, tmp_path):
    # AV2: 2 x 32 lasers x 1800 firings; nuScenes: 32 lasers x 1085 firings (20 Hz). The flat world has
    # nothing above the horizon but cars and poles, so the lasers that point up return little.
    av2_path, nuscenes_path = tmp_path / "0.feather", tmp_path / "0.pcd.bin"
    av2_writer.write_sweep(av2_path, sweeps["av2"])
    nuscenes_writer.write_pcd_bin(nuscenes_path, sweeps["nuscenes"])

    table = feather.read_table(av2_path)
    assert table.schema.names == ["x", "y", "z", "intensity", "laser_number", "offset_ns"]
    assert [str(t) for t in table.schema.types] == ["halffloat"] * 3 + ["uint8", "uint8", "uint32"]
    assert 45_000 < table.num_rows <= 2 * 32 * 1800
    xyz = np.column_stack([table[c].to_numpy().astype(np.float64) for c in "xyz"])
    assert 18_000 < in_crop(xyz).sum() < 35_000
    assert table["offset_ns"].to_numpy().max() < 100_000_000  # one revolution at 10 Hz

    points = np.fromfile(nuscenes_path, np.float32).reshape(-1, 5)  # x, y, z, intensity, ring
    assert 20_000 < len(points) <= 32 * 1085
    ego_xy = np.column_stack([points[:, 1], -points[:, 0]]) + NUSCENES_LIDAR.translation[:2]  # x right
    assert 18_000 < in_crop(ego_xy).sum() < 30_000
    # LIDAR_TOP: at (0.943, 0, 1.84), x right, y forward, tilted as the real rig (rig.NUSCENES_LIDAR)
    ego = points[:, :3].astype(np.float64) @ NUSCENES_LIDAR.rotation.T + NUSCENES_LIDAR.translation
    assert np.allclose(ego, sweeps["nuscenes"].xyz, atol=1e-4)
    ex, ey, ez = sweeps["nuscenes"].xyz.T
    assert np.abs(points[:, :3] - np.column_stack([-ey, ex - 0.943, ez - 1.84])).max() > 0.5  # not level


def test_laser_numbers(sweeps):
    up, down = (lidar_rays(spec) for spec in AV2_LIDARS)
    elevation = {  # degrees in the ego frame, by laser number
        int(n): np.degrees(np.arcsin(rays.directions[rays.laser == n, 2])).mean()
        for rays in (up, down)
        for n in np.unique(rays.laser)
    }
    assert sorted(elevation) == list(range(64))
    # VLP-32C laser ids 0 and 29 point lowest and highest; the lower lidar is upside down
    assert elevation[0] == pytest.approx(-25.0) and elevation[29] == pytest.approx(15.0)
    assert elevation[32] == pytest.approx(25.0) and elevation[32 + 29] == pytest.approx(-15.0)
    assert np.isin(np.arange(64), sweeps["av2"].laser).sum() > 50  # most lasers see something
    # nuScenes ring: 0 is the lowest of the HDL-32E's lasers, 1.33 deg apart
    ring = lidar_rays(NUSCENES_LIDAR)
    rings = [np.degrees(np.arcsin(ring.directions[ring.laser == n, 2])).mean() for n in range(32)]
    assert rings[0] == pytest.approx(-30.67) and rings[31] == pytest.approx(10.67)
    assert np.allclose(np.diff(rings), 41.34 / 31)


def test_paint_is_brighter_than_asphalt(sweeps, texture):
    x, y, heading = POSE
    for sweep in sweeps.values():
        on_ground = np.abs(sweep.xyz[:, 2]) < 0.1
        ex, ey = sweep.xyz[on_ground, 0], sweep.xyz[on_ground, 1]
        world_x = x + np.cos(heading) * ex - np.sin(heading) * ey
        world_y = y + np.sin(heading) * ex + np.cos(heading) * ey
        material = texture.material_at(world_x, world_y)
        intensity = sweep.intensity[on_ground].astype(float)
        paint, asphalt = intensity[material == WHITE], intensity[material == ASPHALT]
        assert len(paint) > 300 and len(asphalt) > 10_000
        assert np.median(paint) / np.median(asphalt) > 8.0  # 110 vs 9 on average


def march(origin: np.ndarray, direction: np.ndarray, boxes: list[Box], step: float = 0.002) -> float:
    """Brute force: the first point, every step metres along the ray, inside one of the boxes (ego frame)."""
    t = np.arange(MIN_RANGE_M, 60.0, step)
    points = origin + t[:, None] * direction
    inside = np.zeros(len(t), bool)
    for b in boxes:
        c, s = np.cos(b.heading), np.sin(b.heading)
        dx, dy = points[:, 0] - b.x, points[:, 1] - b.y
        along, across = c * dx + s * dy, -s * dx + c * dy
        footprint = (np.abs(along) <= b.length / 2) & (np.abs(across) <= b.width / 2)
        inside |= footprint & (points[:, 2] >= 0) & (points[:, 2] <= b.height)
    return float(t[inside.argmax()]) if inside.any() else np.inf


def test_ray_box_hits_agree_with_brute_force():
    rays = lidar_rays(AV2_LIDARS[0])
    distance, hit_object = trace(rays, POSE, CARS)
    x, y, heading = POSE
    c, s = np.cos(heading), np.sin(heading)
    ego_boxes = [  # the cars in the ego frame
        Box(c * (b.x - x) + s * (b.y - y), -s * (b.x - x) + c * (b.y - y), b.heading - heading, b.length,
            b.width, b.height)
        for b in CARS
    ]  # fmt: skip
    # culling by azimuth changes nothing: the same as every ray against every box
    everything = rays.ground_range.copy()
    for b in ego_boxes:
        centre = np.array([b.x, b.y, b.height / 2]) - rays.origin
        everything = np.minimum(everything, ray_box(-centre, rays.directions, b.heading, half_size(b)))
    assert np.array_equal(distance, everything)
    # rays around every box (hits and near misses; the second box straddles azimuth 180 deg) against
    # brute force
    azimuth = np.arctan2(rays.directions[:, 1], rays.directions[:, 0])
    rng = np.random.default_rng(1)
    for b in ego_boxes:
        off = (azimuth - np.arctan2(b.y - rays.origin[1], b.x - rays.origin[0]) + np.pi) % (2 * np.pi) - np.pi
        near = np.flatnonzero((np.abs(off) < np.radians(25)) & (rays.directions[:, 2] < 0.3))
        hits, misses = near[hit_object[near]], near[~hit_object[near]]
        assert len(hits) > 100
        for index in np.concatenate(
            [rng.choice(hits, 15, replace=False), rng.choice(misses, 15, replace=False)]
        ):
            expected = march(rays.origin, rays.directions[index], ego_boxes)
            if expected < rays.ground_range[index]:
                assert hit_object[index] and distance[index] == pytest.approx(expected, abs=0.003)
            else:
                assert not hit_object[index] and distance[index] == rays.ground_range[index]


def half_size(b: Box) -> np.ndarray:
    return np.array([b.length, b.width, b.height]) / 2


def test_logs_have_their_own_lighting_and_noise(texture):
    # write_sensors draws a log's lighting from the log's generator: different logs, different light
    lightings = [draw_lighting(np.random.default_rng([0, 3, index])) for index in range(2)]
    model = camera_model(AV2_CAMERAS[0])
    pose = np.array([0.0, 0.0, 0.0])
    means = []
    for lighting in lightings:
        assert 0.75 <= lighting.brightness <= 1.2 and 0.8 <= lighting.contrast <= 1.2
        assert 2.0 <= lighting.noise_sigma <= 5.0
        noise = Noise(np.random.default_rng(5), lighting.noise_sigma)
        assert noise.like(194, 256).std() == pytest.approx(lighting.noise_sigma, rel=0.1)
        image = render(model, texture, pose, lighting, noise)
        means.append(image.reshape(-1, 3).mean(axis=0))
    assert np.abs(means[0] - means[1]).max() > 10.0  # grey levels
    blue_to_red = [m[0] / m[2] for m in means]  # the white balance: 1.11 and 1.44
    assert abs(blue_to_red[0] - blue_to_red[1]) > 0.2
