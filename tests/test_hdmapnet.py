"""HDMapNet (baselines/models/hdmapnet.py): forward / backward, overfitting, its direction targets, and
its post-processing fed with the ground truth, which must score what `cli roundtrip --via pixel` does."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from baselines.config import tiny
from baselines.layers.bev_encoder import SensorBatch
from baselines.layers.raster_targets import direction_targets, pooled_targets
from baselines.layers.targets import Targets
from baselines.models import MODELS, resolve_config
from baselines.models.hdmapnet import (
    HDMapNetConfig,
    PostProcess,
    build,
    head,
    paper_head,
    tiny_head,
)
from benchmark.graph_table import default_range, graphs_from_table
from benchmark.metric.params import MetricParams
from benchmark.roundtrip import rebuild, roundtrip
from benchmark.score import score_pairs
from pipeline.geometry import Range
from pipeline.io import decode_raster, read_table
from pipeline.lane_graph import LaneGraph
from pipeline.raster import Grid, rasterize

torch.set_num_threads(1)

RANGE = Range(-3.0, 3.0, -6.0, 6.0)  # a small crop: an 80 x 40 raster keeps the tests fast


def small_config(width: int = 8):
    config = tiny()
    config.model = "hdmapnet"
    config.encoder.modality = "lidar"  # the cheapest encoder
    config.encoder.x_range, config.encoder.y_range = (RANGE.x_min, RANGE.x_max), (RANGE.y_min, RANGE.y_max)
    config.encoder.bev_h, config.encoder.bev_w = 8, 4
    config.decoder = HDMapNetConfig(width=width)
    return config


def lanes(forward: bool) -> LaneGraph:
    """A straight lane at x = -1.5 and a lane at x = 1.5 that bends left and merges into it near the
    front; driving forward (+y) or all reversed."""
    x = np.array([-1.5, -1.5, -1.5, 1.5, 1.5, 0.0], np.float32)
    y = np.array([-6.0, 0.0, 6.0, -6.0, -2.0, 1.5], np.float32)
    src, dst = np.array([0, 1, 3, 4, 5], np.int32), np.array([1, 2, 4, 5, 1], np.int32)
    return LaneGraph(x, y, src, dst) if forward else LaneGraph(x, y, dst, src)


def synthetic_batch() -> tuple[SensorBatch, Targets]:
    generator = torch.Generator().manual_seed(0)
    points = torch.rand(2, 300, 4, generator=generator) * torch.tensor([6.0, 12.0, 2.0, 1.0])
    points[..., :2] -= torch.tensor([3.0, 6.0])
    sensors = SensorBatch(points=points, points_mask=torch.ones(2, 300, dtype=torch.bool))
    rasters = [rasterize(lanes(forward), Grid(RANGE)) for forward in (True, False)]
    mask, direction = (torch.from_numpy(np.stack(r)) for r in zip(*rasters))
    return sensors, Targets([], torch.zeros(2, 8, 4, dtype=torch.int64), mask, direction)


def test_forward_backward_on_the_raster_grid():
    torch.manual_seed(0)
    built = build(small_config())
    assert built.needs == {"raster"} and built.modeling == "pixel"
    sensors, targets = synthetic_batch()
    outputs = built.model(sensors)
    assert outputs["seg"].shape == (2, 2, 80, 40) and outputs["direction"].shape == (2, 2, 80, 40)
    losses = built.loss(outputs, targets)
    assert set(losses) == {"loss", "seg", "direction"}
    assert all(torch.isfinite(v) for v in losses.values())
    assert losses["seg"] > 0.1 and losses["direction"] > 0.1
    losses["loss"].backward()
    for module in (built.model.encoder, built.model.conv1, built.model.direction_branch):
        grads = [p.grad for p in module.parameters()]
        assert all(g is not None and torch.isfinite(g).all() for g in grads)
        assert any(g.abs().sum() > 0 for g in grads)


def test_backward_from_a_channels_last_bev_map():
    # The LiDAR encoder returns a channels-last map; the head's backward on one crashed torch on CPU.
    torch.manual_seed(0)
    config = tiny()
    config.model, config.encoder.modality, config.decoder = "hdmapnet", "lidar", tiny_head()
    model = build(config).model  # the real sizes: the crash needs them (40 x 20 -> 400 x 200)
    bev = torch.randn(2, 64, 40, 20).contiguous(memory_format=torch.channels_last).requires_grad_()
    outputs = model.decode(bev)
    (outputs["seg"].square().sum() + outputs["direction"].square().sum()).backward()
    assert torch.isfinite(bev.grad).all() and bev.grad.abs().sum() > 0


def test_loss_halves_when_overfitting_one_batch(overfit):
    torch.manual_seed(0)
    history = overfit(build(small_config()), *synthetic_batch(), steps=30)
    assert history[-1]["loss"] < 0.5 * history[0]["loss"]
    assert history[-1]["direction"] < 0.5 * history[0]["direction"]


def test_direction_targets_decode_back_to_the_prepared_bins():
    # An ellipse driven counter-clockwise passes through (nearly) every one of the 36 bins.
    angle = np.linspace(0, 2 * np.pi, 73)[:-1]
    n = len(angle)
    circle = LaneGraph((2.5 * np.cos(angle)).astype(np.float32), (5 * np.sin(angle)).astype(np.float32),
                       np.arange(n, dtype=np.int32), ((np.arange(n) + 1) % n).astype(np.int32))  # fmt: skip
    grid = Grid(RANGE)
    mask, bins = rasterize(circle, grid)
    assert len(np.unique(bins)) > 30
    vectors = direction_targets(torch.from_numpy(bins)[None])[0].numpy()
    lane = mask > 0
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=0)[lane], 1.0, rtol=1e-6)
    assert not vectors[:, ~lane].any()
    assert np.array_equal(grid.direction_bin(vectors[0], vectors[1])[lane], bins[lane])
    # The rows trap: the forward lane of `lanes` (bottom rows to top rows) points +y, sin > 0.
    mask, bins = rasterize(lanes(forward=True), grid)
    vectors = direction_targets(torch.from_numpy(bins)[None])[0].numpy()
    column = round((-1.5 - RANGE.x_min) / grid.resolution)
    rows = slice(8, 25)  # y from 4.8 to 2.25 m: in front of the merge, where only this lane is drawn
    assert np.allclose(vectors[:, rows, column], [[np.cos(np.radians(95))], [np.sin(np.radians(95))]])


def oracle_outputs(masks: np.ndarray, bins: np.ndarray) -> dict[str, torch.Tensor]:
    """Outputs that are the ground truth: certain logits, the exact direction of each bin."""
    lane = torch.from_numpy(masks > 0)
    seg = torch.stack([torch.zeros(lane.shape), torch.where(lane, 20.0, -20.0)], 1)
    return {"seg": seg, "direction": direction_targets(torch.from_numpy(bins))}


def test_oracle_outputs_have_no_direction_loss_and_rebuild_the_lanes():
    config = small_config()
    built = build(config)
    _, targets = synthetic_batch()
    outputs = oracle_outputs(targets.raster_mask.numpy(), targets.raster_direction.numpy())
    losses = built.loss(outputs, targets)
    assert losses["direction"] == 0 and losses["seg"] < 1e-6
    graphs = built.to_graphs(outputs)
    assert len(graphs) == 2
    for graph, forward in zip(graphs, (True, False)):
        assert graph.src.dtype == np.int32 and graph.dst.dtype == np.int32 and len(graph.x) == len(graph.y)
        assert len(graph.src) > 0 and graph.src.max() < len(graph.x) and graph.dst.max() < len(graph.x)
        assert (graph.src != graph.dst).all()
        assert RANGE.x_min <= graph.x.min() and graph.x.max() <= RANGE.x_max
        assert RANGE.y_min <= graph.y.min() and graph.y.max() <= RANGE.y_max
        # the straight lane at x = -1.5 keeps its driving direction (from the merge to the front)
        ahead = (np.abs(graph.x + 1.5) < 0.3) & (graph.y > 0.5)
        on_lane = ahead[graph.src] & ahead[graph.dst]
        dy = graph.y[graph.dst] - graph.y[graph.src]
        assert on_lane.sum() > 0 and ((dy[on_lane] > 0) == forward).all()


def test_untrained_outputs_give_valid_graphs():
    torch.manual_seed(0)
    config = small_config()
    model = build(config).model.eval()
    sensors, _ = synthetic_batch()
    with torch.no_grad():
        outputs = model(sensors)
    # the median lane probability as the threshold: half the cells are lane, noise for Pixel2Graph
    config.decoder.score_threshold = float(outputs["seg"].softmax(1)[:, 1].median())
    graphs = PostProcess(config)(outputs)
    assert len(graphs) == 2 and all(len(g.src) > 0 for g in graphs)
    for graph in graphs:
        assert len(graph.src) == len(graph.dst) and len(graph.x) == len(graph.y)
        assert max(graph.src.max(), graph.dst.max()) < len(graph.x) and (graph.src != graph.dst).all()
        assert RANGE.x_min <= graph.x.min() and graph.x.max() <= RANGE.x_max


@pytest.mark.parametrize("dataset", ["nuscenes", "av2"])
def test_oracle_through_to_graphs_scores_the_pixel_roundtrip(synth_prepared, dataset):
    data, stride = synth_prepared[dataset], 4
    config = tiny()
    config.model, config.decoder = "hdmapnet", tiny_head()
    config.decoder.resolution = 0.15  # the round trip's: the prepared rasters' own cells
    crop = Range.parse(default_range(data))
    config.encoder.x_range, config.encoder.y_range = (crop.x_min, crop.x_max), (crop.y_min, crop.y_max)
    post = build(config).to_graphs
    gt = graphs_from_table(read_table(data, "graphs"), data / "graphs")
    frame_ids = sorted(gt)[::stride]
    rasters = {row["frame_id"]: decode_raster(row) for row in read_table(data, "rasters").to_pylist()}
    graphs = []
    for start in range(0, len(frame_ids), 4):  # batches of 4 frames
        masks, bins = (np.stack(a) for a in zip(*(rasters[f] for f in frame_ids[start : start + 4])))
        graphs += post(oracle_outputs(masks, bins))
    # the same graphs as the round trip's Pixel2Graph on the prepared rasters ...
    expected = rebuild(data, "pixel", frame_ids, 0.0)
    for frame_id, graph in zip(frame_ids, graphs, strict=True):
        for name in ("x", "y", "src", "dst"):
            assert np.array_equal(getattr(graph, name), getattr(expected[frame_id], name)), frame_id
    # ... and so the same scores as `cli roundtrip --via pixel`
    params = MetricParams(bev_range=default_range(data))
    result = score_pairs([(g, gt[f]) for g, f in zip(graphs, frame_ids)], params)
    reference = roundtrip(data, "pixel", frame_stride=stride)
    assert result == {k: v for k, v in reference.items() if k not in ("data", "via")}
    assert 0.5 < result["directed"]["topo"]["f1"] < 1


def test_head_sizes_are_lanegap_sized():
    # with the camera encoder, within 5 % of LaneGAP's parameters (its fine BEV level included in tiny)
    for preset in ("tiny", "paper"):
        configs = (resolve_config(preset, modality="camera", model=m) for m in ("lanegap", "hdmapnet"))
        lanegap, hdmapnet = (sum(p.numel() for p in MODELS[c.model](c).model.parameters()) for c in configs)
        assert abs(hdmapnet / lanegap - 1) < 0.05, (preset, hdmapnet, lanegap)
    assert head("tiny") == tiny_head() and head("paper") == paper_head() != tiny_head()
    with pytest.raises(ValueError, match="no head size for preset 'huge'"):
        head("huge")


def test_pooled_targets_keep_the_lanes_and_their_directions():
    # 0.3 m outputs (the tiny head) on 0.15 m rasters: every 2 x 2 block with a lane cell is lane, and
    # its direction is the lanes' own (both lanes of `lanes` are straight where they do not bend).
    mask, direction = (torch.from_numpy(a)[None] for a in rasterize(lanes(True), Grid(RANGE)))
    lane, vectors = pooled_targets(mask, direction, (40, 20))
    assert lane.shape == (1, 40, 20) and vectors.shape == (1, 2, 40, 20)
    expected = F.max_pool2d(mask[:, None].float(), 2)[:, 0].long()
    assert torch.equal(lane, expected) and lane.sum() > 20
    norms = vectors.norm(dim=1)[lane > 0]
    assert torch.allclose(norms, torch.ones_like(norms), atol=1e-5)
    assert torch.all(vectors.norm(dim=1)[lane == 0] == 0)
    # the straight lane at x = -1.5 (column 3 at 0.3 m) drives forward (+y) from y = -6 to 0
    assert torch.allclose(vectors[0, :, 22:38, 5], torch.tensor([[0.0], [1.0]]).expand(2, 16), atol=0.09)
    with pytest.raises(ValueError, match="whole multiple"):
        pooled_targets(mask, direction, (30, 15))
    # a range of no whole number of output cells (50 x 100 m: 667 x 333 rasters, 334 x 167 outputs):
    # the last row and column reach past it, with no lane
    cut, _ = pooled_targets(mask[:, :79, :39], direction[:, :79, :39], (40, 20))
    padded = F.pad(mask[:, None, :79, :39].float(), (0, 1, 0, 1))
    assert cut.shape == (1, 40, 20) and torch.equal(cut, F.max_pool2d(padded, 2)[:, 0].long())
