"""What every model module shares: the `Built` record that its `build(config)` returns, the lookup of
its head config by preset, the settings that the query models' heads (LaneGAP, MapTR, STSU) share, and
those that the piece-wise ones (MapTR, STSU) share."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, Protocol, runtime_checkable

from torch import nn

from baselines.config import (
    AT_LEAST_0,
    AT_LEAST_1,
    FRACTION,
    POSITIVE,
    PROBABILITY,
    EncoderConfig,
    Range,
    divisible,
)

if TYPE_CHECKING:
    import numpy as np

    from pipeline.lane_graph import LaneGraph


@runtime_checkable
class ScoredPostProcess(Protocol):
    """A post-processing that also gives each graph edge a score from the model's instance scores (LaneGAP's
    paths, MapTR's and STSU's pieces); HDMapNet's rasters have none."""

    def __call__(self, outputs: dict) -> list[LaneGraph]: ...

    def scored(self, outputs: dict) -> list[tuple[LaneGraph, np.ndarray]]:
        """outputs -> per frame (the very graph `__call__` gives, one score per edge in its src / dst
        order)."""
        ...


@dataclass
class Built:
    model: nn.Module  # SensorBatch -> dict of output tensors
    loss: nn.Module  # (outputs, Targets) -> dict of losses; "loss" is the total, the rest logged
    to_graphs: Callable  # outputs -> one LaneGraph (metres, BEV frame) per frame of the batch
    needs: frozenset[str]  # targets it trains on: "paths", "pieces" (+ links), "raster" (mask + direction)
    modeling: str  # the paper's family: "pixel", "piece" or "path"

    @property
    def scored_graphs(self) -> Callable | None:
        """outputs -> per frame (graph, its edges' scores) where the post-processing keeps the model's
        instance scores (ScoredPostProcess), else None."""
        return self.to_graphs.scored if isinstance(self.to_graphs, ScoredPostProcess) else None

    def to(self, device) -> Built:
        """The model and its loss on `device` together: a loss holds buffers too (piece extents, STSU's
        Bezier inverse) that must sit beside the outputs it reads."""
        self.model.to(device)
        self.loss.to(device)
        return self


def preset_head(model: str, heads: dict, preset: str):
    """`heads[preset]()`, or a clear error naming the model and the presets it has."""
    if preset not in heads:
        raise ValueError(f"{model} has no head size for preset {preset!r}: expected {', '.join(heads)}")
    return heads[preset]()


@dataclass
class QueryHeadConfig:
    """The hierarchical-query decoder (baselines/layers/query_decoder.py) and its set loss, as LaneGAP's,
    MapTR's and STSU's heads share them; each adds its own instance count (`num_paths`,
    `num_pieces`) and the rest of its modelling."""

    layers: Annotated[int, AT_LEAST_1] = 6
    heads: Annotated[int, AT_LEAST_1] = 8
    ffn_channels: Annotated[int, AT_LEAST_1] = 512
    # samples per head (per anchor) in the deformable cross-attention
    deform_points: Annotated[int, AT_LEAST_1] = 4
    dropout: Annotated[float, FRACTION] = 0.1
    # 0: off; s: the decoder also reads the BEV features lifted to cells s times smaller, which a dense
    # lane and direction loss on the prepared rasters trains (baselines/layers/fine_bev.py; the tiny presets')
    fine_scale: Annotated[float, AT_LEAST_0] = 0.0
    fine_weight: Annotated[float, AT_LEAST_0] = 1.0
    # 0: off; w: HDMapNet's head of width w on the BEV (baselines/layers/raster_head.py; the tiny presets'),
    # trained on the prepared rasters, whose lane probability moves the regressed points up to
    # snap_radius m across their polyline onto their lane's centre
    lane_head_width: Annotated[int, AT_LEAST_0] = 0
    # metres per cell of its raster (a whole multiple of the prepared 0.15)
    lane_head_resolution: Annotated[float, POSITIVE] = 0.3
    lane_weight: Annotated[float, AT_LEAST_0] = 1.0
    snap_radius: Annotated[float, AT_LEAST_0] = 1.0
    # focal classification, in the loss and in the Hungarian matching's cost
    cls_weight: Annotated[float, AT_LEAST_0] = 2.0
    # L1 of the matched instances' points (STSU: of their control points)
    point_weight: Annotated[float, AT_LEAST_0] = 5.0
    focal_alpha: Annotated[float, PROBABILITY] = 0.25
    focal_gamma: Annotated[float, AT_LEAST_0] = 2.0
    score_threshold: Annotated[float, PROBABILITY] = 0.4  # instances kept at inference

    def problem(self, encoder: EncoderConfig) -> str | None:
        """What the decoder's build would assert of its fields with the encoder's (Config.check_across)."""
        return divisible(encoder.channels, "encoder.channels", self.heads, "decoder.heads")

    @property
    def needs_raster(self) -> bool:
        """Whether the head trains on the prepared rasters (its fine level or its lane head)."""
        return bool(self.fine_scale or self.lane_head_width)


@dataclass
class PieceHeadConfig(QueryHeadConfig):
    """What MapTR's and STSU's heads share beyond the query decoder: the pieces, their links and the
    post-processing's duplicate suppression."""

    # instance queries: frames hold more pieces than paths (pieces end at junctions)
    num_pieces: Annotated[int, AT_LEAST_1] = 100
    # points per piece (MapTR's 20; the prepared targets are resampled to it)
    piece_points: Annotated[int, Range(low=2)] = 20
    link_weight: Annotated[float, AT_LEAST_0] = 1.0
    # the association loss's positive weight is clamped to this
    max_link_pos_weight: Annotated[float, POSITIVE] = 50.0
    # association probability above which i -> j is a link
    link_threshold: Annotated[float, PROBABILITY] = 0.5
    # 0: off (the papers'); r: a piece with `duplicate_overlap` of its points within r metres of a
    # higher-scoring piece is dropped before Piece2Graph (benchmark/graphs/piece2graph.py suppress_duplicates)
    duplicate_radius: Annotated[float, AT_LEAST_0] = 0.0
    duplicate_overlap: Annotated[float, PROBABILITY] = 0.5
    # MapTRv2's one-to-many matching (0 pieces: off): this many extra queries, in training only, matched
    # to the ground truth repeated `one_to_many_repeats` times, their set loss weighted by
    # `one_to_many_weight`
    one_to_many_pieces: Annotated[int, AT_LEAST_0] = 0
    one_to_many_repeats: Annotated[int, AT_LEAST_1] = 3
    one_to_many_weight: Annotated[float, AT_LEAST_0] = 1.0
