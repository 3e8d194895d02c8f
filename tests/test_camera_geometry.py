"""The camera encoder's geometry end to end: a lane-paint point of the synthetic world, moved into a
prepared frame's BEV frame by its pose and projected by the encoder's `project_points` through the
frame's calibration (as `cli prepare` wrote it and `baselines.data` resized it), lands on the bright
paint that synth drew in that camera's image; the lane centres between the lines land on asphalt."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_synth import painted_lines

from baselines.config import tiny
from baselines.data import IMAGENET_MEAN, IMAGENET_STD, PreparedDataset
from baselines.encoder import project_points
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
        rgb = image.transpose(1, 2, 0) * IMAGENET_STD + IMAGENET_MEAN
        distance = np.linalg.norm(points - sample.sensor_to_ego[camera, :3, 3], axis=1)
        seen = visible[0, camera].numpy() & (distance > 3) & (distance < 20)
        uv = np.round(pixels[0, camera, seen].numpy()).astype(int)
        levels.append(rgb.mean(axis=2)[uv[:, 1], uv[:, 0]])
    return np.concatenate(levels)


@pytest.mark.parametrize("dataset", ["av2", "nuscenes"])
def test_bev_points_project_onto_the_paint_synth_drew(synth_prepared, dataset):
    world = build_world(0)
    paint = painted_lines(world, ("SOLID_WHITE", "SOLID_YELLOW"))
    centres = np.concatenate([lane.centerline(0.1)[:, :2] for lane in world.lanes.values()])
    config = tiny()
    config.encoder.modality = "camera"
    data = PreparedDataset(synth_prepared[dataset], "train" if dataset == "av2" else "mini_train", config)
    contrast, shifted = [], []
    for index in range(0, len(data), 10):
        frame, sample = data.frames[index], data[index]
        on_paint = grey_levels(sample, world_to_bev(frame, paint))
        on_asphalt = grey_levels(sample, world_to_bev(frame, centres))
        # the same points 0.6 m to the side: a projection that far off misses the paint
        off_paint = grey_levels(sample, world_to_bev(frame, paint) + np.array([0.6, 0.6, 0.0]))
        if len(on_paint) > 50 and len(on_asphalt) > 50:
            contrast.append(np.median(on_paint) - np.median(on_asphalt))
            shifted.append(np.median(off_paint) - np.median(on_asphalt))
    assert len(contrast) >= 4
    assert np.median(contrast) > 25, contrast  # measured: AV2 ~45, nuScenes ~35 grey levels
    assert np.median(contrast) > np.median(shifted) + 20, (contrast, shifted)  # shifted: ~5
