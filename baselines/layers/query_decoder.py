"""The hierarchical-query deformable decoder with iterative refinement (MapTR), shared by the models
that regress point sequences: LaneGAP (paths) and the piece-wise models.

Every instance (a path, a piece) is an instance query plus one point query per point (hierarchical
queries: the query of point j of instance i is instance_i + point_j). Each layer: decoupled
self-attention (MapTRv2: the instances attend to each other point index by point index, then the
points of each instance to each other), deformable attention over the BEV map, a feed-forward network;
then it refines the points (in inverse-sigmoid space, as Deformable DETR) and scores the instance.

Bezier variant: K control-point queries per instance; the curve is sampled at N points through the
Bernstein matrix, and each query reads the BEV features along the curve (LaneGAP's Bezier attention).

One-to-many group (MapTRv2's auxiliary one-to-many matching): extra instance queries that exist only in
training, matched to the ground truth repeated several times, so that every target trains several queries
a step; the instance self-attention keeps the two groups apart, so the one-to-one queries, the only ones
at inference, never see them.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from baselines.layers.attention import DeformableAttention
from baselines.layers.blocks import FeedForward, bernstein_matrix, combine_points, inverse_sigmoid, mlp
from baselines.layers.fine_bev import FineBEV

# Points are regressed in sigmoid space over the BEV map widened by this fraction on every side: lanes
# start and end on the crop's edge, which a sigmoid over exactly [0, 1] reaches only at infinity (the
# ends stopped metres short, and the evenly spaced points with them).
MARGIN = 0.1


def to_unit(w: torch.Tensor) -> torch.Tensor:
    """Sigmoid-space coordinates (0..1 over the widened map) -> unit coordinates of the BEV map."""
    return w * (1 + 2 * MARGIN) - MARGIN


def from_unit(uv: torch.Tensor) -> torch.Tensor:
    return (uv + MARGIN) / (1 + 2 * MARGIN)


def initial_lanes(num_instances: int, points: int) -> torch.Tensor:
    """(num_instances, points, 2) inverse-sigmoid coordinates of straight lanes along y, end to end of
    the map: instance i at u = (i // 2 + 0.5) / ceil(num_instances / 2), even ones driving forward
    (v from 1 to 0), odd ones backward."""
    lateral = (torch.arange(num_instances) // 2 + 0.5) / math.ceil(num_instances / 2)
    along = torch.linspace(1.0, 0.0, points)
    v = torch.where((torch.arange(num_instances) % 2 == 0)[:, None], along, along.flip(0))
    u = lateral[:, None].expand(-1, points)
    return inverse_sigmoid(from_unit(torch.stack([u, v], -1)))


class DecoderLayer(nn.Module):
    def __init__(self, dim: int, heads: int, ffn: int, dropout: float, deform_points: int, anchors: int,
                 points_per_instance: int, levels: int = 1):  # fmt: skip
        super().__init__()
        self.points_per_instance = points_per_instance
        self.instance_attn = nn.MultiheadAttention(dim, heads, dropout=dropout, batch_first=True)
        self.point_attn = nn.MultiheadAttention(dim, heads, dropout=dropout, batch_first=True)
        self.cross_attn = DeformableAttention(dim, heads, levels, points=deform_points, anchors=anchors)
        self.ffn = FeedForward(dim, ffn, dropout)
        self.norms = nn.ModuleList(nn.LayerNorm(dim) for _ in range(4))
        self.dropout = nn.Dropout(dropout)

    def forward(
        self, x: torch.Tensor, pos: torch.Tensor, anchors: torch.Tensor, levels: list[torch.Tensor],
        instance_mask: torch.Tensor | None = None,
    ) -> torch.Tensor:  # fmt: skip
        """x, pos (B, Q * N, C); anchors (B, Q * N, A, 2) unit coordinates; levels: BEV maps (B, C, H, W);
        instance_mask (Q, Q): True where instance i may not attend to instance j."""
        batch, tokens, dim = x.shape
        n = self.points_per_instance

        def by_point(t: torch.Tensor) -> torch.Tensor:  # (B, Q * N, C) -> (B * N, Q, C)
            return t.view(batch, -1, n, dim).transpose(1, 2).reshape(batch * n, -1, dim)

        q = by_point(x + pos)
        out = self.instance_attn(q, q, by_point(x), attn_mask=instance_mask, need_weights=False)[0]
        out = out.view(batch, n, -1, dim).transpose(1, 2).reshape(batch, tokens, dim)
        x = self.norms[0](x + self.dropout(out))
        q = (x + pos).view(-1, n, dim)
        out = self.point_attn(q, q, x.view(-1, n, dim), need_weights=False)[0]
        x = self.norms[1](x + self.dropout(out.reshape(batch, tokens, dim)))
        x = self.norms[2](x + self.dropout(self.cross_attn(x + pos, anchors, levels)))
        return self.norms[3](x + self.dropout(self.ffn(x)))


class QueryDecoder(nn.Module):
    """BEV features (B, C, H, W) -> per layer instance logits (L, B, Q) and points (L, B, Q, N, 2) in unit
    coordinates, and the last layer's instance features (B, Q, C): the mean of its point features. With a
    fine scale, the attention also reads the fine BEV level, and in training "fine" holds its auxiliary
    outputs (baselines/layers/fine_bev.py). With a one-to-many group, in training "many_logits" and
    "many_points" hold its outputs, as "logits" and "points"."""

    def __init__(self, dim: int, instances: int, points: int, bezier_points: int, layers: int, heads: int,
                 ffn: int, dropout: float, deform_points: int, fine_scale: float = 0.0,
                 one_to_many: int = 0):  # fmt: skip
        super().__init__()
        self.fine = FineBEV(dim, fine_scale) if fine_scale else None
        self.instances, self.one_to_many = instances, one_to_many
        total = instances + one_to_many
        self.bezier = bezier_points > 0
        self.queries_per_instance = bezier_points if self.bezier else points
        # Each embedding holds a content half and a positional half.
        self.instance_embedding = nn.Parameter(torch.randn(total, 2 * dim) * 0.02)
        self.point_embedding = nn.Parameter(torch.randn(self.queries_per_instance, 2 * dim) * 0.02)
        # Learned initial points of every query: straight lanes spread across the BEV width, alternately
        # driving forward and backward; lanes mostly run along the road, and starting there instead of
        # all at the centre speeds up training.
        lanes = [initial_lanes(n, self.queries_per_instance) for n in (instances, one_to_many) if n]
        self.initial_reference = nn.Parameter(torch.cat(lanes))
        # True (masked) between the two groups
        group = torch.arange(total) >= instances
        self.register_buffer("instance_mask", group[:, None] != group[None], False)
        anchors = bezier_points if self.bezier else 1
        levels = 2 if self.fine is not None else 1  # the coarse map, and the fine one
        self.layers = nn.ModuleList(
            DecoderLayer(dim, heads, ffn, dropout, deform_points, anchors, self.queries_per_instance, levels)
            for _ in range(layers)
        )
        self.class_heads = nn.ModuleList(mlp(dim, 1, 2) for _ in range(layers))
        self.point_heads = nn.ModuleList(mlp(dim, 2, 3) for _ in range(layers))
        for head in self.class_heads:  # start at a 1% probability, as focal-loss detectors do
            nn.init.constant_(head[-1].bias, -math.log(99.0))
        for head in self.point_heads:
            nn.init.zeros_(head[-1].weight)
            nn.init.zeros_(head[-1].bias)
        if self.bezier:
            self.register_buffer("bernstein", bernstein_matrix(points, bezier_points), False)
            # Anchors of the Bezier deformable attention: the curve at its K control parameters.
            self.register_buffer("anchor_basis", bernstein_matrix(bezier_points, bezier_points), False)

    def anchors(self, reference: torch.Tensor) -> torch.Tensor:
        """reference (B, Q*K, 2) unit coordinates -> the deformable attention's anchors (B, Q*K, A, 2)."""
        if not self.bezier:
            return reference.unsqueeze(2)
        batch, k = reference.shape[0], self.queries_per_instance
        curve = combine_points(self.anchor_basis, reference.view(batch, -1, k, 2))  # (B, Q, K, 2), fp32
        return curve.unsqueeze(2).expand(-1, -1, k, -1, -1).reshape(batch, -1, k, 2)

    def forward(self, bev: torch.Tensor) -> dict[str, torch.Tensor]:
        batch, dim = bev.shape[:2]
        levels, outputs = [bev], {}
        if self.fine is not None:
            fine, aux = self.fine(bev)
            levels.append(fine)
            if aux is not None:
                outputs["fine"] = aux
        # the one-to-many group only in training: the groups never meet, so leaving it out changes nothing
        instances = self.instances + (self.one_to_many if self.training else 0)
        mask = self.instance_mask if self.training and self.one_to_many else None
        queries = (self.instance_embedding[:instances, None] + self.point_embedding[None]).flatten(0, 1)
        x, pos = queries.unsqueeze(0).expand(batch, -1, -1).split(dim, dim=-1)
        reference = self.initial_reference[:instances].sigmoid().view(1, -1, 2).expand(batch, -1, -1)
        all_logits, all_points = [], []
        for layer, class_head, point_head in zip(self.layers, self.class_heads, self.point_heads):
            x = layer(x, pos, self.anchors(to_unit(reference)), levels, mask)
            refined = (point_head(x) + inverse_sigmoid(reference)).sigmoid()
            features = x.view(batch, instances, self.queries_per_instance, dim).mean(2)
            all_logits.append(class_head(features).squeeze(-1))
            points = refined.view(batch, instances, self.queries_per_instance, 2)
            # the curves in fp32 under autocast too (blocks.combine_points): they are the output's geometry
            all_points.append(to_unit(combine_points(self.bernstein, points) if self.bezier else points))
            reference = refined.detach()  # each layer refines the previous one's points
        logits, points, one = torch.stack(all_logits), torch.stack(all_points), self.instances
        if instances > one:
            outputs.update(many_logits=logits[:, :, one:], many_points=points[:, :, one:])
        outputs.update(logits=logits[:, :, :one], points=points[:, :, :one], features=features[:, :one])
        return outputs
