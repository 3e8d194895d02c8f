"""Unit tests of the LaneGAP model code on random tensors: no dataset needed."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from baselines.config import apply_overrides
from baselines.layers.attention import DeformableAttention, deformable_sample
from baselines.layers.bev_encoder import SensorBatch, bev_cell_centres
from baselines.layers.blocks import bernstein_matrix
from baselines.layers.matcher import focal_cost, hungarian_match, ordered_point_cost
from baselines.layers.query_decoder import MARGIN
from baselines.layers.resnet import build_resnet
from baselines.layers.targets import Targets
from baselines.models import load_config, resolve_config
from baselines.models.lanegap import LaneGAP, LaneGAPLoss, select_paths
from pipeline.camera import project_points

torch.set_num_threads(1)


def look_at_camera(yaw: float, height: float = 1.5) -> torch.Tensor:
    """camera -> BEV 4x4 of a camera at (0, 0, height) looking horizontally at heading `yaw` (0 = +y)."""
    forward = torch.tensor([math.sin(yaw), math.cos(yaw), 0.0])
    right = torch.tensor([math.cos(yaw), -math.sin(yaw), 0.0])
    down = torch.tensor([0.0, 0.0, -1.0])
    pose = torch.eye(4)
    pose[:3, :3] = torch.stack([right, down, forward], 1)  # columns: camera x, y, z in the BEV frame
    pose[2, 3] = height
    return pose


def random_batch(batch: int = 2, cameras: int = 6, height: int = 48, width: int = 80) -> SensorBatch:
    generator = torch.Generator().manual_seed(0)
    intrinsics = torch.tensor([[40.0, 0, width / 2], [0, 40.0, height / 2], [0, 0, 1]])
    poses = torch.stack([look_at_camera(2 * math.pi * i / cameras) for i in range(cameras)])
    points = torch.randn(batch, 500, 4, generator=generator) * torch.tensor([8.0, 20.0, 1.0, 0.3])
    mask = torch.ones(batch, 500, dtype=torch.bool)
    mask[-1, 400:] = False
    return SensorBatch(
        images=torch.randn(batch, cameras, 3, height, width, generator=generator),
        intrinsics=intrinsics.expand(batch, cameras, 3, 3).clone(),
        sensor_to_ego=poses.expand(batch, cameras, 4, 4).clone(),
        image_sizes=torch.tensor([height, width]).expand(batch, cameras, 2).clone(),
        points=points,
        points_mask=mask,
    )


def test_resnet_matches_torchvision_names_and_sizes():
    # Parameter counts of torchvision's resnet18 / 34 / 50 (with their fc layer).
    expected = {"resnet18": 11_689_512, "resnet34": 21_797_672, "resnet50": 25_557_032}
    for name, count in expected.items():
        model = build_resnet(name)
        assert sum(p.numel() for p in model.parameters()) == count
    keys = build_resnet("resnet50").state_dict().keys()
    for key in [
        "conv1.weight",
        "bn1.num_batches_tracked",
        "layer1.0.downsample.0.weight",
        "layer1.0.downsample.1.running_var",
        "layer4.2.conv3.weight",
        "layer4.2.bn3.bias",
        "fc.bias",
    ]:
        assert key in keys


def test_resnet_loads_a_state_dict_file(tmp_path):
    torch.manual_seed(0)
    source = build_resnet("resnet18")
    torch.save(source.state_dict(), tmp_path / "resnet18.pth")
    loaded = build_resnet("resnet18", weights=tmp_path / "resnet18.pth")
    assert torch.equal(loaded.layer3[1].conv2.weight, source.layer3[1].conv2.weight)
    strides = [4, 8, 16, 32]
    outputs = loaded.eval()(torch.randn(1, 3, 64, 96))
    assert [tuple(o.shape[-2:]) for o in outputs] == [(64 // s, 96 // s) for s in strides]


def test_bernstein_matrix_is_a_bezier_curve():
    basis = bernstein_matrix(7, 5)
    assert torch.allclose(basis.sum(1), torch.ones(7))
    controls = torch.randn(5, 2, generator=torch.Generator().manual_seed(1))
    curve = basis @ controls
    assert torch.allclose(curve[0], controls[0]) and torch.allclose(curve[-1], controls[-1])
    # De Casteljau at t = 1/3 (row 2 of 7 evenly spaced parameters).
    points = controls.clone()
    for _ in range(4):
        points = points[:-1] + (points[1:] - points[:-1]) / 3
    assert torch.allclose(curve[2], points[0], atol=1e-6)
    # Evenly spaced collinear controls give evenly spaced points (linear precision).
    line = torch.stack([torch.linspace(0, 1, 5), torch.zeros(5)], 1)
    assert torch.allclose((basis @ line)[:, 0], torch.linspace(0, 1, 7), atol=1e-6)


@pytest.mark.parametrize("seed", range(6))
def test_hungarian_matching_equals_brute_force(seed):
    generator = torch.Generator().manual_seed(seed)
    queries, n = 5, 4
    num_targets = seed % 4 + 1
    logits = torch.randn(queries, generator=generator)
    points = torch.rand(queries, n, 2, generator=generator)
    targets = torch.rand(num_targets, n, 2, generator=generator)
    rows, cols = hungarian_match(logits, points, targets, cls_weight=2.0, point_weight=5.0)
    cost = 2.0 * focal_cost(logits)[:, None] + 5.0 * ordered_point_cost(points, targets)
    best = min(
        sum(cost[q, g] for g, q in enumerate(chosen))
        for chosen in itertools.permutations(range(queries), num_targets)
    )
    assert len(rows) == num_targets and sorted(cols.tolist()) == list(range(num_targets))
    assert math.isclose(float(cost[rows, cols].sum()), float(best), rel_tol=1e-6)


def test_point_cost_keeps_the_direction():
    path = torch.stack([torch.linspace(0, 1, 10), torch.full((10,), 0.5)], 1)
    cost = ordered_point_cost(path[None], torch.stack([path, path.flip(0)]))
    assert cost[0, 0] == 0 and cost[0, 1] > 0.4


def test_projection_of_a_bev_point_to_its_pixel():
    # A point 10 m ahead and 2 m to the right of a forward camera 1.5 m up, on the ground.
    intrinsics = torch.tensor([[[[100.0, 0, 64], [0, 100.0, 48], [0, 0, 1]]]])
    pose = look_at_camera(0.0)[None, None]
    sizes = torch.tensor([[[96, 128]]])
    points = torch.tensor([[2.0, 10.0, 0.0], [0.0, -10.0, 0.0], [100.0, 10.0, 0.0]])
    pixels, visible = project_points(points, intrinsics, pose, sizes)
    assert torch.allclose(pixels[0, 0, 0], torch.tensor([64 + 100 * 2 / 10, 48 + 100 * 1.5 / 10]))
    assert visible[0, 0].tolist() == [True, False, False]  # behind the camera; outside the image


def test_bev_cell_centres_follow_the_raster_convention():
    config = resolve_config("tiny").encoder
    centres = bev_cell_centres(config)
    cell = 60 / config.bev_h
    assert torch.allclose(centres[0, 0], torch.tensor([-15 + cell / 2, 30 - cell / 2]))
    unit = config.metres_to_unit(centres)
    assert torch.allclose(unit[0, 0], torch.tensor([0.5 / config.bev_w, 0.5 / config.bev_h]))
    assert torch.allclose(config.unit_to_metres(unit), centres, atol=1e-5)
    assert np.allclose(config.metres_to_unit(np.array([[15.0, -30.0]])), [[1.0, 1.0]])


def test_deformable_sample_reads_the_pixel_under_the_location():
    value = torch.zeros(1, 1, 4, 6)
    value[0, 0, 1, 4] = 7.0
    location = torch.tensor([(4 + 0.5) / 6, (1 + 0.5) / 4]).view(1, 1, 1, 1, 1, 2)
    out = deformable_sample([value], location, torch.ones(1, 1, 1, 1, 1))
    assert torch.allclose(out, torch.tensor([[[7.0]]]))
    attention = DeformableAttention(16, heads=4, levels=2, points=3, anchors=2)
    query = torch.randn(2, 5, 16)
    out = attention(query, torch.rand(2, 5, 2, 2), [torch.randn(2, 16, 8, 4), torch.randn(2, 16, 4, 2)])
    assert out.shape == (2, 5, 16)


@pytest.mark.parametrize(("modality", "bezier_points"), [("camera", 0), ("lidar", 5), ("fusion", 0)])
def test_lanegap_shapes_loss_and_gradients(modality, bezier_points):
    torch.manual_seed(0)
    config = resolve_config("tiny")
    config.encoder.modality = modality
    config.decoder.bezier_points = bezier_points
    model = LaneGAP(config)
    batch = random_batch()
    outputs = model(batch)
    layers, paths, n = config.decoder.layers, config.decoder.num_paths, config.decoder.path_points
    assert outputs["logits"].shape == (layers, 2, paths)
    assert outputs["points"].shape == (layers, 2, paths, n, 2)
    assert outputs["seg"].shape == (2, 2, config.encoder.bev_h, config.encoder.bev_w)
    # points may reach MARGIN beyond the map, so that a path can end on the crop's edge
    assert -MARGIN <= outputs["points"].min() and outputs["points"].max() <= 1 + MARGIN
    targets = [torch.rand(3, n, 2), torch.zeros(0, n, 2)]
    seg = torch.randint(0, 2, (2, config.encoder.bev_h, config.encoder.bev_w))
    # the prepared 0.15 m rasters, for the fine BEV level's loss (0.6 m cells: 1.5 m / fine_scale 2.5)
    raster_mask = torch.randint(0, 2, (2, 400, 200), dtype=torch.uint8)
    raster_direction = raster_mask * torch.randint(1, 37, (2, 400, 200), dtype=torch.uint8)
    assert outputs["fine"].shape == (2, 4, 100, 50)
    losses = LaneGAPLoss(config.decoder)(outputs, Targets(targets, seg, raster_mask, raster_direction))
    assert set(losses) == {
        "loss",
        "cls",
        "points",
        "seg",
        "fine_seg",
        "fine_direction",
        "lane_seg",
        "lane_direction",
    }
    assert torch.isfinite(losses["loss"])
    losses["loss"].backward()
    first = model.encoder.camera.backbone.conv1 if modality != "lidar" else model.encoder.lidar.point_net[0]
    assert first.weight.grad is not None and first.weight.grad.abs().sum() > 0
    model.eval()
    with torch.no_grad():
        outputs = model(batch)
    assert "seg" not in outputs and "fine" not in outputs  # the auxiliary heads are off at inference
    assert outputs["lane_seg"].shape == (2, 2, 200, 100)  # the lane head's 0.3 m cells: snapping reads it
    selected = select_paths(outputs, threshold=0.0)
    assert len(selected) == 2 and selected[0][1].shape == (paths, n, 2)
    assert torch.all(selected[0][0][:-1] >= selected[0][0][1:])


def test_camera_encoder_reads_the_camera_that_sees_a_cell():
    # A BEV cell straight ahead must depend on the front camera's image and not on the rear one's.
    torch.manual_seed(0)
    config = resolve_config("tiny")
    config.encoder.camera_layers = 1
    model = LaneGAP(config).eval()
    batch = random_batch(batch=1)
    batch.images.requires_grad_(True)
    bev = model.encoder(batch)
    row, col = config.encoder.bev_h // 4, config.encoder.bev_w // 2  # 15 m ahead
    # A random read-out: a plain sum over channels is constant after the final LayerNorm.
    (bev[0, :, row, col] * torch.randn(bev.shape[1])).sum().backward()
    per_camera = batch.images.grad.abs().sum(dim=(0, 2, 3, 4))
    assert per_camera[0] > 0 and per_camera[3] == 0  # camera 0 looks at +y, camera 3 backwards


def test_config_overrides_and_round_trip(tmp_path):
    config = apply_overrides(
        resolve_config("tiny"),
        ["train.lr=3e-4", "encoder.kernel_size=5,5", "decoder.aux_seg=false", "encoder.modality=lidar"],
    )
    assert config.train.lr == 3e-4 and config.encoder.kernel_size == (5, 5)
    assert config.decoder.aux_seg is False and config.encoder.modality == "lidar"
    config.save(tmp_path / "config.json")
    assert load_config(tmp_path / "config.json") == config
    with pytest.raises(ValueError):
        apply_overrides(config, ["train.nope=1"])


@pytest.mark.parametrize("modality", ["camera", "lidar", "fusion"])
def test_gflops_are_counted_for_every_modality(modality):
    """`cli eval`'s FLOP count runs on every encoder (the camera branch once broke torch's counter);
    fusion costs the sum of its branches plus the fuser, so it counts more than either."""
    from baselines.evaluate import count_gflops

    counts = {}
    for name in ("camera", "lidar", modality):
        config = apply_overrides(resolve_config("tiny"), [f"encoder.modality={name}"])
        torch.manual_seed(0)
        counts[name] = count_gflops(LaneGAP(config).eval(), random_batch(batch=1))
    assert counts["camera"] > 0.01 and counts["lidar"] > 0.01
    if modality == "fusion":
        assert counts["fusion"] > max(counts["camera"], counts["lidar"])
