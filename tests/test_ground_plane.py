"""The ground plane per frame (frames.ground_z, ground_slope) and the exact image scale of `read_image`:
on a level frame (slope 0, 0), as every AV2 frame and the learning checks' synthetic AV2 data, the camera
encoder's sampling points, its image features, the LiDAR's heights above the ground and the loader's LiDAR
are bit for bit what they were with ground_z alone (the formulas of before are written out here); on a
sloped frame the sampling points lie on the plane. A full-size image keeps the scale 1; a JPEG decoded at
1/8 whose size 8 does not divide has the scale of its decoded extent."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from baselines.data import height_above_ground, read_image
from baselines.layers.bev_encoder import (
    CameraEncoder,
    PillarEncoder,
    SensorBatch,
    above_ground_to_bev,
    ground_height,
)
from baselines.models import resolve_config


def formula_of_before(points: torch.Tensor, ground_z: torch.Tensor) -> torch.Tensor:
    """`above_ground_to_bev` before the ground plane (commit 26a24ba): ground_z added to every height."""
    lifted = points.repeat(len(ground_z), 1, 1)
    lifted[..., 2] += ground_z[:, None]
    return lifted


def same_bits(a: torch.Tensor, b: torch.Tensor) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and torch.equal(a.view(torch.int32), b.view(torch.int32))


def look_at(yaw: float, height: float = 1.5) -> torch.Tensor:
    """Camera (x right, y down, z forward) -> BEV frame, looking along yaw (0 = +y) from `height`."""
    forward = torch.tensor([math.sin(-yaw), math.cos(yaw), 0.0])
    right = torch.tensor([math.cos(yaw), math.sin(yaw), 0.0])
    pose = torch.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = right, torch.tensor([0.0, 0.0, -1.0]), forward
    pose[2, 3] = height
    return pose


def camera_batch(ground_z: list[float], ground_slope, cameras: int = 4) -> SensorBatch:
    height, width = 48, 80
    intrinsics = torch.tensor([[40.0, 0, width / 2], [0, 40.0, height / 2], [0, 0, 1]])
    poses = torch.stack([look_at(2 * math.pi * i / cameras) for i in range(cameras)])
    batch = len(ground_z)
    return SensorBatch(
        intrinsics=intrinsics.expand(batch, cameras, 3, 3).clone(),
        sensor_to_ego=poses.expand(batch, cameras, 4, 4).clone(),
        image_sizes=torch.tensor([height, width]).expand(batch, cameras, 2).clone(),
        ground_z=torch.tensor(ground_z),
        ground_slope=None if ground_slope is None else torch.tensor(ground_slope, dtype=torch.float32),
    )


# the learning checks' synthetic AV2 frames have ground_z 0 (as `cli prepare` records it, -0.0 included);
# real AV2 about -0.33
LEVEL_GROUNDS = [0.0, -0.0, -0.343328, 1.25]


@pytest.mark.parametrize("preset", ["tiny", "paper", "gpu"])
def test_level_sampling_points_are_the_formula_of_before_bit_for_bit(preset):
    encoder = resolve_config(preset, modality="camera").encoder
    points = CameraEncoder(encoder).pillar_points
    ground_z = torch.tensor(LEVEL_GROUNDS)
    before = formula_of_before(points, ground_z)
    assert same_bits(above_ground_to_bev(points, ground_z, torch.zeros(len(ground_z), 2)), before)
    assert same_bits(above_ground_to_bev(points, ground_z), before)  # no slope given: level


def test_level_image_features_are_those_of_before_bit_for_bit():
    """The whole geometry of the camera encoder (projection, view choice, kernel sampling) on level frames
    with slope (0, 0), as the loader hands them over, against the same frames with ground_z alone."""
    config = resolve_config("paper", modality="camera").encoder  # four heights, -1.5 to 1.5 m
    config.backbone, config.channels, config.bev_h, config.bev_w = "resnet18", 16, 20, 10
    encoder = CameraEncoder(config).eval()
    torch.manual_seed(0)
    features = torch.randn(len(LEVEL_GROUNDS), 4, 16, 6, 10)
    sampled, mask, views = encoder.sample_image_features(
        features, camera_batch(LEVEL_GROUNDS, [[0.0, 0.0]] * len(LEVEL_GROUNDS)), (48, 80)
    )
    before = encoder.sample_image_features(features, camera_batch(LEVEL_GROUNDS, None), (48, 80))
    assert mask.any() and same_bits(sampled, before[0]) and torch.equal(mask, before[1])
    assert views == before[2]


def test_level_lidar_heights_are_those_of_before_bit_for_bit():
    """The pillar encoder's heights above the ground and the loader's z_range filter: the points' z minus
    ground_z, as before, on level frames."""
    generator = torch.Generator().manual_seed(0)
    spread = torch.tensor([8.0, 20.0, 1.0, 0.3])
    points = torch.randn(len(LEVEL_GROUNDS), 3000, 4, generator=generator) * spread
    ground_z = torch.tensor(LEVEL_GROUNDS)
    level = ground_height(points[..., :2], ground_z, torch.zeros(len(LEVEL_GROUNDS), 2))
    assert same_bits(points[..., 2] - level, points[..., 2] - ground_z[:, None])
    config = resolve_config("tiny", modality="lidar").encoder
    torch.manual_seed(0)
    pillars = PillarEncoder(config).eval()
    mask = torch.ones(points.shape[:2], dtype=torch.bool)
    with torch.no_grad():
        new = pillars(SensorBatch(points=points, points_mask=mask, ground_z=ground_z,
                                  ground_slope=torch.zeros(len(LEVEL_GROUNDS), 2)))  # fmt: skip
        old = pillars(SensorBatch(points=points, points_mask=mask, ground_z=ground_z))
    assert same_bits(new, old)
    for ground in LEVEL_GROUNDS:
        numpy_points = points[0].numpy()
        ground32 = float(np.float32(ground))  # frames.ground_z is float32
        before = numpy_points[:, 2] - ground32
        after = height_above_ground(numpy_points, ground32, [0.0, 0.0])
        assert after.dtype == np.float32 and np.array_equal(after.view(np.int32), before.view(np.int32))


def test_sampling_points_lie_on_a_sloped_ground_plane():
    """nuScenes' real key frame: z = -1.8408 + 0.0059 x + 0.0242 y in LIDAR_TOP; a height h above the
    ground is added straight up (along the BEV frame's z)."""
    encoder = resolve_config("paper", modality="camera").encoder
    points = CameraEncoder(encoder).pillar_points
    ground_z, slope = torch.tensor([-1.8408, 0.0]), torch.tensor([[0.0059, 0.0242], [0.0, 0.0]])
    lifted = above_ground_to_bev(points, ground_z, slope)
    x, y = points[:, 0], points[:, 1]
    assert torch.equal(lifted[..., :2], points[:, :2].expand(2, -1, -1))
    torch.testing.assert_close(lifted[0, :, 2], -1.8408 + 0.0059 * x + 0.0242 * y + points[:, 2])
    assert torch.equal(lifted[1], points)
    front = y > 29
    assert (lifted[0, front, 2] - points[front, 2] - -1.8408).min() > 0.6  # 2.4 % of 30 m: 0.7 m higher


def test_read_image_scale_is_that_of_the_decoded_extent(tmp_path):
    """A 1600 x 900 JPEG at 1/8 (the tiny preset) decodes to 200 x 113 blocks of 8 x 8 pixels, 904 rows the
    last of which half padding, resized to 200 x 112: the scale is 112 / 904 (112 / 900 put the bottom rows
    0.5 px off). At full size, or where 8 divides the size, it is new / size as before; other formats,
    which OpenCV resizes to floor(size / 8) over the whole image, keep new / size too."""
    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (900, 1600, 3), dtype=np.uint8)
    jpeg, png = tmp_path / "a.jpg", tmp_path / "a.png"
    cv2.imwrite(str(jpeg), image)
    cv2.imwrite(str(png), image)
    loaded, sx, sy = read_image(jpeg, 1 / 8, 1600, 900)
    assert loaded.shape == (112, 200, 3) and (sx, sy) == (200 / 1600, 112 / 904)
    _, sx, sy = read_image(png, 1 / 8, 1600, 900)
    assert (sx, sy) == (200 / 1600, 112 / 900)
    _, sx, sy = read_image(jpeg, 0.5, 1600, 900)  # 1/2: 800 x 450, no resize
    assert (sx, sy) == (0.5, 0.5)
    # full size (the learning checks' synthetic AV2 images, scale 1): the image as decoded, scale 1
    loaded, sx, sy = read_image(jpeg, 1.0, 1600, 900)
    assert (sx, sy) == (1.0, 1.0)
    assert np.array_equal(loaded, cv2.cvtColor(cv2.imread(str(jpeg)), cv2.COLOR_BGR2RGB))
    # the synthetic nuScenes images (400 x 225) at 1/2: 113 rows over 226, resized to 112
    small = tmp_path / "small.jpg"
    cv2.imwrite(str(small), image[:225, :400])
    loaded, sx, sy = read_image(small, 0.5, 400, 225)
    assert loaded.shape == (112, 200, 3) and (sx, sy) == (0.5, 112 / 226)
