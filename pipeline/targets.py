"""All training targets of one frame: graph, pieces, paths and rasters, as table rows."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.geometry import Range, resample_polylines
from pipeline.lane_graph import LaneGraph, LaneMap, crop_lane_graph
from pipeline.paths import Paths, pieces_to_paths
from pipeline.pieces import Pieces, graph_to_pieces
from pipeline.raster import Grid, rasterize
from pipeline.records import Lane


@dataclass(frozen=True)
class TargetOptions:
    bev_range: Range = field(default_factory=Range)
    path_points: int = 30
    piece_points: int = 20
    max_paths: int = 256
    resolution: float = 0.15
    line_width: int = 5

    @property
    def grid(self) -> Grid:
        return Grid(self.bev_range, self.resolution, self.line_width)


@dataclass
class FrameTargets:
    graph: LaneGraph
    pieces: Pieces
    paths: Paths
    path_points: np.ndarray  # (P, path_points, 2)
    path_lengths: np.ndarray
    piece_points: np.ndarray  # (Q, piece_points, 2)
    piece_lengths: np.ndarray
    mask: np.ndarray
    direction: np.ndarray


def flat_pose(ego_to_world: np.ndarray) -> np.ndarray:
    """The pose with its roll and pitch removed: for maps without heights (nuScenes), as MapTR does."""
    yaw = np.arctan2(ego_to_world[1, 0], ego_to_world[0, 0])
    flat = np.eye(4)
    flat[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    flat[:2, 3] = ego_to_world[:2, 3]
    return flat


def rigid_inverse(T: np.ndarray) -> np.ndarray:
    inverse = np.eye(4)
    inverse[:3, :3] = T[:3, :3].T
    inverse[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return inverse


def resample(chains: list[np.ndarray], graph: LaneGraph, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    if not chains:
        return np.zeros((0, n_points, 2)), np.zeros(0)
    ids = np.concatenate(chains)
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in chains])])
    xy = np.stack([graph.x[ids], graph.y[ids]], 1).astype(np.float64)
    return resample_polylines(xy, offsets, n_points)


def warm_up() -> None:
    """Load the numba kernels once (before forking workers, so that each does not load them again)."""
    lane_map = LaneMap.from_lanes([Lane("a", np.array([[0.0, 0, 0], [1, 0, 0]]), ["b"]),
                                   Lane("b", np.array([[1.0, 0, 0], [2, 0, 0]]), [])])  # fmt: skip
    frame_targets(lane_map, np.eye(4), TargetOptions())


def frame_targets(lane_map: LaneMap, ego_to_world: np.ndarray, options: TargetOptions) -> FrameTargets:
    return graph_targets(crop_lane_graph(lane_map, rigid_inverse(ego_to_world), options.bev_range), options)


def graph_targets(graph: LaneGraph, options: TargetOptions) -> FrameTargets:
    """The targets of a frame's cropped lane graph (a map's, or OpenLane-V2's annotated lanes')."""
    pieces = graph_to_pieces(graph)
    paths = pieces_to_paths(pieces, len(graph.x), options.max_paths)
    path_points, path_lengths = resample(paths.vertex_ids, graph, options.path_points)
    piece_points, piece_lengths = resample(pieces.chains, graph, options.piece_points)
    mask, direction = rasterize(graph, options.grid)
    return FrameTargets(
        graph, pieces, paths, path_points, path_lengths, piece_points, piece_lengths, mask, direction
    )
