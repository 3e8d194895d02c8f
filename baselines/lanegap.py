"""LaneGAP (Liao et al., "Lane Graph as Path"): the path decoder, its loss and its post-processing.

A MapTR-style decoder: every path is an instance query plus one point query per point (hierarchical
queries); 6 layers of self-attention, deformable attention over the shared BEV map and a feed-forward
network; each layer refines the points (iterative refinement in inverse-sigmoid space) and scores
the path. Coordinates are unit coordinates of the BEV map (see `EncoderConfig.metres_to_unit`).

Bezier variant: K control-point queries per path; the path is the Bezier curve sampled at N points
through the Bernstein matrix (paper Eq. 2), and each query reads the BEV features along the curve.
"""

from __future__ import annotations

import math

import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import nn

from baselines.attention import DeformableAttention, inverse_sigmoid
from baselines.config import Config, DecoderConfig
from baselines.encoder import BEVEncoder, FeedForward, SensorBatch
from baselines.matcher import hungarian_match

MODELING = "path"  # the paper's family: pixel-wise, piece-wise or path-wise


def bernstein_matrix(num_points: int, num_controls: int) -> torch.Tensor:
    """(num_points, num_controls): row i is the Bernstein basis of degree K - 1 at t_i = i / (N - 1),
    so `matrix @ controls` samples the curve at N evenly spaced parameters (paper Eq. 2)."""
    degree = num_controls - 1
    t = torch.linspace(0, 1, num_points, dtype=torch.float64).unsqueeze(1)
    k = torch.arange(num_controls, dtype=torch.float64).unsqueeze(0)
    binomial = torch.tensor([math.comb(degree, j) for j in range(num_controls)], dtype=torch.float64)
    return (binomial * t**k * (1 - t) ** (degree - k)).float()


def initial_lanes(num_paths: int, points: int) -> torch.Tensor:
    """(num_paths, points, 2) inverse-sigmoid unit coordinates of straight lanes along y: path i at
    u = (i // 2 + 0.5) / ceil(num_paths / 2), even paths driving forward (v from 1 to 0), odd backward."""
    lateral = (torch.arange(num_paths) // 2 + 0.5) / math.ceil(num_paths / 2)
    along = torch.linspace(0.95, 0.05, points)
    v = torch.where((torch.arange(num_paths) % 2 == 0)[:, None], along, along.flip(0))
    u = lateral[:, None].expand(-1, points)
    return inverse_sigmoid(torch.stack([u, v], -1))


def mlp(dim: int, out: int, layers: int = 3) -> nn.Sequential:
    modules: list[nn.Module] = []
    for _ in range(layers - 1):
        modules += [nn.Linear(dim, dim), nn.ReLU(True)]
    return nn.Sequential(*modules, nn.Linear(dim, out))


class PathDecoderLayer(nn.Module):
    def __init__(self, dim: int, config: DecoderConfig, anchors: int):
        super().__init__()
        self.self_attn = nn.MultiheadAttention(dim, config.heads, dropout=config.dropout, batch_first=True)
        self.cross_attn = DeformableAttention(
            dim, config.heads, levels=1, points=config.deform_points, anchors=anchors
        )
        self.ffn = FeedForward(dim, config.ffn_channels, config.dropout)
        self.norms = nn.ModuleList(nn.LayerNorm(dim) for _ in range(3))
        self.dropout = nn.Dropout(config.dropout)

    def forward(
        self, x: torch.Tensor, pos: torch.Tensor, anchors: torch.Tensor, bev: torch.Tensor
    ) -> torch.Tensor:
        q = x + pos
        x = self.norms[0](x + self.dropout(self.self_attn(q, q, x, need_weights=False)[0]))
        x = self.norms[1](x + self.dropout(self.cross_attn(x + pos, anchors, [bev])))
        return self.norms[2](x + self.dropout(self.ffn(x)))


class LaneGAP(nn.Module):
    """Sensors -> per decoder layer: path logits (L, B, Q) and path points (L, B, Q, N, 2), plus the
    auxiliary BEV segmentation logits (B, 2, H, W) in training."""

    def __init__(self, config: Config):
        super().__init__()
        self.config = config
        decoder = config.decoder
        dim = config.encoder.channels
        self.encoder = BEVEncoder(config.encoder)
        self.num_paths = decoder.num_paths
        self.bezier = decoder.bezier_points > 0
        self.queries_per_path = decoder.bezier_points if self.bezier else decoder.path_points
        # Each embedding holds a content half and a positional half (MapTR's hierarchical queries:
        # the query of point j of path i is instance_i + point_j).
        self.instance_embedding = nn.Parameter(torch.randn(decoder.num_paths, 2 * dim) * 0.02)
        self.point_embedding = nn.Parameter(torch.randn(self.queries_per_path, 2 * dim) * 0.02)
        # Learned initial points of every path query, in inverse-sigmoid space. They start as straight
        # lanes spread across the BEV width, alternately driving forward and backward: paths mostly
        # run along the road, and starting there instead of all at the centre speeds up training.
        self.initial_reference = nn.Parameter(initial_lanes(decoder.num_paths, self.queries_per_path))
        anchors = decoder.bezier_points if self.bezier else 1
        self.layers = nn.ModuleList(PathDecoderLayer(dim, decoder, anchors) for _ in range(decoder.layers))
        self.class_heads = nn.ModuleList(mlp(dim, 1, 2) for _ in range(decoder.layers))
        self.point_heads = nn.ModuleList(mlp(dim, 2, 3) for _ in range(decoder.layers))
        for head in self.class_heads:  # start at a 1% path probability, as focal-loss detectors do
            nn.init.constant_(head[-1].bias, -math.log(99.0))
        for head in self.point_heads:
            nn.init.zeros_(head[-1].weight)
            nn.init.zeros_(head[-1].bias)
        if self.bezier:
            self.register_buffer(
                "bernstein", bernstein_matrix(decoder.path_points, decoder.bezier_points), False
            )
            # Anchors of the Bezier deformable attention: the curve at its K control parameters.
            self.register_buffer(
                "anchor_basis", bernstein_matrix(decoder.bezier_points, decoder.bezier_points), False
            )
        self.seg_head = (
            nn.Sequential(nn.Conv2d(dim, dim, 3, padding=1), nn.ReLU(True), nn.Conv2d(dim, 2, 1))
            if decoder.aux_seg
            else None
        )

    def anchors(self, reference: torch.Tensor) -> torch.Tensor:
        """reference (B, Q*K, 2) -> the deformable attention's anchors (B, Q*K, anchors, 2)."""
        if not self.bezier:
            return reference.unsqueeze(2)
        batch = reference.shape[0]
        controls = reference.view(batch, self.num_paths, self.queries_per_path, 2)
        curve = self.anchor_basis @ controls  # (B, Q, K, 2): points along each path's curve
        expanded = curve.unsqueeze(2).expand(-1, -1, self.queries_per_path, -1, -1)
        return expanded.reshape(batch, -1, self.queries_per_path, 2)

    def forward(self, batch: SensorBatch) -> dict[str, torch.Tensor]:
        return self.decode(self.encoder(batch))

    def decode(self, bev: torch.Tensor) -> dict[str, torch.Tensor]:
        """BEV features (B, C, H, W) -> the outputs of `forward`."""
        num_batch, dim = bev.shape[:2]
        queries = (self.instance_embedding[:, None] + self.point_embedding[None]).flatten(0, 1)
        content, pos = queries.unsqueeze(0).expand(num_batch, -1, -1).split(dim, dim=-1)
        reference = self.initial_reference.sigmoid().view(1, -1, 2).expand(num_batch, -1, -1)
        x = content
        all_logits, all_points = [], []
        for layer, class_head, point_head in zip(
            self.layers, self.class_heads, self.point_heads, strict=True
        ):
            x = layer(x, pos, self.anchors(reference), bev)
            refined = (point_head(x) + inverse_sigmoid(reference)).sigmoid()
            per_path = x.view(num_batch, self.num_paths, self.queries_per_path, dim)
            all_logits.append(class_head(per_path.mean(2)).squeeze(-1))
            points = refined.view(num_batch, self.num_paths, self.queries_per_path, 2)
            all_points.append(self.bernstein @ points if self.bezier else points)
            reference = refined.detach()  # each layer refines the previous one's points (as Deformable DETR)
        outputs = {"logits": torch.stack(all_logits), "points": torch.stack(all_points)}
        if self.seg_head is not None and self.training:
            outputs["seg"] = self.seg_head(bev)
        return outputs


def sigmoid_focal_loss(
    logits: torch.Tensor, labels: torch.Tensor, alpha: float, gamma: float
) -> torch.Tensor:
    prob = logits.sigmoid()
    ce = F.binary_cross_entropy_with_logits(logits, labels, reduction="none")
    p_t = prob * labels + (1 - prob) * (1 - labels)
    alpha_t = alpha * labels + (1 - alpha) * (1 - labels)
    return (alpha_t * (1 - p_t) ** gamma * ce).sum()


class LaneGAPLoss(nn.Module):
    """Paper Eq. 3 and 4 on every decoder layer: Hungarian matching, focal classification loss, L1 on
    the matched paths' ordered points, and the auxiliary BEV segmentation cross-entropy."""

    def __init__(self, config: DecoderConfig):
        super().__init__()
        self.config = config

    def forward(
        self, outputs: dict[str, torch.Tensor], targets: list[torch.Tensor], seg_target: torch.Tensor | None
    ) -> dict[str, torch.Tensor]:
        """targets: per frame (G, N, 2) unit path points; seg_target (B, H, W) long, -100 = ignore."""
        config = self.config
        logits_per_layer, points_per_layer = outputs["logits"], outputs["points"]
        device = logits_per_layer.device
        # Normalise by the number of ground-truth paths over all processes (as DETR).
        num_targets = torch.tensor(float(sum(len(t) for t in targets)), device=device)
        if dist.is_available() and dist.is_initialized():
            dist.all_reduce(num_targets)
            num_targets = num_targets / dist.get_world_size()
        num_targets = num_targets.clamp(min=1.0)
        total = torch.zeros((), device=device)
        for logits, points in zip(logits_per_layer, points_per_layer, strict=True):
            labels = torch.zeros_like(logits, dtype=torch.float32)
            point_loss = torch.zeros((), device=device)
            for frame, target in enumerate(targets):
                rows, cols = hungarian_match(
                    logits[frame].detach(),
                    points[frame].detach(),
                    target,
                    config.cls_weight,
                    config.point_weight,
                    config.focal_alpha,
                    config.focal_gamma,
                )
                labels[frame, rows.to(device)] = 1.0
                matched = points[frame, rows.to(device)].float() - target[cols.to(device)]
                point_loss = point_loss + matched.abs().sum(-1).mean(-1).sum()
            class_loss = sigmoid_focal_loss(logits.float(), labels, config.focal_alpha, config.focal_gamma)
            class_loss = class_loss / num_targets
            point_loss = point_loss / num_targets
            total = total + config.cls_weight * class_loss + config.point_weight * point_loss
        losses = {"cls": class_loss.detach(), "points": point_loss.detach()}
        if "seg" in outputs and seg_target is not None:
            seg_loss = F.cross_entropy(outputs["seg"].float(), seg_target, ignore_index=-100)
            seg_loss = torch.nan_to_num(seg_loss)  # a batch with no labelled cell
            total = total + config.seg_weight * seg_loss
            losses["seg"] = seg_loss.detach()
        losses["loss"] = total
        return losses


@torch.no_grad()
def select_paths(
    outputs: dict[str, torch.Tensor], threshold: float
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Last decoder layer -> per frame (scores (P,), points (P, N, 2) unit) of paths scoring > threshold,
    best first."""
    scores = outputs["logits"][-1].float().sigmoid()
    points = outputs["points"][-1].float()
    selected = []
    for frame_scores, frame_points in zip(scores, points, strict=True):
        keep = (frame_scores > threshold).nonzero().squeeze(1)
        order = keep[frame_scores[keep].argsort(descending=True)]
        selected.append((frame_scores[order].cpu(), frame_points[order].cpu()))
    return selected
