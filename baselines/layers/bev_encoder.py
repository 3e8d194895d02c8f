"""The shared BEV encoder: every baseline decoder reads the (B, C, bev_h, bev_w) map it produces.

- Camera: ResNet + FPN-like neck + a GKT view transformer (geometry-guided kernel attention: each BEV
  query projects its pillar points into the cameras through the calibration and attends to the
  k x k kernel of image features around each projection).
- LiDAR: a PointPillars-style pillar encoder scattered onto the same BEV grid.
- Fusion: both maps, fused by a convolution.

BEV map layout: row 0 is the front edge (y_max), column 0 the left edge (x_min), as the rasters of
docs/guide/prepare.md. All of it is plain PyTorch (no custom CUDA op).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
import torch.nn.functional as F
from torch import nn

from baselines.config import EncoderConfig
from baselines.layers.attention import DeformableAttention
from baselines.layers.blocks import FeedForward, constant, fp32_grid_sample
from baselines.layers.resnet import build_resnet
from pipeline.camera import project_points

IMAGENET_MEAN = (123.675, 116.28, 103.53)  # torchvision's, RGB 0..255
IMAGENET_STD = (58.395, 57.12, 57.375)


@dataclass
class SensorBatch:
    """Model input. Camera fields are None for LiDAR-only runs and vice versa."""

    # (B, Ncam, 3, H, W) zero-padded bottom / right: uint8 RGB as loaded, or float already normalised
    images: torch.Tensor | None = None
    intrinsics: torch.Tensor | None = None  # (B, Ncam, 3, 3) of the resized images
    sensor_to_ego: torch.Tensor | None = None  # (B, Ncam, 4, 4) camera frame -> BEV frame
    image_sizes: torch.Tensor | None = None  # (B, Ncam, 2) height, width of each image before padding
    points: torch.Tensor | None = None  # (B, P, 4) x, y, z, intensity in the BEV frame, zero-padded
    points_mask: torch.Tensor | None = None  # (B, P) True for real points
    # (B,) z of the ground under the BEV origin, in the BEV frame (frames.ground_z); None: z = 0
    ground_z: torch.Tensor | None = None
    # (B, 2) dz/dx, dz/dy of the ground plane in the BEV frame (frames.ground_slope): the ground is
    # z = ground_z + a x + b y (nuScenes' LIDAR_TOP is tilted on the ego); None: level
    ground_slope: torch.Tensor | None = None

    def to(self, device: torch.device | str) -> SensorBatch:
        moved = {f.name: getattr(self, f.name) for f in fields(self)}
        return SensorBatch(
            **{k: None if v is None else v.to(device, non_blocking=True) for k, v in moved.items()}
        )

    @property
    def batch_size(self) -> int:
        return (self.images if self.images is not None else self.points).shape[0]

    def normalised_images(self) -> torch.Tensor:
        """Images normalised by ImageNet's mean and std (torchvision's), zero in the padding. The loader
        hands over uint8: normalising here runs on the model's device, not in the loader's workers."""
        if self.images.dtype != torch.uint8:
            return self.images
        mean = constant(IMAGENET_MEAN, self.images.device).view(3, 1, 1)
        std = constant(IMAGENET_STD, self.images.device).view(3, 1, 1)
        height, width = self.images.shape[-2:]
        rows = torch.arange(height, device=self.images.device) < self.image_sizes[..., 0:1]  # (B, Ncam, H)
        cols = torch.arange(width, device=self.images.device) < self.image_sizes[..., 1:2]  # (B, Ncam, W)
        inside = (rows[..., :, None] & cols[..., None, :]).unsqueeze(2)  # (B, Ncam, 1, H, W)
        return ((self.images.float() - mean) / std) * inside

    def ground(self) -> torch.Tensor:
        """(B,) ground_z, zeros where it is not given."""
        if self.ground_z is not None:
            return self.ground_z.float()
        reference = self.images if self.images is not None else self.points
        return torch.zeros(self.batch_size, device=reference.device)

    def slope(self) -> torch.Tensor | None:
        """(B, 2) ground_slope, None (level) where it is not given."""
        return None if self.ground_slope is None else self.ground_slope.float()


def bev_cell_centres(config: EncoderConfig) -> torch.Tensor:
    """(bev_h, bev_w, 2) x, y in metres of each BEV cell centre (row 0 = front)."""
    (x0, x1), (y0, y1) = config.x_range, config.y_range
    xs = x0 + (torch.arange(config.bev_w, dtype=torch.float32) + 0.5) * (x1 - x0) / config.bev_w
    ys = y1 - (torch.arange(config.bev_h, dtype=torch.float32) + 0.5) * (y1 - y0) / config.bev_h
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([grid_x, grid_y], -1)


def ground_height(
    xy: torch.Tensor, ground_z: torch.Tensor, ground_slope: torch.Tensor | None
) -> torch.Tensor:
    """(B, P) z of the ground under BEV points xy (B, P, 2) of B frames, in each one's BEV frame: the plane
    z = ground_z + a x + b y of their ground_z (B,) and ground_slope (B, 2) (frames.ground_z, ground_slope);
    ground_z alone where ground_slope is None. A slope of (0, 0) gives ground_z bit for bit (x * 0 is +-0)."""
    height = ground_z[:, None]
    if ground_slope is None:
        return height.expand(xy.shape[:-1])
    return height + ground_slope[:, 0:1] * xy[..., 0] + ground_slope[:, 1:2] * xy[..., 1]


def above_ground_to_bev(
    points: torch.Tensor, ground_z: torch.Tensor, ground_slope: torch.Tensor | None = None
) -> torch.Tensor:
    """Points (P, 3) whose z is the height above the ground -> (B, P, 3) in the BEV frame of each of B
    frames, given their ground plane: ground_z (B,) and ground_slope (B, 2) (`ground_height`). The height is
    added along the BEV frame's z, straight above the point (x, y) of the ground plane."""
    lifted = points.repeat(len(ground_z), 1, 1)
    lifted[..., 2] += ground_height(lifted[..., :2], ground_z, ground_slope)
    return lifted


class FPNNeck(nn.Module):
    """Lateral 1x1 convs and a top-down sum from stride 32 down to `out_stride`, then a 3x3 conv."""

    def __init__(self, stage_channels: list[int], channels: int, out_stride: int):
        super().__init__()
        if out_stride not in (4, 8, 16, 32):
            raise ValueError(f"feature_stride must be 4, 8, 16 or 32, got {out_stride}")
        self.first_stage = int(math.log2(out_stride)) - 2  # layer1 has stride 4
        self.lateral = nn.ModuleList(nn.Conv2d(c, channels, 1) for c in stage_channels[self.first_stage :])
        self.output = nn.Sequential(
            nn.Conv2d(channels, channels, 3, padding=1, bias=False), nn.BatchNorm2d(channels), nn.ReLU(True)
        )

    def forward(self, stages: list[torch.Tensor]) -> torch.Tensor:
        stages = stages[self.first_stage :]
        x = self.lateral[-1](stages[-1])
        for lateral, stage in zip(reversed(self.lateral[:-1]), reversed(stages[:-1]), strict=True):
            x = lateral(stage) + F.interpolate(x, size=stage.shape[-2:], mode="nearest")
        return self.output(x)


class GeometryKernelAttention(nn.Module):
    """Multi-head attention of each BEV query over the image features sampled in the kernels around
    its projections (all pillar heights, at most `max_views` cameras, k x k kernel each)."""

    def __init__(self, dim: int, heads: int, num_heights: int, kernel_size: tuple[int, int]):
        super().__init__()
        self.heads = heads
        rows, cols = kernel_size
        self.query_proj = nn.Linear(dim, dim)
        self.key_proj = nn.Linear(dim, dim, bias=False)
        self.value_proj = nn.Linear(dim, dim)
        self.output_proj = nn.Linear(dim, dim)
        # Where a sample sits (pillar height, kernel cell) tells the query how to weigh it.
        self.sample_embedding = nn.Parameter(torch.randn(num_heights, rows * cols, dim) * 0.02)

    def forward(
        self, query: torch.Tensor, sampled: torch.Tensor, mask: torch.Tensor, views: int
    ) -> torch.Tensor:
        """query (B, Q, C); sampled (B, C, Q, S) image features, S = heights * views * kernel;
        mask (B, Q, S) True where the sample's projection is valid. Returns (B, Q, C)."""
        batch, num_queries, dim = query.shape
        heads, head_dim = self.heads, dim // self.heads
        q = self.query_proj(query).view(batch, num_queries, heads, head_dim)
        # q_h . (W_k,h f) = (W_k,h^T q_h) . f: the query is taken to feature space once, instead of
        # projecting every one of the Q * S sampled features.
        q_in_features = torch.einsum("bqhd,hdc->bqhc", q, self.key_proj.weight.view(heads, head_dim, dim))
        num_heights, kernel, _ = self.sample_embedding.shape
        positions = (
            self.sample_embedding.unsqueeze(1).expand(num_heights, views, kernel, dim).reshape(-1, dim)
        )
        positions = self.key_proj(positions)  # (S, C)
        logits = torch.einsum("bqhc,bcqs->bqhs", q_in_features, sampled)
        logits = logits + torch.einsum("bqhd,shd->bqhs", q, positions.view(-1, heads, head_dim))
        logits = (logits / math.sqrt(head_dim)).masked_fill(~mask.unsqueeze(2), -1e4)
        # Queries that see no camera get all-zero weights (and keep only their residual).
        weights = logits.softmax(-1) * mask.unsqueeze(2)
        pooled = torch.einsum("bqhs,bcqs->bqhc", weights, sampled)  # (B, Q, heads, C)
        values = torch.einsum("bqhc,hdc->bqhd", pooled, self.value_proj.weight.view(heads, head_dim, dim))
        seen = mask.any(-1, keepdim=True).to(values.dtype)
        values = values.reshape(batch, num_queries, dim) + self.value_proj.bias * seen
        return self.output_proj(values)


class BevLayer(nn.Module):
    """BEV self-attention (deformable), kernel attention to the cameras, feed-forward; post-norm."""

    def __init__(self, config: EncoderConfig):
        super().__init__()
        dim = config.channels
        self.self_attn = DeformableAttention(dim, heads=config.camera_heads, levels=1, points=4)
        self.cross_attn = GeometryKernelAttention(
            dim, config.camera_heads, len(config.camera_heights), config.kernel_size
        )
        self.ffn = FeedForward(dim, dim * 2, config.dropout)
        self.norms = nn.ModuleList(nn.LayerNorm(dim) for _ in range(3))
        self.dropout = nn.Dropout(config.dropout)
        self.bev_shape = (config.bev_h, config.bev_w)

    def forward(
        self,
        bev: torch.Tensor,
        pos: torch.Tensor,
        reference: torch.Tensor,
        sampled: torch.Tensor,
        mask: torch.Tensor,
        views: int,
    ) -> torch.Tensor:
        batch, num_queries, dim = bev.shape
        bev_map = bev.transpose(1, 2).reshape(batch, dim, *self.bev_shape)
        bev = self.norms[0](bev + self.dropout(self.self_attn(bev + pos, reference, [bev_map])))
        bev = self.norms[1](bev + self.dropout(self.cross_attn(bev + pos, sampled, mask, views)))
        return self.norms[2](bev + self.dropout(self.ffn(bev)))


class CameraEncoder(nn.Module):
    def __init__(self, config: EncoderConfig):
        super().__init__()
        self.config = config
        dim = config.channels
        self.backbone = build_resnet(config.backbone, config.backbone_width, config.backbone_weights)
        # The classification head is never used; dropping it keeps it out of the optimiser.
        self.backbone.fc = nn.Identity()
        self.neck = FPNNeck(self.backbone.stage_channels, dim, config.feature_stride)
        self.bev_queries = nn.Parameter(torch.randn(config.bev_h * config.bev_w, dim) * 0.02)
        self.row_embedding = nn.Parameter(torch.randn(config.bev_h, dim // 2) * 0.02)
        self.col_embedding = nn.Parameter(torch.randn(config.bev_w, dim - dim // 2) * 0.02)
        self.layers = nn.ModuleList(BevLayer(config) for _ in range(config.camera_layers))
        centres = bev_cell_centres(config)  # (H, W, 2)
        heights = torch.tensor(config.camera_heights, dtype=torch.float32)
        pillars = torch.cat(
            [
                centres[:, :, None, :].expand(-1, -1, len(heights), 2),
                heights.view(1, 1, -1, 1).expand(config.bev_h, config.bev_w, -1, 1),
            ],
            -1,
        )
        # (Q * Z, 3), z above the ground: each frame's ground plane (ground_z, ground_slope) moves them into
        # its BEV frame
        self.register_buffer("pillar_points", pillars.view(-1, 3), persistent=False)
        reference = config.metres_to_unit(centres.view(-1, 1, 2))  # (Q, 1, 2) unit coordinates
        self.register_buffer("reference", reference, persistent=False)
        rows, cols = config.kernel_size
        dy, dx = torch.meshgrid(
            torch.arange(rows) - (rows - 1) / 2, torch.arange(cols) - (cols - 1) / 2, indexing="ij"
        )
        # Offsets of the GKT kernel samples around a projection, in feature cells (x, y).
        self.register_buffer(
            "kernel_offsets", torch.stack([dx, dy], -1).view(-1, 2).float(), persistent=False
        )
        self._freeze_stages()

    def _freeze_stages(self) -> None:
        """mmdet's `frozen_stages`: -1 none, 0 the stem (conv1, bn1), n the stem and layer1..layer{n}."""
        stages = self.config.backbone_frozen_stages
        frozen = [self.backbone.conv1, self.backbone.bn1] if stages >= 0 else []
        frozen += [getattr(self.backbone, f"layer{i}") for i in range(1, stages + 1)]
        for module in frozen:
            for parameter in module.parameters():
                parameter.requires_grad_(False)

    def train(self, mode: bool = True) -> CameraEncoder:
        super().train(mode)
        if mode and self.config.backbone_norm_eval:
            for module in self.backbone.modules():
                if isinstance(module, nn.BatchNorm2d):
                    module.eval()
        return self

    def sample_image_features(
        self, features: torch.Tensor, batch: SensorBatch, image_hw: tuple[int, int]
    ) -> tuple[torch.Tensor, torch.Tensor, int]:
        """features (B, Ncam, C, Hf, Wf) -> sampled (B, C, Q, S) and mask (B, Q, S)."""
        config = self.config
        num_batch, cameras, dim, feature_h, feature_w = features.shape
        points = above_ground_to_bev(self.pillar_points, batch.ground(), batch.slope())
        pixels, visible = project_points(points, batch.intrinsics, batch.sensor_to_ego, batch.image_sizes)
        views = min(config.max_views, cameras)
        # The first `views` cameras that see each point (a point is seen by one, or two in overlaps).
        order = torch.arange(cameras, 0, -1, device=visible.device).view(1, -1, 1)
        view_index = (visible * order).topk(views, dim=1).indices  # (B, V, QZ)
        view_pixels = pixels.gather(1, view_index.unsqueeze(-1).expand(-1, -1, -1, 2))
        view_visible = visible.gather(1, view_index)
        # Kernel samples in feature-map coordinates (cell centres at integers).
        stride_y = image_hw[0] / feature_h
        stride_x = image_hw[1] / feature_w
        stride = constant([stride_x, stride_y], pixels.device)
        cells = (view_pixels + 0.5) / stride - 0.5
        cells = cells.unsqueeze(-2) + self.kernel_offsets  # (B, V, QZ, K, 2)
        # The cameras are stacked as the depth of a volume; with align_corners=True an integer depth
        # index falls exactly on one camera, so 3D trilinear sampling is 2D bilinear in that camera.
        # This samples only the chosen views instead of every point in every camera.
        grid_x = cells[..., 0] / max(feature_w - 1, 1) * 2 - 1
        grid_y = cells[..., 1] / max(feature_h - 1, 1) * 2 - 1
        grid_z = (view_index.float() / max(cameras - 1, 1) * 2 - 1).unsqueeze(-1).expand_as(grid_x)
        grid = torch.stack([grid_x, grid_y, grid_z], -1)  # (B, V, QZ, K, 3)
        num_heights = len(config.camera_heights)
        kernel = grid.shape[-2]
        num_queries = config.bev_h * config.bev_w
        grid = grid.view(num_batch, views, num_queries, num_heights, kernel, 3).permute(0, 2, 3, 1, 4, 5)
        grid = grid.reshape(num_batch, num_queries, num_heights * views * kernel, 1, 3)
        volume = features.transpose(1, 2)  # (B, C, Ncam, Hf, Wf)
        # Sampled in fp32 (blocks.fp32_grid_sample); returned in the features' dtype, which the attention's
        # einsums cast it to anyway: a second, fp32 copy of the largest tensor would add nothing.
        sampled = fp32_grid_sample(volume, grid, mode="bilinear", align_corners=True).to(features.dtype)
        mask = view_visible.view(num_batch, views, num_queries, num_heights, 1).permute(0, 2, 3, 1, 4)
        mask = mask.expand(-1, -1, -1, -1, kernel).reshape(num_batch, num_queries, -1)
        return sampled.squeeze(-1), mask, views

    def forward(self, batch: SensorBatch) -> torch.Tensor:
        config = self.config
        images = batch.normalised_images()
        num_batch, cameras = images.shape[:2]
        features = self.neck(self.backbone(images.flatten(0, 1)))
        features = features.view(num_batch, cameras, *features.shape[1:])
        sampled, mask, views = self.sample_image_features(features, batch, images.shape[-2:])
        pos = torch.cat(
            [
                self.row_embedding[:, None, :].expand(-1, config.bev_w, -1),
                self.col_embedding[None, :, :].expand(config.bev_h, -1, -1),
            ],
            -1,
        ).view(1, -1, config.channels)
        bev = self.bev_queries.unsqueeze(0).expand(num_batch, -1, -1)
        reference = self.reference.unsqueeze(0).expand(num_batch, -1, -1, -1)
        for layer in self.layers:
            bev = layer(bev, pos, reference, sampled, mask, views)
        return bev.transpose(1, 2).reshape(num_batch, config.channels, config.bev_h, config.bev_w)


class ConvBlock(nn.Sequential):
    def __init__(self, in_channels: int, out_channels: int, stride: int = 1):
        super().__init__(
            nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1, bias=False),
            nn.BatchNorm2d(out_channels),
            nn.ReLU(True),
        )


class PillarEncoder(nn.Module):
    """PointPillars: a per-point linear layer on (x, y, z, intensity, offsets to the pillar mean and
    centre), each feature normalised first, max-pooled per pillar, scattered to a grid and refined by a
    small 2D CNN."""

    def __init__(self, config: EncoderConfig):
        super().__init__()
        self.config = config
        self.grid_h = config.bev_h * config.pillar_subdivision
        self.grid_w = config.bev_w * config.pillar_subdivision
        pillar = config.pillar_channels
        # x and y span tens of metres, intensity 0..1: unnormalised, the paint's intensity is ~1e-4 of each
        # channel's variance at initialisation and LiDAR-only training may not find it in 880 steps
        # (docs/EXPERIMENTS.md, 2026-12-05, commit 1084dc5)
        self.point_norm = nn.BatchNorm1d(9)
        self.point_net = nn.Sequential(
            nn.Linear(9, pillar, bias=False), nn.BatchNorm1d(pillar), nn.ReLU(True)
        )
        layers: list[nn.Module] = [ConvBlock(pillar, config.channels, stride=config.pillar_subdivision)]
        layers += [ConvBlock(config.channels, config.channels) for _ in range(config.lidar_blocks)]
        self.backbone = nn.Sequential(*layers)

    def forward(self, batch: SensorBatch) -> torch.Tensor:
        config = self.config
        # z above the ground plane, for the z_range and as a feature: the same on both datasets' frames
        points, points_mask = batch.points.clone(), batch.points_mask
        points[..., 2] -= ground_height(points[..., :2], batch.ground(), batch.slope())
        num_batch = points.shape[0]
        (x0, x1), (y0, y1), (z0, z1) = config.x_range, config.y_range, config.z_range
        cell_w = (x1 - x0) / self.grid_w
        cell_h = (y1 - y0) / self.grid_h
        batch_index = torch.arange(num_batch, device=points.device).unsqueeze(1).expand_as(points_mask)
        x, y, z = points[..., 0], points[..., 1], points[..., 2]
        col = torch.floor((x - x0) / cell_w).long()
        row = torch.floor((y1 - y) / cell_h).long()
        keep = points_mask & (col >= 0) & (col < self.grid_w) & (row >= 0) & (row < self.grid_h)
        keep &= (z >= z0) & (z <= z1)
        flat, batch_index, row, col = points[keep], batch_index[keep], row[keep], col[keep]
        pillar = (batch_index * self.grid_h + row) * self.grid_w + col
        cells = num_batch * self.grid_h * self.grid_w
        counts = torch.zeros(cells, device=points.device).index_add_(0, pillar, torch.ones_like(flat[:, 0]))
        sums = torch.zeros(cells, 3, device=points.device).index_add_(0, pillar, flat[:, :3])
        mean = sums[pillar] / counts[pillar].unsqueeze(1)
        centre_x = x0 + (col.float() + 0.5) * cell_w
        centre_y = y1 - (row.float() + 0.5) * cell_h
        decorated = torch.cat(
            [flat, flat[:, :3] - mean, (flat[:, 0] - centre_x)[:, None], (flat[:, 1] - centre_y)[:, None]], 1
        )
        point_features = self.point_net(self.point_norm(decorated))
        canvas = torch.zeros(cells, point_features.shape[1], device=points.device, dtype=point_features.dtype)
        # Point features are >= 0 after the ReLU, so a zero canvas with amax is the pillar max.
        canvas = canvas.scatter_reduce(
            0, pillar.unsqueeze(1).expand_as(point_features), point_features, "amax"
        )
        canvas = canvas.view(num_batch, self.grid_h, self.grid_w, -1).permute(0, 3, 1, 2)
        return self.backbone(canvas)


class BEVEncoder(nn.Module):
    """Sensors -> (B, channels, bev_h, bev_w) BEV features, for `camera`, `lidar` or `fusion`."""

    def __init__(self, config: EncoderConfig):
        super().__init__()
        self.config = config
        uses_camera = config.modality in ("camera", "fusion")
        uses_lidar = config.modality in ("lidar", "fusion")
        self.camera = CameraEncoder(config) if uses_camera else None
        self.lidar = PillarEncoder(config) if uses_lidar else None
        self.fuser = ConvBlock(2 * config.channels, config.channels) if uses_camera and uses_lidar else None

    def forward(self, batch: SensorBatch) -> torch.Tensor:
        maps = []
        if self.camera is not None:
            maps.append(self.camera(batch))
        if self.lidar is not None:
            maps.append(self.lidar(batch))
        return self.fuser(torch.cat(maps, 1)) if self.fuser is not None else maps[0]
