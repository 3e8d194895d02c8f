"""STSU (Can et al., "Structured Bird's-Eye-View Traffic Scene Understanding"), the piece-wise Bezier
baseline: its head config, the Bezier fit of its targets and its loss; the model and the
post-processing are the piece-wise ones (baselines/models/piecewise.py), which `build()` returns together.

The model: the shared BEV encoder and the shared query decoder in Bezier mode (4 control points per
piece through 6 layers that refine them, the same deformable attention over the BEV as LaneGAP's, so
that only the modelling differs) and the association head on the pieces' instance features. The loss:
Hungarian matching (2 x focal + 5 x L1 of the control points), sigmoid focal classification and L1 on
the matched control points at every layer, the association cross-entropy. The ground-truth control
points: a least-squares fit on arc-length samples of each prepared piece. The post-processing: the
curves sampled at `piece_points`, pieces and links through Piece2Graph.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import torch

from baselines.config import Config, Range
from baselines.layers.blocks import bernstein_basis, bernstein_matrix, combine_points
from baselines.models.base import Built, PieceHeadConfig, preset_head
from baselines.models.piecewise import PieceCriterion, PieceModel, PiecePostProcess, piece_needs


@dataclass
class STSUConfig(PieceHeadConfig):
    """The piece-wise models' shared settings (PieceHeadConfig; point_weight weighs the L1 of the control
    points, piece_points are the fitted pieces' points and the curves' samples) and STSU's own."""

    bezier_points: Annotated[int, Range(low=2)] = 4  # control points per piece (STSU: a cubic)


# Head sizes for a fair comparison: with the same encoder (camera), as many parameters as LaneGAP within
# 3 % (LaneGAP: 37,976,700 paper, 1,401,243 tiny), at LaneGAP's decoder widths (the Bezier
# attention's offsets per anchor add what the association head saves on LaneGAP's segmentation head).


def paper_head() -> STSUConfig:
    """38,037,667 parameters with the paper encoder (camera)."""
    return STSUConfig()


def gpu_head() -> STSUConfig:
    """The paper's head with what the CPU checks' short schedule needed and the 0.3 m BEV does not change
    (docs/EXPERIMENTS.md, 2026-12-06): score threshold 0.6 and duplicates suppressed within 3 m, the links'
    positive weight clamped at 10 (not the one-to-many group, which cost STSU 0.11 TOPO F1)."""
    return STSUConfig(score_threshold=0.6, duplicate_radius=3.0, max_link_pos_weight=10.0)


def tiny_head() -> STSUConfig:
    """1,430,842 parameters with the tiny encoder (camera); LaneGAP's tiny layers and widths, its fine BEV
    level (0.6 m cells, without which it barely learns in the CPU budget) and lane head, and MapTR's
    duplicate suppression within 3 m, score threshold 0.6 and links' positive weight clamped at 10
    (docs/EXPERIMENTS.md, 2026-12-04)."""
    return STSUConfig(
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
    )


def head(preset: str) -> STSUConfig:
    """STSU's head config of a preset (`baselines.models.HEADS`)."""
    return preset_head("STSU", {"paper": paper_head, "tiny": tiny_head, "gpu": gpu_head}, preset)


def arc_length_parameters(points: torch.Tensor) -> torch.Tensor:
    """Polylines (..., n, 2) -> (..., n) the fraction of the length travelled at each point; evenly
    spaced for a polyline of no length."""
    steps = (points[..., 1:, :] - points[..., :-1, :]).norm(dim=-1)
    arc = torch.cat([torch.zeros_like(steps[..., :1]), steps.cumsum(-1)], -1)
    even = torch.linspace(0, 1, points.shape[-2], dtype=points.dtype, device=points.device)
    length = arc[..., -1:]
    return torch.where(length > 0, arc / length.clamp(min=1e-12), even)


def fit_bezier(points: torch.Tensor, num_controls: int) -> torch.Tensor:
    """Polylines (..., n, 2) -> (..., K, 2) control points of the Bezier curve nearest in least squares
    to the points at their arc-length parameters, with the first and last control points on the
    polyline's ends: a piece's ends are the graph's vertices, and a free fit would move every junction
    by its residual."""
    dtype = points.dtype
    points = points.double()
    basis = bernstein_basis(arc_length_parameters(points), num_controls)  # (..., n, K)
    first, last = points[..., :1, :], points[..., -1:, :]
    residual = points - basis[..., :1] * first - basis[..., -1:] * last
    inner = torch.linalg.pinv(basis[..., 1:-1]) @ residual  # (..., K - 2, 2)
    return torch.cat([first, inner, last], -2).to(dtype)


class STSULoss(PieceCriterion):
    """The piece-wise criterion on control points: the predicted ones (the decoder returns its curves
    sampled at N points) against those fitted to the prepared pieces."""

    def __init__(self, config: Config):
        super().__init__(config)
        head = config.decoder
        # The decoder returns B @ controls with B the (N, K) Bernstein matrix of full column rank, so
        # pinv(B) recovers the controls exactly (and passes their gradient).
        controls = torch.linalg.pinv(bernstein_matrix(head.piece_points, head.bezier_points).double())
        self.register_buffer("controls", controls.float(), persistent=False)

    def geometry(self, points: torch.Tensor) -> torch.Tensor:
        return combine_points(self.controls, points)  # in fp32, never TF32

    def target_geometry(self, pieces: torch.Tensor) -> torch.Tensor:
        return fit_bezier(pieces, self.head.bezier_points)


def build(config: Config) -> Built:
    model = PieceModel(config, config.decoder.bezier_points)
    return Built(model, STSULoss(config), PiecePostProcess(config), piece_needs(config), "piece")
