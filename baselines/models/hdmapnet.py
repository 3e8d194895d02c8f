"""HDMapNet (Li et al.), the pixel-wise baseline: the model, its loss and its post-processing, which
`build()` returns together.

The model: the shared BEV encoder, its features upsampled (bilinear) to the raster grid of the prepared
targets (0.15 m cells: 400 x 200 for 60 x 30 m), then HDMapNet's `BevEncode` head: a ResNet-18 stem
and layer1-3, and per branch an `Up` block (x4, concatenated with the layer1 skip) and a x2 upsampling
to the raster size. Two branches: lane segmentation (2 classes) and direction, the unit tangent
(cos, sin) of the travel direction regressed as LaneExtraction does ("L2 loss on the (-1, 1) normalized
direction map", LaneGAP's appendix) instead of HDMapNet's 37-way classification.
The loss: cross-entropy on the prepared lane raster, L2 on the direction at lane pixels.
The post-processing: the thresholded mask and the predicted directions through Pixel2Graph.

Conventions (docs/guide/prepare.md): outputs are on the raster grid itself, row 0 the front edge (y max),
column 0 the left edge (x min). HDMapNet's own canvas is transposed to this one (x forward along its
columns); nothing here uses it. The direction (cos, sin) is in the BEV frame (x right, y forward), not
in image coordinates, where rows run down and so flip the sign of the y component.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np
import torch
from torch import nn

from baselines.config import AT_LEAST_0, AT_LEAST_1, POSITIVE, PROBABILITY, Config, EncoderConfig
from baselines.layers.bev_encoder import BEVEncoder, SensorBatch
from baselines.layers.raster_head import RasterHead, raster_shape
from baselines.layers.raster_targets import raster_losses
from baselines.layers.targets import Targets
from baselines.models.base import Built, preset_head
from benchmark.graphs.pixel2graph import pixel2graph
from pipeline.geometry import Range
from pipeline.lane_graph import LaneGraph
from pipeline.raster import Grid


@dataclass
class HDMapNetConfig:
    """The BevEncode head and its loss. `width` is its ResNet-18 width: layer1-3 have width, 2 x width and
    4 x width channels, an `Up` block 4 x width and the last convolution 2 x width (HDMapNet: 64)."""

    width: Annotated[int, AT_LEAST_1] = 64
    # metres per output cell: the prepared rasters' (0.15), or a whole multiple of it, whose targets are
    # the rasters pooled (the tiny preset's 0.3 m: a quarter of the cost, as its coarser BEV grid)
    resolution: Annotated[float, POSITIVE] = 0.15
    # the prepared rasters' bins, to hand Pixel2Graph the predicted direction
    direction_bins: Annotated[int, AT_LEAST_1] = 36
    seg_weight: Annotated[float, AT_LEAST_0] = 1.0
    direction_weight: Annotated[float, AT_LEAST_0] = 1.0
    # cross-entropy weight of the lane class (HDMapNet's BCE: 2.13)
    lane_class_weight: Annotated[float, AT_LEAST_0] = 1.0
    score_threshold: Annotated[float, PROBABILITY] = 0.5  # lane probability above which a cell is lane

    def problem(self, encoder: EncoderConfig) -> str | None:
        """None: the convolutional head takes any encoder width (Config.check_across)."""
        return None


# Head sizes for a fair comparison: with the same encoder (camera), as many parameters as LaneGAP
# within 5 % (LaneGAP: 37,976,700 paper, 1,401,243 tiny with its fine BEV level and its lane head).


def paper_head() -> HDMapNetConfig:
    """HDMapNet's own widths: 37,291,252 parameters with the paper encoder (camera); the gpu preset's too,
    as the CPU checks needed no other setting of it but the tiny size (docs/EXPERIMENTS.md, 2026-12-06)."""
    return HDMapNetConfig(width=64)


def tiny_head() -> HDMapNetConfig:
    """1,386,496 parameters with the tiny encoder (camera): width 18, LaneGAP's size since the query
    models carry a width-12 head of this kind (baselines/layers/raster_head.py). Output cells of 0.3 m
    (200 x 100 for 30 x 60 m): a quarter of the cost of the prepared rasters' 0.15 m, for a small loss in the
    ground truth's round trip through Pixel2Graph (docs/EXPERIMENTS.md)."""
    return HDMapNetConfig(width=18, resolution=0.3)


def head(preset: str) -> HDMapNetConfig:
    """HDMapNet's head config of a preset (`baselines.models.HEADS`)."""
    return preset_head("HDMapNet", {"paper": paper_head, "tiny": tiny_head, "gpu": paper_head}, preset)


class HDMapNet(RasterHead):
    """Sensors -> "seg": lane logits (B, 2, H, W) and "direction": (cos, sin) (B, 2, H, W), on the
    raster grid (H x W cells of config.decoder.resolution): BevEncode (baselines/layers/raster_head.py) on the
    shared encoder."""

    def __init__(self, config: Config):
        super().__init__(config.encoder.channels, config.decoder.width,
                         raster_shape(config.encoder, config.decoder.resolution))  # fmt: skip
        self.encoder = BEVEncoder(config.encoder)

    def forward(self, batch: SensorBatch) -> dict[str, torch.Tensor]:
        return self.decode(self.encoder(batch))


class HDMapNetLoss(nn.Module):
    """Cross-entropy of the lane logits against the prepared raster, plus the squared error of the
    (cos, sin) direction averaged over the lane pixels."""

    def __init__(self, config: Config):
        super().__init__()
        self.config = config.decoder

    def forward(self, outputs: dict[str, torch.Tensor], targets: Targets) -> dict[str, torch.Tensor]:
        config = self.config
        seg_loss, direction_loss = raster_losses(
            outputs["seg"], outputs["direction"], targets.raster_mask, targets.raster_direction,
            config.lane_class_weight, config.direction_bins,
        )  # fmt: skip
        total = config.seg_weight * seg_loss + config.direction_weight * direction_loss
        return {"loss": total, "seg": seg_loss.detach(), "direction": direction_loss.detach()}


class PostProcess:
    """Outputs -> one lane graph per frame in metres: cells whose lane probability passes the threshold,
    their predicted direction as the prepared rasters' bins, through Pixel2Graph."""

    def __init__(self, config: Config):
        head = config.decoder
        self.threshold = head.score_threshold
        # Pixel2Graph reads a map of direction bins (the prepared rasters' format): the predicted vectors
        # are binned as the rasters were, by the raster grid's own rule (at most half a bin, 5 degrees, off).
        (x0, x1), (y0, y1) = config.encoder.x_range, config.encoder.y_range
        self.grid = Grid(Range(x0, x1, y0, y1), head.resolution, direction_bins=head.direction_bins)

    @torch.no_grad()
    def __call__(self, outputs: dict[str, torch.Tensor]) -> list[LaneGraph]:
        # the grid's cells whose centres lie in the range: the output's last row and column may reach past it
        rows, cols = self.grid.shape
        masks = (outputs["seg"].float().softmax(1)[:, 1, :rows, :cols] > self.threshold).cpu().numpy()
        directions = outputs["direction"].float()[..., :rows, :cols].cpu().numpy()
        graphs = []
        for mask, (dx, dy) in zip(masks, directions, strict=True):
            bins = np.where(mask, self.grid.direction_bin(dx, dy), 0).astype(np.uint8)
            graphs.append(pixel2graph(mask, bins, self.grid))
        return graphs


def build(config: Config) -> Built:
    return Built(HDMapNet(config), HDMapNetLoss(config), PostProcess(config), frozenset({"raster"}), "pixel")
