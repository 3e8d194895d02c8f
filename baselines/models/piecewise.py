"""What the piece-wise baselines (MapTR: polylines, STSU: Bezier curves) share: the model, its
association head, the criterion and the post-processing through Piece2Graph.

A piece is a maximal lane stretch between junctions (docs/guide/prepare.md); a lane graph is its pieces plus
the links "piece i ends where piece j starts". The model: the shared BEV encoder, the shared query decoder
regressing every piece in driving order, and STSU's association head scoring every ordered pair of
queries as a link. The criterion (DETR's SetCriterion): per decoder layer, Hungarian matching, focal
classification and L1 on the matched pieces; on the last layer, binary cross-entropy of the matched
pairs' association logits against the prepared `piece_links`; with a fine BEV level (the tiny preset),
its lane and direction loss (fine_bev.py).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from baselines.config import Config
from baselines.layers.bev_encoder import BEVEncoder, SensorBatch
from baselines.layers.blocks import count, mean_over_processes, mlp, sigmoid_focal_loss
from baselines.layers.fine_bev import fine_losses
from baselines.layers.matcher import match_layers
from baselines.layers.query_decoder import QueryDecoder
from baselines.layers.raster_head import (
    lane_head,
    lane_head_losses,
    lane_outputs,
    lane_probability,
    snap_polylines,
)
from baselines.layers.targets import Targets
from benchmark.graphs.piece2graph import piece2graph, piece2graph_scored, suppress_duplicates
from pipeline.lane_graph import LaneGraph


class AssociationHead(nn.Module):
    """Instance features (B, Q, C) -> (B, Q, Q) logits of "piece i ends where piece j starts": an MLP on
    the concatenated features [f_i, f_j] of every ordered pair (STSU)."""

    def __init__(self, dim: int):
        super().__init__()
        self.first = nn.Linear(2 * dim, dim)
        self.rest = mlp(dim, 1, 2)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        # first([f_i, f_j]) = W_i f_i + W_j f_j + b: two (B, Q, C) products broadcast over the pairs
        # instead of a (B, Q, Q, 2C) concatenation, Q times less work and memory for the same MLP
        w_i, w_j = self.first.weight.split(features.shape[-1], dim=1)
        hidden = F.linear(features, w_i, self.first.bias)[:, :, None] + F.linear(features, w_j)[:, None]
        return self.rest(hidden.relu()).squeeze(-1)


class PieceModel(nn.Module):
    """Sensors -> per decoder layer piece logits (L, B, Q) and points (L, B, Q, N, 2) in unit coordinates
    (N = piece_points; a Bezier decoder samples its curves there), the last layer's instance features
    (B, Q, C) and the association logits "links" (B, Q, Q)."""

    def __init__(self, config: Config, bezier_points: int = 0):
        super().__init__()
        head = config.decoder
        dim = config.encoder.channels
        self.encoder = BEVEncoder(config.encoder)
        self.decoder = QueryDecoder(
            dim, head.num_pieces, head.piece_points, bezier_points, head.layers, head.heads,
            head.ffn_channels, head.dropout, head.deform_points, head.fine_scale, head.one_to_many_pieces,
        )  # fmt: skip
        self.association = AssociationHead(dim)
        self.lane_head = lane_head(config)

    def forward(self, batch: SensorBatch) -> dict[str, torch.Tensor]:
        return self.decode(self.encoder(batch))

    def decode(self, bev: torch.Tensor) -> dict[str, torch.Tensor]:
        """BEV features (B, C, H, W) -> the outputs of `forward`."""
        outputs = self.decoder(bev)
        outputs["links"] = self.association(outputs["features"])
        if self.lane_head is not None:
            outputs.update(lane_outputs(self.lane_head, bev))
        return outputs


def association_targets(cols: torch.Tensor, links: torch.Tensor, num_pieces: int) -> torch.Tensor:
    """cols (M,): the target piece of each matched query; links (L, 2) (src, dst) target pieces ->
    (M, M) 0 / 1: 1 where matched query a's piece ends where matched query b's piece starts."""
    adjacency = torch.zeros(num_pieces, num_pieces, device=cols.device)
    adjacency[links[:, 0], links[:, 1]] = 1.0
    return adjacency[cols][:, cols]


def association_loss(
    logits: torch.Tensor, matches: list[tuple[torch.Tensor, torch.Tensor]], targets: Targets,
    max_pos_weight: float,
) -> torch.Tensor:  # fmt: skip
    """Binary cross-entropy of the association logits (B, Q, Q) of every ordered pair of matched queries
    (the pair of a query with itself too: a piece may close a loop) against the prepared links.

    Links are rare (about one per piece among the M^2 pairs of M pieces), so the positives are weighted
    by negatives / positives of the batch (over all processes), clamped to [1, max_pos_weight]: below the
    clamp the links and the non-links weigh about the same in total, and a batch with a handful of links
    does not get an extreme weight. The tiny heads clamp lower, at 10, so that the links disturb the
    shared decoder less (docs/EXPERIMENTS.md, 2026-12-04). The mean is over the batch's matched
    pairs."""
    pair_logits, labels = [], []
    for frame, (rows, cols) in enumerate(matches):
        pair_logits.append(logits[frame][rows][:, rows].flatten())
        pieces = len(targets.pieces[frame])
        labels.append(association_targets(cols, targets.piece_links[frame], pieces).flatten())
    pair_logits, labels = torch.cat(pair_logits).float(), torch.cat(labels)
    pairs, positives = mean_over_processes(torch.stack([count(len(labels), labels.device), labels.sum()]))
    pos_weight = ((pairs - positives) / positives.clamp(min=1.0)).clamp(1.0, max_pos_weight)
    loss = F.binary_cross_entropy_with_logits(pair_logits, labels, pos_weight=pos_weight, reduction="sum")
    return loss / pairs.clamp(min=1.0)


def direction_loss(points: torch.Tensor, targets: torch.Tensor, extent: torch.Tensor) -> torch.Tensor:
    """MapTR's direction loss, summed: 1 - cosine between the predicted and the target vectors of
    consecutive points (M, N, 2), in metres (unit coordinates stretch x and y differently)."""
    predicted = (points[:, 1:] - points[:, :-1]) * extent
    target = (targets[:, 1:] - targets[:, :-1]) * extent
    return (1 - F.cosine_similarity(predicted, target, dim=-1)).sum()


class PieceCriterion(nn.Module):
    """Every decoder layer: Hungarian matching (cls_weight x focal + point_weight x ordered L1), focal
    classification, L1 on the matched pieces and, with a direction weight (MapTR), the direction loss;
    the last layer: the association loss of its matched pairs. All but the association are summed over
    the matched pieces and divided by the number of target pieces (over all processes), as LaneGAP.

    What the L1 and the matching compare is each model's `geometry` of a piece: the N points as they are
    (MapTR) or the Bezier control points (STSU, which overrides `geometry` and `target_geometry`)."""

    def __init__(self, config: Config, direction_weight: float = 0.0):
        super().__init__()
        self.head = config.decoder
        self.direction_weight = direction_weight
        (x0, x1), (y0, y1) = config.encoder.x_range, config.encoder.y_range
        self.register_buffer("extent", torch.tensor([x1 - x0, y1 - y0]), persistent=False)

    def geometry(self, points: torch.Tensor) -> torch.Tensor:
        """Predicted points (..., N, 2) -> what is matched and regressed."""
        return points

    def target_geometry(self, pieces: torch.Tensor) -> torch.Tensor:
        """Prepared pieces (G, n, 2) -> what is matched and regressed."""
        return pieces

    def set_losses(
        self, all_logits: torch.Tensor, all_points: torch.Tensor, goals: list[torch.Tensor], targets: Targets,
        num_targets: torch.Tensor, repeats: int = 1,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor], list[tuple[torch.Tensor, torch.Tensor]]]:  # fmt: skip
        """Every layer's (L, B, Q) logits and (L, B, Q, N, 2) points against the targets, each repeated
        `repeats` times -> the weighted sum over the layers, the last layer's terms and its matches."""
        head, device = self.head, all_logits.device
        total = torch.zeros((), device=device)
        all_regressed = self.geometry(all_points.float())
        goals = [goal.repeat(repeats, 1, 1) for goal in goals]
        all_matches = match_layers(all_logits.detach(), all_regressed.detach(), goals, head.cls_weight,
                                   head.point_weight, head.focal_alpha, head.focal_gamma)  # fmt: skip
        for logits, points, regressed, matches in zip(all_logits, all_points, all_regressed, all_matches,
                                                      strict=True):  # fmt: skip
            points = points.float()
            labels = torch.zeros_like(logits, dtype=torch.float32)
            point_loss = torch.zeros((), device=device)
            dir_loss = torch.zeros((), device=device)
            for frame, (goal, (rows, cols)) in enumerate(zip(goals, matches, strict=True)):
                labels[frame, rows] = 1.0
                point_loss = point_loss + (regressed[frame, rows] - goal[cols]).abs().sum(-1).mean(-1).sum()
                if self.direction_weight:
                    target = targets.pieces[frame][cols % len(targets.pieces[frame])].float()
                    dir_loss = dir_loss + direction_loss(points[frame, rows], target, self.extent)
            class_loss = sigmoid_focal_loss(logits.float(), labels, head.focal_alpha, head.focal_gamma)
            normaliser = num_targets * repeats
            terms = {"cls": class_loss / normaliser, "points": point_loss / normaliser}
            total = total + head.cls_weight * terms["cls"] + head.point_weight * terms["points"]
            if self.direction_weight:
                terms["direction"] = dir_loss / normaliser
                total = total + self.direction_weight * terms["direction"]
        return total, terms, matches

    def forward(self, outputs: dict[str, torch.Tensor], targets: Targets) -> dict[str, torch.Tensor]:
        head = self.head
        device = outputs["logits"].device
        goals = [self.target_geometry(p.float()) for p in targets.pieces]
        pieces = count(sum(len(p) for p in targets.pieces), device)
        num_targets = mean_over_processes(pieces).clamp(min=1.0)
        total, terms, matches = self.set_losses(
            outputs["logits"], outputs["points"], goals, targets, num_targets
        )
        losses = {name: term.detach() for name, term in terms.items()}
        if "many_logits" in outputs:
            many, many_terms, _ = self.set_losses(
                outputs["many_logits"], outputs["many_points"], goals, targets, num_targets,
                head.one_to_many_repeats,
            )  # fmt: skip
            total = total + head.one_to_many_weight * many
            losses["many_points"] = many_terms["points"].detach()
        link_loss = association_loss(outputs["links"], matches, targets, head.max_link_pos_weight)
        total = total + head.link_weight * link_loss
        losses["links"] = link_loss.detach()
        if "fine" in outputs:
            fine = fine_losses(outputs["fine"], targets)
            total = total + head.fine_weight * sum(fine.values())
            losses.update({name: loss.detach() for name, loss in fine.items()})
        if "lane_seg" in outputs:
            lane = lane_head_losses(outputs, targets)
            total = total + head.lane_weight * sum(lane.values())
            losses.update({name: loss.detach() for name, loss in lane.items()})
        losses["loss"] = total
        return losses


def piece_needs(config: Config) -> frozenset[str]:
    """The prepared tables a piece-wise model trains on: the pieces and their links, and the rasters
    with a fine BEV level or a lane head."""
    return frozenset({"pieces", "raster"} if config.decoder.needs_raster else {"pieces"})


class PiecePostProcess:
    """Outputs -> one lane graph per frame: the pieces scoring above the score threshold, in metres, less
    those that duplicate a higher-scoring one (with a duplicate radius), and the links i -> j among them
    whose association probability passes the link threshold, through Piece2Graph (which joins linked
    ends at their mean); `scored` adds each edge's score (a ScoredPostProcess)."""

    def __init__(self, config: Config):
        self.encoder, self.head = config.encoder, config.decoder

    @torch.no_grad()
    def __call__(self, outputs: dict[str, torch.Tensor]) -> list[LaneGraph]:
        return [piece2graph(pieces, pairs) for pieces, pairs, _ in self.kept(outputs)]

    def scored(self, outputs: dict[str, torch.Tensor]) -> list[tuple[LaneGraph, np.ndarray]]:
        """Per frame (the graph `__call__` gives, each edge's score): the highest score among the kept
        pieces that give it (piece2graph_scored; every kept piece is above the threshold already)."""
        return [piece2graph_scored(pieces, pairs, scores, piece_threshold=0.0)
                for pieces, pairs, scores in self.kept(outputs)]  # fmt: skip

    @torch.no_grad()
    def kept(self, outputs: dict[str, torch.Tensor]) -> list[tuple[list[np.ndarray], np.ndarray, np.ndarray]]:
        """Per frame the kept pieces in metres, their links (L, 2) and their scores."""
        head = self.head
        scores = outputs["logits"][-1].float().sigmoid().cpu()
        points = outputs["points"][-1].float().cpu()
        links = outputs["links"].float().sigmoid().cpu()
        probability = lane_probability(outputs)
        kept = []
        frames = zip(scores, points, links, strict=True)
        for frame, (frame_scores, frame_points, frame_links) in enumerate(frames):
            keep = (frame_scores > head.score_threshold).nonzero().squeeze(1)
            pieces = [self.encoder.polyline_to_metres(p.numpy()) for p in frame_points[keep]]
            if probability is not None:
                pieces = snap_polylines(pieces, probability[frame], self.encoder, head.snap_radius)
            distinct = suppress_duplicates(
                pieces, frame_scores[keep].numpy(), head.duplicate_radius, head.duplicate_overlap
            )
            keep = keep[torch.from_numpy(distinct)]
            pieces = [pieces[i] for i in distinct]
            pairs = (frame_links[keep][:, keep] > head.link_threshold).nonzero().numpy()
            kept.append((pieces, pairs, frame_scores[keep].numpy()))
        return kept
