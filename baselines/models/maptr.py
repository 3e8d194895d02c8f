"""MapTR (Liao et al.), the piece-wise polyline baseline: its head config; the model, loss and
post-processing are the piece-wise ones (baselines/models/piecewise.py), which `build()` returns together.

The model: the shared BEV encoder and the hierarchical-query decoder (the one LaneGAP uses) regressing
every piece as 20 ordered points, one ordering only since pieces are directed, plus STSU's association
head on each piece's instance feature (the mean of its point features). The loss: MapTR's focal
classification (2.0), point L1 (5.0) and direction cosine (0.005) at every layer, and the association
cross-entropy. The post-processing: pieces and links through Piece2Graph.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from baselines.config import AT_LEAST_0, Config
from baselines.models.base import Built, PieceHeadConfig, preset_head
from baselines.models.piecewise import PieceCriterion, PieceModel, PiecePostProcess, piece_needs


@dataclass
class MapTRConfig(PieceHeadConfig):
    """The piece-wise models' shared settings (PieceHeadConfig) and MapTR's own."""

    direction_weight: Annotated[float, AT_LEAST_0] = 0.005


# Head sizes for a fair comparison: with the same encoder (camera), as many parameters as LaneGAP within
# 3 % (LaneGAP: 37,976,700 paper, 1,401,243 tiny). Its decoder is LaneGAP's at the same widths; the
# association head (about 0.2 M / 12 k) takes the place of LaneGAP's auxiliary segmentation head.


def paper_head() -> MapTRConfig:
    """37,604,963 parameters with the paper encoder (camera)."""
    return MapTRConfig()


def gpu_head() -> MapTRConfig:
    """The paper's head with what the CPU checks' short schedule needed and the 0.3 m BEV does not change
    (docs/EXPERIMENTS.md, 2026-12-06): score threshold 0.6 and duplicates suppressed within 3 m, the links'
    positive weight clamped at 10, and MapTRv2's one-to-many group (as many training-only queries as the
    100 of inference, the targets repeated 3 times)."""
    return MapTRConfig(score_threshold=0.6, duplicate_radius=3.0, max_link_pos_weight=10.0,
                       one_to_many_pieces=100)  # fmt: skip


def tiny_head() -> MapTRConfig:
    """1,384,730 parameters with the tiny encoder (camera), 6,720 of them used in training only; the layers
    and widths of LaneGAP's tiny head, its fine BEV level (0.6 m cells, without which it barely learns in
    the CPU budget) and its lane head (the points snapped onto its lane centres within 1 m), 40 queries
    for at most 29 pieces a frame in the synthetic data. 880 steps leave several queries on some lanes,
    half of the copies driving it the wrong way: duplicates are suppressed within 3 m, and the score
    threshold is 0.6, both chosen on the learning check's training frames; the links' positive weight is
    clamped at 10, so that the association loss disturbs the shared decoder less; MapTRv2's one-to-many
    matching (40 more queries in training, the targets repeated 3 times) (docs/EXPERIMENTS.md,
    2026-12-04)."""
    return MapTRConfig(
        num_pieces=40,
        layers=3,
        heads=4,
        ffn_channels=128,
        dropout=0.0,
        score_threshold=0.6,
        fine_scale=2.5,
        lane_head_width=12,
        duplicate_radius=3.0,
        max_link_pos_weight=10.0,
        one_to_many_pieces=40,
    )


def head(preset: str) -> MapTRConfig:
    """MapTR's head config of a preset (`baselines.models.HEADS`)."""
    return preset_head("MapTR", {"paper": paper_head, "tiny": tiny_head, "gpu": gpu_head}, preset)


def build(config: Config) -> Built:
    loss = PieceCriterion(config, config.decoder.direction_weight)
    return Built(PieceModel(config), loss, PiecePostProcess(config), piece_needs(config), "piece")
