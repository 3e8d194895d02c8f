"""HDMapNet's `BevEncode` head on the shared BEV features: lane logits and the travel direction on a
raster grid. HDMapNet is this head on the encoder (baselines/models/hdmapnet.py); the query models of
the tiny preset carry a small one beside their decoder (`lane_head_width`), trained on the prepared
rasters, whose lane probability moves each regressed point across its polyline onto the centre of the
lane it lies on (`snap_polylines`).

Why: the tiny preset's 1.5 m BEV cells are three times the metric's 0.45 m match radius; regressed
points land on the right lane but often beyond that radius, and the 0.3 m dense head finds the lane's
centre to a fraction of a cell (docs/EXPERIMENTS.md, 2026-12-04, commit 0fbbd26).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from scipy.ndimage import map_coordinates
from torch import nn

from baselines.config import Config, EncoderConfig
from baselines.layers.raster_targets import raster_losses
from baselines.layers.resnet import resnet18
from baselines.layers.targets import Targets


def raster_shape(encoder: EncoderConfig, resolution: float) -> tuple[int, int]:
    """(rows, columns) of a raster of `resolution` m cells from the front-left corner of the encoder's
    range, enough to cover it (50 x 100 m in 0.3 m cells: 334 x 167, the last row and column reaching past
    the range, as the prepared 0.15 m raster's 667 x 333 padded to 668 x 334)."""
    (x0, x1), (y0, y1) = encoder.x_range, encoder.y_range
    return math.ceil(round((y1 - y0) / resolution, 6)), math.ceil(round((x1 - x0) / resolution, 6))


class Up(nn.Module):
    """HDMapNet's `Up`: upsample to the skip's size, concatenate the skip, two 3x3 conv-BN-ReLU."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.conv = nn.Sequential(
            nn.Conv2d(in_channels, out_channels, 3, padding=1, bias=False),
            nn.BatchNorm2d(out_channels),
            nn.ReLU(True),
            nn.Conv2d(out_channels, out_channels, 3, padding=1, bias=False),
            nn.BatchNorm2d(out_channels),
            nn.ReLU(True),
        )

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        # HDMapNet scales by 4 (its canvas is divisible by 8); the skip's size is the same there and
        # also fits grids that are not.
        x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=True)
        return self.conv(torch.cat([skip, x], 1))


class Branch(nn.Module):
    """One output of BevEncode: `Up` with the layer1 skip, then x2 to the output size and a 1x1 conv."""

    def __init__(self, width: int, out_channels: int):
        super().__init__()
        self.up1 = Up(width + 4 * width, 4 * width)
        self.up2 = nn.Sequential(
            nn.Conv2d(4 * width, 2 * width, 3, padding=1, bias=False),
            nn.BatchNorm2d(2 * width),
            nn.ReLU(True),
            nn.Conv2d(2 * width, out_channels, 1),
        )

    def forward(self, x: torch.Tensor, skip: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        x = self.up1(x, skip)
        return self.up2(F.interpolate(x, size=size, mode="bilinear", align_corners=True))


class RasterHead(nn.Module):
    """BEV features (B, channels, bev_h, bev_w) -> "seg": lane logits (B, 2, H, W) and "direction":
    (cos, sin) (B, 2, H, W) on the raster grid `size` (row 0 the front edge, column 0 the left edge)."""

    def __init__(self, channels: int, width: int, size: tuple[int, int]):
        super().__init__()
        self.size = size
        # BevEncode: the ResNet-18 trunk's layers on a stem that takes the BEV channels; no max-pool,
        # so layer1 is at 1/2 of the input and layer3 at 1/8.
        trunk = resnet18(width)
        self.conv1 = nn.Conv2d(channels, width, 7, stride=2, padding=3, bias=False)
        self.bn1, self.relu = trunk.bn1, trunk.relu
        self.layer1, self.layer2, self.layer3 = trunk.layer1, trunk.layer2, trunk.layer3
        self.seg_branch = Branch(width, 2)
        self.direction_branch = Branch(width, 2)

    def decode(self, bev: torch.Tensor, direction: bool = True) -> dict[str, torch.Tensor]:
        """direction=False leaves out the direction branch (a query model's lane head at inference)."""
        # Cell-centred grids on the same range: align_corners=False maps every centre onto its place.
        # contiguous(): the encoder's map can be channels-last, and this head's backward on a
        # channels-last input corrupts the heap in torch 2.13 on CPU (a crash, found by `cli train`).
        x = F.interpolate(bev.contiguous(), size=self.size, mode="bilinear", align_corners=False)
        skip = self.layer1(self.relu(self.bn1(self.conv1(x))))
        x = self.layer3(self.layer2(skip))
        outputs = {"seg": self.seg_branch(x, skip, self.size)}
        if direction:
            outputs["direction"] = self.direction_branch(x, skip, self.size)
        return outputs


def lane_head(config: Config) -> RasterHead | None:
    """A query model's lane head as its decoder config asks (`lane_head_width`, 0: none)."""
    head = config.decoder
    if not head.lane_head_width:
        return None
    size = raster_shape(config.encoder, head.lane_head_resolution)
    return RasterHead(config.encoder.channels, head.lane_head_width, size)


def lane_outputs(head: RasterHead, bev: torch.Tensor) -> dict[str, torch.Tensor]:
    """The lane head's outputs under the names a query model's outputs give them: the lane logits always
    (the post-processing reads the lane probability), the direction in training only (its loss). It
    reads the BEV features without training them: the query model learns as it would without the head,
    which only refines its points."""
    outputs = head.decode(bev.detach(), direction=head.training)
    named = {"lane_seg": outputs["seg"]}
    if "direction" in outputs:
        named["lane_direction"] = outputs["direction"]
    return named


def lane_head_losses(outputs: dict[str, torch.Tensor], targets: Targets) -> dict[str, torch.Tensor]:
    """A query model's lane head ("lane_seg", "lane_direction") against the prepared raster: lane
    cross-entropy "lane_seg" and direction L2 "lane_direction", as HDMapNet's loss."""
    if targets.raster_mask is None:
        raise ValueError("the lane head trains on the prepared rasters: the model must need 'raster'")
    seg, direction = raster_losses(
        outputs["lane_seg"], outputs["lane_direction"], targets.raster_mask, targets.raster_direction,
        adaptive=True,
    )  # fmt: skip
    return {"lane_seg": seg, "lane_direction": direction}


def lane_probability(outputs: dict[str, torch.Tensor]) -> np.ndarray | None:
    """(B, H, W) lane probability of a query model's lane head, None without one."""
    if "lane_seg" not in outputs:
        return None
    return outputs["lane_seg"].float().softmax(1)[:, 1].cpu().numpy()


SNAP_STEP_M = 0.1  # the profile across a polyline is read every 10 cm
SNAP_FLOOR = 0.3  # a ridge whose top is below this lane probability moves nothing


def snap_polylines(
    polylines: list[np.ndarray], probability: np.ndarray, encoder: EncoderConfig, radius: float
) -> list[np.ndarray]:
    """Each point of each (n, 2) polyline (metres) moved across its polyline onto the centre of the
    lane-probability ridge nearest it within `radius` m: the local maximum nearest the point, and the
    centroid of the run of samples around it above half that maximum (a fraction of a cell). A point with
    no ridge above SNAP_FLOOR there stays. `probability` (H, W) is a raster over the encoder's range."""
    if radius <= 0 or not polylines:
        return polylines
    (x0, x1), (y0, y1) = encoder.x_range, encoder.y_range
    rows, cols = probability.shape
    cell = ((x1 - x0) / cols, (y1 - y0) / rows)
    sizes = [len(p) for p in polylines]
    xy = np.concatenate(polylines).astype(np.float64)
    # the tangent of each point along its own polyline (one-sided at the ends)
    tangent = np.concatenate([np.gradient(p.astype(np.float64), axis=0) if len(p) > 1 else np.zeros((1, 2))
                              for p in polylines])  # fmt: skip
    length = np.linalg.norm(tangent, axis=1, keepdims=True)
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], 1) / np.maximum(length, 1e-9)
    offsets = np.arange(-round(radius / SNAP_STEP_M), round(radius / SNAP_STEP_M) + 1) * SNAP_STEP_M
    across = xy[:, None] + offsets[None, :, None] * normal[:, None]  # (P, K, 2)
    # scipy's map_coordinates: bilinear reads of the raster at continuous (row, column), centres at integers
    coordinates = [(y1 - across[..., 1]) / cell[1] - 0.5, (across[..., 0] - x0) / cell[0] - 0.5]
    profile = map_coordinates(probability.astype(np.float64), coordinates, order=1, mode="nearest")
    padded = np.pad(profile, ((0, 0), (1, 1)), constant_values=-1.0)
    top = (profile >= padded[:, :-2]) & (profile >= padded[:, 2:]) & (profile > SNAP_FLOOR)
    nearest = np.where(top, np.abs(offsets)[None], np.inf).argmin(1)  # the ridge top nearest the point
    peak = profile[np.arange(len(xy)), nearest]
    # the ridge: the run of samples above half its top that holds the top
    weight = profile - peak[:, None] / 2
    index, below = np.arange(len(offsets))[None], weight <= 0
    start = np.where(below & (index <= nearest[:, None]), index, -1).max(1)
    end = np.where(below & (index >= nearest[:, None]), index, len(offsets)).min(1)
    weight *= (index > start[:, None]) & (index < end[:, None])
    shift = (weight * offsets[None]).sum(1) / np.maximum(weight.sum(1), 1e-12)
    moved = top.any(1) & (length[:, 0] > 0)
    snapped = xy + np.where(moved, shift, 0.0)[:, None] * normal
    # inside the map, as the ground truth and the unsnapped points (polyline_to_metres)
    snapped = np.clip(snapped, [x0, y0], [x1, y1])
    return np.split(snapped, np.cumsum(sizes)[:-1])
