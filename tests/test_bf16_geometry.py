"""Under bf16 autocast (the gpu preset: CUDA's `torch.autocast("cuda", dtype=torch.bfloat16)`) the geometry
runs in fp32: the camera projection, GKT's sampling grid and its `grid_sample`, the Bezier curves of the
query decoder. CI has no GPU: the CPU's bf16 autocast lowers einsum and matmul to bf16 as CUDA's does, so
those run under it. It runs `grid_sample` in fp32 itself, where CUDA's runs it in bf16 when the volume and
the grid both come in bf16; that guard is tested on bf16 inputs without autocast, as CUDA's would run it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from baselines.layers.bev_encoder import CameraEncoder, SensorBatch
from baselines.layers.query_decoder import QueryDecoder, to_unit
from baselines.models import resolve_config
from pipeline.camera import project_points, scaled_intrinsics


def bf16_autocast() -> torch.autocast:
    return torch.autocast("cpu", dtype=torch.bfloat16)


def rotation(vector: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation by |vector| radians about vector."""
    angle = np.linalg.norm(vector)
    k = np.array([[0, -vector[2], vector[1]], [vector[2], 0, -vector[0]], [-vector[1], vector[0], 0]]) / angle
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def av2_like_rig(seed: int = 0, num_points: int = 20_000):
    """AV2's seven ring cameras resized by 0.3 (2048 x 1550, the front one upright), a few metres from the
    BEV origin, tilted by up to 2 degrees, around a BEV frame with x right and y forward; and BEV points up
    to 50 m away. Returns intrinsics (1, 7, 3, 3), sensor_to_ego (1, 7, 4, 4), image_sizes (1, 7, 2) and
    points (P, 3), fp32 tensors."""
    rng = np.random.default_rng(seed)
    intrinsics, poses, sizes = [], [], []
    for camera, yaw_deg in enumerate([90, 135, 45, 185, -5, 240, -60]):
        width, height = (1550, 2048) if camera == 0 else (2048, 1550)
        focal = 1773.0 if camera == 0 else 1686.0
        k = np.array([[focal, 0, width / 2 - 0.5], [0, focal, height / 2 - 0.5], [0, 0, 1]])
        k[:2, 2] += rng.uniform(-20, 20, 2)
        intrinsics.append(scaled_intrinsics(k, 0.3, 0.3))
        sizes.append([round(height * 0.3), round(width * 0.3)])
        yaw = math.radians(yaw_deg)
        forward = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
        camera_axes = np.column_stack([right, [0.0, 0.0, -1.0], forward])  # OpenCV: x right, y down, z ahead
        pose = np.eye(4)
        pose[:3, :3] = camera_axes @ rotation(rng.uniform(-0.035, 0.035, 3))
        ahead = rng.uniform(0.5, 1.5) * forward[:2] + rng.uniform(-0.5, 0.5, 2)
        pose[:3, 3] = [*ahead, rng.uniform(1.5, 2.0)]
        poses.append(pose)
    radius = 50 * np.sqrt(rng.uniform(0, 1, num_points))
    angle = rng.uniform(0, 2 * math.pi, num_points)
    points = np.column_stack([radius * np.cos(angle), radius * np.sin(angle), rng.uniform(-2, 2, num_points)])
    as_tensor = lambda a: torch.tensor(np.asarray(a), dtype=torch.float32)[None]  # noqa: E731
    return as_tensor(intrinsics), as_tensor(poses), as_tensor(sizes), as_tensor(points)[0]


def ramp_features(cameras: int, height: int, width: int) -> torch.Tensor:
    """(1, Ncam, 3, H, W) feature maps whose channels are each cell's column, row and camera index: small
    integers, exact in bf16, and a bilinear sample of them is the position it was sampled at."""
    rows, cols = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    maps = [torch.stack([cols, rows, torch.full_like(rows, c)]) for c in range(cameras)]
    return torch.stack(maps).float()[None]


def test_projection_under_bf16_autocast_equals_fp32():
    intrinsics, pose, sizes, points = av2_like_rig()
    pixels, visible = project_points(points, intrinsics, pose, sizes)
    with bf16_autocast():
        autocast_pixels, autocast_visible = project_points(points, intrinsics, pose, sizes)
    assert autocast_pixels.dtype == torch.float32 and visible.sum() > 5000
    assert torch.equal(autocast_visible, visible)
    assert (autocast_pixels - pixels)[visible].norm(dim=-1).max() < 1e-3
    # and fp32 is right: against the same projection in float64
    k, to_camera = intrinsics[0].double(), torch.linalg.inv(pose[0].double())[:, :3]
    homogeneous = torch.cat([points.double(), torch.ones(len(points), 1, dtype=torch.float64)], 1)
    in_camera = torch.einsum("nij,pj->npi", to_camera, homogeneous)
    on_image = torch.einsum("nij,npj->npi", k, in_camera)
    exact = on_image[..., :2] / on_image[..., 2:]
    assert (pixels[0].double() - exact)[visible[0]].norm(dim=-1).max() < 1e-3


@pytest.fixture(scope="module")
def gkt():
    """The gpu preset's camera encoder on the AV2-like rig: (encoder, batch, image size, ramp features)."""
    config = resolve_config("gpu").encoder
    intrinsics, pose, sizes, _ = av2_like_rig()
    batch = SensorBatch(
        intrinsics=intrinsics, sensor_to_ego=pose, image_sizes=sizes, ground_z=torch.tensor([-0.33])
    )
    image_hw = (640, 640)  # 614 x 614 at most, padded to a multiple of 32 (data.image_divisor)
    stride = config.feature_stride
    features = ramp_features(7, math.ceil(image_hw[0] / stride), math.ceil(image_hw[1] / stride))
    return CameraEncoder(config).eval(), batch, image_hw, features


def test_gkt_samples_where_fp32_does_under_bf16_autocast(gkt):
    """Sampling the ramps reads back each sample's position: under autocast (the neck's features in bf16)
    it is fp32's, rounded to bf16 as the attention reads it."""
    encoder, batch, image_hw, features = gkt
    sampled, mask, _ = encoder.sample_image_features(features, batch, image_hw)
    with bf16_autocast():
        autocast_sampled, autocast_mask, _ = encoder.sample_image_features(
            features.bfloat16(), batch, image_hw
        )
    assert mask.sum() > 10_000 and torch.equal(autocast_mask, mask)
    assert torch.equal(autocast_sampled, sampled.bfloat16())


def test_gkt_sampling_and_its_backward_run_in_fp32_on_bf16_features(gkt):
    """CUDA's autocast hands grid_sample bf16 features; sampled in bf16, the grid would be rounded and the
    backward would sum the many samples of a feature cell in bf16. Both match fp32 to bf16's rounding."""
    encoder, batch, image_hw, features = gkt
    features32 = features.clone().requires_grad_(True)
    sampled, _, _ = encoder.sample_image_features(features32, batch, image_hw)
    # positive, as counts of samples, and exact in bf16: both runs send the same gradient back
    weights = torch.rand(sampled.shape, generator=torch.Generator().manual_seed(0)).bfloat16().float()
    (sampled * weights).sum().backward()
    features16 = features.bfloat16().requires_grad_(True)
    sampled16, _, _ = encoder.sample_image_features(features16, batch, image_hw)
    (sampled16.float() * weights).sum().backward()
    assert sampled16.dtype == torch.bfloat16 and torch.equal(sampled16, sampled.bfloat16())
    assert features32.grad.max() > 50  # many samples add up in some cells
    torch.testing.assert_close(features16.grad, features32.grad.bfloat16(), rtol=2**-8, atol=1e-3)


@pytest.mark.parametrize("points, controls", [(20, 4), (30, 5)])  # STSU's pieces, LaneGAP's Bezier paths
def test_bezier_curves_under_bf16_autocast_equal_fp32(points, controls):
    """The point heads start at zero, so the decoder's curves are those of its initial control points
    whatever the features: under autocast they must be fp32's."""
    torch.manual_seed(0)
    decoder = QueryDecoder(32, 20, points, controls, 2, 4, 64, 0.0, 4).eval()
    with torch.no_grad():
        decoder.initial_reference.normal_(0, 1.5)
    bev = torch.randn(1, 32, 20, 10)
    with torch.no_grad():
        curves = decoder(bev)["points"]
        with bf16_autocast():
            autocast_curves = decoder(bev)["points"]
        reference = decoder.initial_reference.sigmoid().view(1, -1, 2)
        anchors = decoder.anchors(reference)
        with bf16_autocast():
            autocast_anchors = decoder.anchors(reference)
    assert autocast_curves.dtype == torch.float32
    assert (autocast_curves - curves).abs().max() < 1e-5
    assert (autocast_anchors - anchors).abs().max() < 1e-5
    exact = to_unit(decoder.bernstein.double() @ reference.double().view(1, 20, controls, 2))
    assert (curves[-1].double() - exact).abs().max() < 1e-5
