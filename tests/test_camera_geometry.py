"""The camera encoder's geometry end to end: a lane-paint point of the synthetic world, moved into a
prepared frame's BEV frame by its pose and projected by the encoder's `project_points` (pipeline/camera.py)
through the frame's calibration (as `cli prepare` wrote it and `baselines.data` resized it), lands on the
bright paint that synth drew in that camera's image; the lane centres between the lines land on asphalt.
The same holds for the tiny preset's own pillar height, lifted onto each frame's ground by the ground plane
that `cli prepare` recorded (`ground_z`, `ground_slope`: nuScenes' LIDAR_TOP is 1.84 m above the ground and
pitched 1.4 deg on the ego, as the real rig, so that the ground rises 2.4 % forward in its frame)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_synth import painted_lines

from baselines.data import PreparedDataset
from baselines.layers.bev_encoder import above_ground_to_bev
from baselines.models import resolve_config
from pipeline.camera import project_points
from pipeline.io import read_table
from pipeline.manifest import PreparedData
from pipeline.synth.world import build_world


def world_to_bev(frame: dict, xy: np.ndarray) -> np.ndarray:
    w, x, y, z = frame["pose_rotation"]
    rotation = np.array(  # BEV -> world
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    world = np.column_stack([xy, np.zeros(len(xy))])  # synth's ground is the plane z = 0
    return (world - np.array(frame["pose_translation"])) @ rotation


def grey_levels(sample, points: np.ndarray) -> np.ndarray:
    """Grey level (0..255) under each BEV point in every camera that sees it 3-20 m away."""
    pixels, visible = project_points(
        torch.from_numpy(points).float(),
        torch.from_numpy(sample.intrinsics)[None],
        torch.from_numpy(sample.sensor_to_ego)[None],
        torch.from_numpy(sample.image_sizes)[None],
    )
    levels = []
    for camera, image in enumerate(sample.images):
        rgb = image.transpose(1, 2, 0).astype(np.float64)
        distance = np.linalg.norm(points - sample.sensor_to_ego[camera, :3, 3], axis=1)
        seen = visible[0, camera].numpy() & (distance > 3) & (distance < 20)
        uv = np.round(pixels[0, camera, seen].numpy()).astype(int)
        levels.append(rgb.mean(axis=2)[uv[:, 1], uv[:, 0]])
    return np.concatenate(levels)


def on_default_pillars(frame: dict, points: np.ndarray) -> np.ndarray:
    """BEV points moved to the tiny preset's pillar height above the frame's ground plane, as the camera
    encoder places its pillar points."""
    (height,) = resolve_config("tiny").encoder.camera_heights
    above_ground = torch.from_numpy(np.column_stack([points[:, :2], np.full(len(points), height)])).float()
    slope = torch.tensor([frame["ground_slope"]], dtype=torch.float32)
    return above_ground_to_bev(above_ground, torch.tensor([frame["ground_z"]]), slope)[0].numpy()


@pytest.mark.parametrize("dataset", ["av2", "nuscenes"])
@pytest.mark.parametrize("height", ["pose", "default pillars"])
def test_bev_points_project_onto_the_paint_synth_drew(synth_prepared, dataset, height):
    world = build_world(0)
    paint = painted_lines(world, ("SOLID_WHITE", "SOLID_YELLOW"))
    centres = np.concatenate([lane.centerline(0.1)[:, :2] for lane in world.lanes.values()])
    config = resolve_config("tiny")
    config.encoder.modality = "camera"
    split = "train" if dataset == "av2" else "mini_train"
    data = PreparedDataset(PreparedData.open(synth_prepared[dataset]), split, config)

    def bev(frame: dict, xy: np.ndarray) -> np.ndarray:
        points = world_to_bev(frame, xy)  # "pose": the ground's own height, through the pose
        return on_default_pillars(frame, points) if height == "default pillars" else points

    contrast, shifted = [], []
    for index in range(0, len(data), 10):
        frame, sample = data.frames[index], data[index]
        on_paint = grey_levels(sample, bev(frame, paint))
        on_asphalt = grey_levels(sample, bev(frame, centres))
        # the same points 0.6 m to the side: a projection that far off misses the paint
        off_paint = grey_levels(sample, bev(frame, paint) + np.array([0.6, 0.6, 0.0]))
        if len(on_paint) > 50 and len(on_asphalt) > 50:
            contrast.append(np.median(on_paint) - np.median(on_asphalt))
            shifted.append(np.median(off_paint) - np.median(on_asphalt))
    assert len(contrast) >= 4
    assert np.median(contrast) > 25, contrast  # measured: AV2 ~45, nuScenes ~35 grey levels
    assert np.median(contrast) > np.median(shifted) + 20, (contrast, shifted)  # shifted: ~5


def test_prepare_records_the_ground_under_the_bev_origin(synth_prepared):
    """nuScenes: LIDAR_TOP is 1.84 m above the ground, which rises 2.4 % forward in its frame (it is pitched
    on the ego as the real rig: pipeline/synth/rig.py); AV2: the synthetic egovehicle origin is on the
    ground, level."""
    for dataset, expected, slope in (("nuscenes", -1.84, (0.0059, 0.0242)), ("av2", 0.0, (0.0, 0.0))):
        frames = read_table(synth_prepared[dataset], "frames", columns=["ground_z", "ground_slope"])
        ground = frames["ground_z"].to_numpy()
        assert len(ground) > 0 and np.allclose(ground, expected, atol=0.01), (dataset, ground)
        slopes = np.array(frames["ground_slope"].to_pylist())
        assert np.allclose(slopes, slope, atol=1e-4), (dataset, slopes[0])
    assert (np.array(read_table(synth_prepared["av2"], "frames")["ground_slope"].to_pylist()) == 0).all()


def test_the_synthetic_lidar_ground_is_on_the_recorded_plane(synth_prepared):
    """The synthetic nuScenes sweep is written in the tilted LIDAR_TOP frame: its ground returns lie on the
    plane that `cli prepare` recorded (z = ground_z + a x + b y), not on the flat z = ground_z (0.4-0.7 m off
    it 20-30 m ahead and behind), as the real key frame's (tests/test_real_sensors.py)."""
    config = resolve_config("tiny")
    config.encoder.modality = "lidar"
    data = PreparedDataset(PreparedData.open(synth_prepared["nuscenes"]), "mini_train", config)
    for index in (0, len(data) // 2):
        frame, points = data.frames[index], data[index].points.astype(np.float64)
        (a, b), ground_z = frame["ground_slope"], frame["ground_z"]
        above_plane = points[:, 2] - (ground_z + a * points[:, 0] + b * points[:, 1])
        for far in (points[:, 1] < -20, points[:, 1] > 20):
            on_plane = np.abs(above_plane[far]) < 0.1  # the range noise is 0.02 m
            assert on_plane.sum() > 100, (index, far.sum(), on_plane.sum())  # measured: 154-191 of 154-399
            assert np.abs(np.median(above_plane[far][on_plane])) < 0.01  # measured: 0.0002 m
            assert np.abs(np.median(points[far][on_plane, 2] - ground_z)) > 0.4  # measured: 0.61-0.63 m


@pytest.mark.parametrize("dataset", ["av2", "nuscenes"])
def test_the_tiny_preset_crops_only_sky(synth_prepared, dataset):
    """The rows that `data.synthetic_image_crop_top` cuts off hold no projection of the BEV grid's pillar
    points: the encoder sees every BEV cell in as many cameras, at the same image content, as uncropped."""
    whole, cropped = resolve_config("tiny"), resolve_config("tiny")
    assert cropped.data.synthetic_image_crop_top > 0
    whole.data.synthetic_image_crop_top = 0.0
    split = "train" if dataset == "av2" else "mini_train"
    encoder = cropped.encoder
    (x0, x1), (y0, y1) = encoder.x_range, encoder.y_range
    xs, ys = np.meshgrid(np.linspace(x0, x1, 4 * encoder.bev_w), np.linspace(y0, y1, 4 * encoder.bev_h))
    grid = np.column_stack([xs.ravel(), ys.ravel()])
    for config in (whole, cropped):
        config.encoder.modality = "camera"
    prepared = PreparedData.open(synth_prepared[dataset])
    data = [PreparedDataset(prepared, split, config) for config in (whole, cropped)]
    for index in (0, len(data[0]) // 2):
        frame = data[0].frames[index]
        points = torch.from_numpy(on_default_pillars(frame, grid)).float()
        seen = []
        for prepared in data:
            sample = prepared[index]
            pixels, visible = project_points(
                points, *(torch.from_numpy(a)[None] for a in (sample.intrinsics, sample.sensor_to_ego,
                                                                sample.image_sizes)),
            )  # fmt: skip
            seen.append((sample, pixels[0], visible[0]))
        (full, full_pixels, full_visible), (cut, cut_pixels, cut_visible) = seen
        assert torch.equal(full_visible, cut_visible)
        top = full.image_sizes[:, 0] - cut.image_sizes[:, 0]  # rows cut off each camera
        assert (top > 0).all()
        shift = torch.from_numpy(np.stack([np.zeros_like(top), top], 1)).float()[:, None]
        assert full_visible.sum() > 1000
        assert torch.allclose((full_pixels - shift)[full_visible], cut_pixels[cut_visible], atol=1e-3)
        for camera, (height, width) in enumerate(cut.image_sizes):
            kept = full.images[camera, :, top[camera] : top[camera] + height, :width]
            assert np.array_equal(kept, cut.images[camera, :, :height, :width])
