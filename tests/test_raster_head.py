"""The query models' lane head (baselines/layers/raster_head.py): HDMapNet's head under its own names, and the
snapping of regressed points onto the lane centres of a lane-probability raster."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from baselines.data import PreparedDataset, collate
from baselines.layers.raster_head import lane_head_losses, raster_shape, snap_polylines
from baselines.models import build, resolve_config
from pipeline.geometry import Range
from pipeline.lane_graph import LaneGraph
from pipeline.manifest import PreparedData
from pipeline.raster import Grid, rasterize


def lane_raster(lanes: list[np.ndarray], encoder, resolution: float = 0.3) -> np.ndarray:
    """A lane probability of 1 on the prepared raster's 0.75 m lines along `lanes`, pooled to
    `resolution` m cells as the lane head's targets (any lane cell inside), 0 elsewhere."""
    (x0, x1), (y0, y1) = encoder.x_range, encoder.y_range
    xy = np.concatenate(lanes)
    ends = np.cumsum([len(lane) for lane in lanes])
    src = np.concatenate([np.arange(s, e - 1) for s, e in zip(np.r_[0, ends[:-1]], ends)])
    graph = LaneGraph(xy[:, 0].astype(np.float32), xy[:, 1].astype(np.float32), src.astype(np.int32),
                      (src + 1).astype(np.int32))  # fmt: skip
    mask, _ = rasterize(graph, Grid(Range(x0, x1, y0, y1)))
    rows, cols = raster_shape(encoder, resolution)
    k = round(resolution / 0.15)
    padded = np.zeros((rows * k, cols * k))
    padded[: mask.shape[0], : mask.shape[1]] = mask
    return padded.reshape(rows, k, cols, k).max(axis=(1, 3))


def straight(x: float, y0: float = -20.0, y1: float = 20.0, n: int = 20) -> np.ndarray:
    return np.column_stack([np.full(n, x), np.linspace(y0, y1, n)])


@pytest.fixture
def encoder():
    return resolve_config("tiny", model="maptr").encoder


def test_points_move_onto_the_nearest_lane_centre(encoder):
    lanes = [straight(-3.5), straight(0.2), straight(3.9)]
    probability = lane_raster(lanes, encoder)
    # predicted 0.4-0.9 m beside each lane, on either side
    predicted = [straight(-3.5 + 0.7), straight(0.2 - 0.9), straight(3.9 + 0.4)]
    snapped = snap_polylines(predicted, probability, encoder, radius=1.0)
    for lane, before, after in zip(lanes, predicted, snapped, strict=True):
        assert np.abs(before[:, 0] - lane[:, 0]).min() > 0.35
        assert np.abs(after[:, 0] - lane[:, 0]).max() < 0.16, after[:, 0]  # half a 0.3 m cell
        assert np.allclose(after[:, 1], before[:, 1])  # across the polyline only


def test_an_oblique_curve_snaps_across_itself(encoder):
    angle = np.linspace(0, np.pi / 3, 40)
    lane = np.column_stack([-12 + 25 * (1 - np.cos(angle)), -20 + 25 * np.sin(angle)])
    probability = lane_raster([lane], encoder)
    predicted = lane * 1.0 + 0.6 * np.column_stack([np.cos(angle), -np.sin(angle)])  # 0.6 m outwards
    (snapped,) = snap_polylines([predicted], probability, encoder, radius=1.0)
    inside = (np.abs(snapped[:, 0]) < 14) & (np.abs(snapped[:, 1]) < 29)
    dense = np.linspace(0, 1, 400)[:, None]
    segments = np.concatenate([a + dense * (b - a) for a, b in zip(lane[:-1], lane[1:])])
    distance = np.linalg.norm(snapped[inside, None] - segments[None], axis=-1).min(1)
    assert inside.sum() > 20 and distance.max() < 0.16, distance.max()


def test_snapped_points_stay_inside_the_map(encoder):
    (x0, x1), (y0, y1) = encoder.x_range, encoder.y_range
    lanes = [straight(x1 - 0.1), np.column_stack([np.linspace(-10, 10, 20), np.full(20, y1 - 0.1)])]
    probability = lane_raster(lanes, encoder)
    predicted = [straight(x1 - 0.5), np.column_stack([np.linspace(-10, 10, 20), np.full(20, y1 - 0.6)])]
    snapped = np.concatenate(snap_polylines(predicted, probability, encoder, radius=1.0))
    assert np.all((snapped >= [x0, y0]) & (snapped <= [x1, y1]))
    assert np.abs(snapped[:20, 0] - (x1 - 0.1)).max() < 0.2  # moved to the lane at the map's edge


def test_points_without_a_lane_near_them_stay(encoder):
    probability = lane_raster([straight(0.0)], encoder)
    far = [straight(2.5)]  # the lane is 2.5 m away: beyond the radius
    assert np.array_equal(snap_polylines(far, probability, encoder, radius=1.0)[0], far[0])
    faint = [straight(0.6)]
    assert np.array_equal(snap_polylines(faint, probability * 0.2, encoder, radius=1.0)[0], faint[0])
    assert snap_polylines(faint, probability, encoder, radius=0.0) is faint
    single = [np.array([[0.6, 3.0]])]  # no direction to snap across
    assert np.array_equal(snap_polylines(single, probability, encoder, radius=1.0)[0], single[0])


def test_the_prepared_raster_moves_perturbed_paths_back_onto_their_lanes(synth_prepared):
    """The ground-truth paths of synth frames, shifted 0.6 m sideways, snap back onto the lanes of the
    prepared raster pooled to the lane head's cells."""
    config = resolve_config("tiny", modality="lidar", model="lanegap")
    needs = frozenset({"paths", "raster"})
    data = PreparedDataset(PreparedData.open(synth_prepared["av2"]), "train", config, needs)
    rows, cols = raster_shape(config.encoder, 0.3)
    errors_before, errors_after = [], []
    for index in range(0, len(data), 9):
        sample = data[index]
        mask = sample.raster[0]
        padded = np.zeros((rows * 2, cols * 2))
        padded[: mask.shape[0], : mask.shape[1]] = mask
        probability = padded.reshape(rows, 2, cols, 2).max(axis=(1, 3))
        paths = [config.encoder.unit_to_metres(p.astype(np.float64)) for p in sample.paths]
        shifted = []
        for path in paths:
            tangent = np.gradient(path, axis=0)
            normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
            shifted.append(
                path + 0.6 * normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)
            )
        snapped = snap_polylines(shifted, probability, config.encoder, radius=1.0)
        for path, before, after in zip(paths, shifted, snapped, strict=True):
            errors_before.append(np.linalg.norm(before - path, axis=1))
            errors_after.append(np.linalg.norm(after - path, axis=1))
    before, after = np.concatenate(errors_before), np.concatenate(errors_after)
    assert np.median(before) == pytest.approx(0.6, abs=0.01)
    assert np.median(after) < 0.16 and np.mean(after < 0.45) > 0.9, (np.median(after), np.mean(after < 0.45))


@pytest.mark.parametrize("model", ["lanegap", "maptr", "stsu"])
def test_query_models_train_their_lane_head_and_snap_with_it(synth_prepared, model):
    config = resolve_config("tiny", modality="lidar", model=model)
    built = build(config)
    assert "raster" in built.needs
    data = PreparedDataset(PreparedData.open(synth_prepared["av2"]), "train", config, built.needs)
    batch = collate([data[0], data[1]])
    outputs = built.model(batch.sensors)
    rows, cols = raster_shape(config.encoder, config.decoder.lane_head_resolution)
    assert outputs["lane_seg"].shape == (2, 2, rows, cols)
    losses = built.loss(outputs, batch.targets)
    assert {"lane_seg", "lane_direction"} <= set(losses)
    # the lane head trains itself only: its loss leaves the encoder's gradients at none
    lane = lane_head_losses(outputs, batch.targets)
    (lane["lane_seg"] + lane["lane_direction"]).backward()
    assert built.model.lane_head.conv1.weight.grad.abs().sum() > 0
    assert all(p.grad is None for p in built.model.encoder.parameters())
    built.model.eval()
    with torch.no_grad():
        assert "lane_seg" in built.model(batch.sensors)  # the post-processing reads it
    config.decoder.lane_head_width = 0
    assert build(config).model.lane_head is None
