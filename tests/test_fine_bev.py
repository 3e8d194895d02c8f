"""The query decoders' fine BEV level (baselines/layers/fine_bev.py): its shapes, its loss against the
prepared raster, and that the decoder reads it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from baselines.layers.fine_bev import FineBEV, fine_losses
from baselines.layers.query_decoder import QueryDecoder
from baselines.layers.raster_targets import pooled_targets
from baselines.layers.targets import Targets
from pipeline.geometry import Range
from pipeline.lane_graph import LaneGraph
from pipeline.raster import Grid, rasterize


def two_lanes() -> tuple[torch.Tensor, torch.Tensor]:
    """The prepared raster (1, 80, 40) of a 6 x 12 m crop: a lane driving +y at x = -1.5, one driving -y
    at x = 1.5."""
    graph = LaneGraph(
        np.array([-1.5, -1.5, 1.5, 1.5], np.float32), np.array([-6.0, 6.0, 6.0, -6.0], np.float32),
        np.array([0, 2], np.int32), np.array([1, 3], np.int32),
    )  # fmt: skip
    mask, bins = rasterize(graph, Grid(Range(-3.0, 3.0, -6.0, 6.0)))
    return torch.from_numpy(mask)[None], torch.from_numpy(bins)[None]


def test_fine_level_shapes_and_its_auxiliary_outputs_in_training_only():
    torch.manual_seed(0)
    fine = FineBEV(8, 5)
    level, aux = fine(torch.randn(2, 8, 4, 2))
    assert level.shape == (2, 8, 20, 10) and aux.shape == (2, 4, 20, 10)
    level, aux = fine.eval()(torch.randn(2, 8, 4, 2))
    assert level.shape == (2, 8, 20, 10) and aux is None


def test_fine_losses_vanish_on_the_raster_itself_and_grow_against_it():
    mask, bins = two_lanes()
    lane, direction = pooled_targets(mask, bins, (40, 20))  # 0.3 m cells: the tiny preset's fine level
    perfect = torch.cat([torch.stack([torch.zeros_like(lane), 20.0 * (2 * lane - 1)], 1), direction], 1)
    targets = Targets([], torch.zeros(1, 8, 4, dtype=torch.int64), mask, bins)
    losses = fine_losses(perfect.float(), targets)
    assert losses["fine_seg"] < 1e-6 and losses["fine_direction"] < 1e-10
    # +y on the left lane, -y on the right one (the bins' centres: 95 and 275 degrees)
    assert direction[0, 1, 20, 5] > 0.99 and direction[0, 1, 20, 15] < -0.99
    reversed_lanes = torch.cat([perfect[:, :2], -direction], 1)
    assert fine_losses(reversed_lanes, targets)["fine_direction"] == pytest.approx(4.0)
    no_lanes = torch.cat([-perfect[:, :2], direction], 1)
    assert fine_losses(no_lanes, targets)["fine_seg"] > 10
    with pytest.raises(ValueError, match="must need 'raster'"):
        fine_losses(perfect, Targets([], targets.seg))


def test_decoder_reads_the_fine_level():
    torch.manual_seed(0)
    decoder = QueryDecoder(16, 4, 5, 0, 2, 4, 32, 0.0, 2, fine_scale=5)
    bev = torch.randn(2, 16, 4, 2)
    outputs = decoder(bev)
    assert outputs["fine"].shape == (2, 4, 20, 10) and outputs["points"].shape == (2, 2, 4, 5, 2)
    # the scores alone (the point heads start at zero): their gradient reaches the fine level through the
    # deformable attention
    outputs["logits"].sum().backward()
    assert decoder.fine.level.weight.grad.abs().sum() > 0
    assert "fine" not in decoder.eval()(bev)


def test_adaptive_pooling_is_the_exact_one_on_whole_multiples_and_takes_any_grid():
    mask, bins = two_lanes()  # 80 x 40 raster cells
    for size in ((40, 20), (20, 10)):
        exact, adaptive = pooled_targets(mask, bins, size), pooled_targets(mask, bins, size, adaptive=True)
        assert torch.equal(exact[0], adaptive[0]) and torch.allclose(exact[1], adaptive[1], atol=1e-6)
    # a BEV grid whose cells are no whole number of raster cells (as 33 columns over 50 m)
    lane, direction = pooled_targets(mask, bins, (33, 17), adaptive=True)
    assert lane.shape == (1, 33, 17) and lane[0, :, 4].all() and not lane[0, :, 8].any()
    assert torch.allclose(direction[0, 1, :, 4], torch.tensor(0.9962), atol=1e-3)
