"""The prepared lane raster as dense BEV targets, and the losses against them: a lane mask (2-class
cross-entropy) and the unit tangent (cos, sin) of the travel direction (L2 on the lane cells, "the (-1, 1)
normalized direction map" of LaneGAP's appendix). HDMapNet's two branches train on them, and so does the
fine BEV level of the query decoders (baselines/layers/fine_bev.py).

The direction is in the BEV frame (x right, y forward), not in image coordinates, where rows run down and
so flip the sign of the y component.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from baselines.layers.blocks import constant, mean_over_processes
from pipeline.raster import direction_vectors


def direction_targets(bins: torch.Tensor, direction_bins: int = 36) -> torch.Tensor:
    """Direction bins (B, H, W) -> (B, 2, H, W) unit (cos, sin) of each bin's centre angle in the BEV
    frame; zero where there is no lane (bin 0)."""
    vectors = constant(direction_vectors(direction_bins).tolist(), bins.device)
    return vectors[bins.long()].permute(0, 3, 1, 2)


def pooled_targets(
    mask: torch.Tensor, bins: torch.Tensor, size: tuple[int, int], direction_bins: int = 36,
    adaptive: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """The prepared raster (B, H, W) on an output grid `size` whose cells hold k x k raster cells:
    (lane mask (B, h, w) long: any lane cell inside, unit direction (B, 2, h, w): the mean of the lane
    cells' directions, zero off the lanes). adaptive: any grid over the same range, each cell pooling the
    raster cells it overlaps (the fine BEV level follows the BEV grid, whose cells need not be a whole
    number of raster cells: 33 columns over 50 m)."""
    if adaptive:
        lane = F.adaptive_max_pool2d(mask[:, None].float(), size)[:, 0].long()
        mean = F.adaptive_avg_pool2d(direction_targets(bins, direction_bins), size)
        return lane, mean / mean.norm(dim=1, keepdim=True).clamp(min=1e-6) * lane[:, None]
    rows, cols = mask.shape[-2:]
    k = -(-rows // size[0])
    pad_rows, pad_cols = k * size[0] - rows, k * size[1] - cols
    if not (0 <= pad_rows < k and 0 <= pad_cols < k):
        raise ValueError(
            f"the prepared rasters are {rows} x {cols} cells, not a whole multiple of the model's output "
            f"{size[0]} x {size[1]}: the output cells must be the rasters' or a whole multiple of them"
        )
    # a range that is not a whole number of output cells: the last ones reach past it, with no lane
    mask, bins = (F.pad(t, (0, pad_cols, 0, pad_rows)) for t in (mask, bins))
    vectors = direction_targets(bins, direction_bins)
    if k == 1:
        return mask.long(), vectors
    lane = F.max_pool2d(mask[:, None].float(), k)[:, 0].long()
    mean = F.avg_pool2d(vectors, k)
    return lane, mean / mean.norm(dim=1, keepdim=True).clamp(min=1e-6) * lane[:, None]


def raster_losses(
    seg: torch.Tensor, direction: torch.Tensor, mask: torch.Tensor, bins: torch.Tensor,
    lane_class_weight: float = 1.0, direction_bins: int = 36, adaptive: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """Lane logits (B, 2, h, w) and (cos, sin) (B, 2, h, w) against the prepared raster (B, H, W) pooled
    to their grid (`pooled_targets`) -> (cross-entropy of the logits, squared error of the direction
    averaged over the lane cells)."""
    lane, target = pooled_targets(mask, bins, tuple(seg.shape[-2:]), direction_bins, adaptive)
    logits = seg.float()
    class_weight = constant([1.0, lane_class_weight], logits.device)
    on_lane = (target.abs().sum(1, keepdim=True) > 0).float()
    # Both normalised by their counts over all processes, so that DDP trains as one process would.
    weights, lane_cells = mean_over_processes(torch.stack([class_weight[lane].sum(), on_lane.sum()]))
    seg_loss = F.cross_entropy(logits, lane, weight=class_weight, reduction="sum") / weights.clamp(min=1.0)
    error = (direction.float() - target) ** 2
    return seg_loss, (error * on_lane).sum() / lane_cells.clamp(min=1.0)
