"""Multi-scale deformable attention (Deformable DETR) in pure PyTorch, sampling with `grid_sample`.

No custom CUDA op: the sampling is `F.grid_sample`, so the same code runs on CPU and GPU.
Locations are unit coordinates: (0, 0) is the top-left corner of a feature map, (1, 1) its
bottom-right corner; for the BEV map that is (x_min, y_max) and (x_max, y_min).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from baselines.layers.blocks import constant, fp32_grid_sample


def deformable_sample(
    values: list[torch.Tensor], locations: torch.Tensor, weights: torch.Tensor
) -> torch.Tensor:
    """Weighted sum of bilinear samples.

    values: per level (B * heads, head_dim, H_l, W_l); locations: (B, Nq, heads, L, S, 2) unit coordinates;
    weights: (B, Nq, heads, L, S). Returns (B, Nq, heads * head_dim).
    """
    batch, num_queries, heads, levels, samples, _ = locations.shape
    grids = 2 * locations - 1  # grid_sample wants [-1, 1]; align_corners=False maps -1 to the map edge
    per_level = []
    for level, value in enumerate(values):
        grid = grids[:, :, :, level].permute(0, 2, 1, 3, 4).reshape(batch * heads, num_queries, samples, 2)
        # fp32 out, as CUDA's autocast gave it (promoting the bf16 values to the fp32 grid): the weighted
        # sum over the samples below stays in fp32
        per_level.append(
            fp32_grid_sample(value, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        )
    sampled = torch.stack(per_level, dim=-2)  # (B * heads, head_dim, Nq, L, S)
    w = weights.permute(0, 2, 1, 3, 4).reshape(batch * heads, 1, num_queries, levels, samples)
    out = (sampled * w).sum(dim=(-2, -1))  # (B * heads, head_dim, Nq)
    return out.view(batch, heads * out.shape[1], num_queries).transpose(1, 2)


class DeformableAttention(nn.Module):
    """Each query samples `points` locations around each of its `anchors` reference points, per head
    and level, and sums them with learned weights (softmax over all its samples of a head).

    One anchor per query is plain Deformable DETR; several anchors let a query read along a curve
    (LaneGAP's Bezier deformable attention).
    """

    def __init__(self, dim: int, heads: int = 8, levels: int = 1, points: int = 4, anchors: int = 1):
        super().__init__()
        if dim % heads:
            raise ValueError(f"dim {dim} is not divisible by heads {heads}")
        self.heads, self.levels, self.points, self.anchors = heads, levels, points, anchors
        samples = levels * anchors * points
        self.sampling_offsets = nn.Linear(dim, heads * samples * 2)
        self.attention_weights = nn.Linear(dim, heads * samples)
        self.value_proj = nn.Linear(dim, dim)
        self.output_proj = nn.Linear(dim, dim)
        self._reset_parameters()

    def _reset_parameters(self) -> None:
        # Deformable DETR's start: head h looks in direction 2*pi*h/heads, point p at distance p + 1.
        nn.init.zeros_(self.sampling_offsets.weight)
        angles = torch.arange(self.heads, dtype=torch.float32) * (2 * math.pi / self.heads)
        directions = torch.stack([angles.cos(), angles.sin()], -1)
        directions = directions / directions.abs().max(-1, keepdim=True).values
        bias = directions.view(self.heads, 1, 1, 1, 2).repeat(1, self.levels, self.anchors, self.points, 1)
        bias *= torch.arange(1, self.points + 1, dtype=torch.float32).view(1, 1, 1, -1, 1)
        with torch.no_grad():
            self.sampling_offsets.bias.copy_(bias.flatten())
        nn.init.zeros_(self.attention_weights.weight)
        nn.init.zeros_(self.attention_weights.bias)
        nn.init.xavier_uniform_(self.value_proj.weight)
        nn.init.zeros_(self.value_proj.bias)
        nn.init.xavier_uniform_(self.output_proj.weight)
        nn.init.zeros_(self.output_proj.bias)

    def forward(
        self, query: torch.Tensor, reference: torch.Tensor, values: list[torch.Tensor]
    ) -> torch.Tensor:
        """query (B, Nq, C); reference (B, Nq, anchors, 2) unit coordinates; values per level (B, C, H, W)."""
        batch, num_queries, dim = query.shape
        heads, levels, anchors, points = self.heads, self.levels, self.anchors, self.points
        head_values = []
        for value in values:
            _, _, height, width = value.shape
            projected = self.value_proj(value.flatten(2).transpose(1, 2))  # (B, HW, C)
            head_values.append(projected.transpose(1, 2).reshape(batch * heads, dim // heads, height, width))
        offsets = self.sampling_offsets(query).view(batch, num_queries, heads, levels, anchors, points, 2)
        sizes = constant([[v.shape[-1], v.shape[-2]] for v in values], query.device)
        # Offsets are in pixels of each level, so a unit step is one feature cell at every scale. In fp32
        # whatever the query's dtype: bf16 would round the map's sizes and the sampling positions.
        anchor = reference.float().view(batch, num_queries, 1, 1, anchors, 1, 2)
        locations = anchor + offsets.float() / sizes.view(1, 1, 1, levels, 1, 1, 2)
        weights = self.attention_weights(query).view(batch, num_queries, heads, levels * anchors * points)
        weights = weights.softmax(-1).view(batch, num_queries, heads, levels, anchors * points)
        locations = locations.view(batch, num_queries, heads, levels, anchors * points, 2)
        return self.output_proj(deformable_sample(head_values, locations, weights))
