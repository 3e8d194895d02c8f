"""Graph2Pixel: the HDMapNet targets, a lane mask and a direction map on the BEV grid."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.geometry import Range
from pipeline.lane_graph import LaneGraph

SUBPIXEL_BITS = 4  # cv2 draws with fixed-point coordinates: 1/16 pixel


def direction_vectors(direction_bins: int = 36) -> np.ndarray:
    """(direction_bins + 1, 2): the unit vector (x, y) of each direction bin's centre angle, indexed by the
    bin value (Grid.direction_bin); row 0, no lane, is zero. `direction_vectors()[raster]` decodes a map."""
    angle = np.radians((np.arange(direction_bins + 1) - 0.5) * 360.0 / direction_bins)
    vectors = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    vectors[0] = 0.0
    return vectors


@dataclass(frozen=True)
class Grid:
    bev_range: Range
    resolution: float = 0.15
    line_width: int = 5
    direction_bins: int = 36

    @property
    def shape(self) -> tuple[int, int]:
        """(rows along y, columns along x); row 0 is the front edge."""
        rows = round((self.bev_range.y_max - self.bev_range.y_min) / self.resolution)
        cols = round((self.bev_range.x_max - self.bev_range.x_min) / self.resolution)
        return rows, cols

    def to_pixels(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Continuous (column, row) coordinates; pixel centres sit at integer + 0.5."""
        return np.stack(
            [(x - self.bev_range.x_min) / self.resolution, (self.bev_range.y_max - y) / self.resolution], -1
        )

    def pixel_centres(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(n, 2) metres (x, y) of the centres of pixels (rows, cols): the inverse of `to_pixels`."""
        return np.stack(
            [
                self.bev_range.x_min + (cols + 0.5) * self.resolution,
                self.bev_range.y_max - (rows + 0.5) * self.resolution,
            ],
            axis=1,
        )

    def direction_bin(self, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
        """1 + floor(theta / bin width) for theta = atan2(dy, dx) in [0, 360) degrees."""
        theta = np.degrees(np.arctan2(dy, dx)) % 360.0
        return 1 + np.minimum((theta * self.direction_bins / 360.0).astype(np.int64), self.direction_bins - 1)


def rasterize(graph: LaneGraph, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """(mask, direction) uint8 arrays of grid.shape: every edge drawn line_width pixels wide."""
    direction = np.zeros(grid.shape, np.uint8)
    if len(graph.src) == 0:
        return direction.copy(), direction
    # pixel (c, r) covers [c, c + 1) x [r, r + 1); cv2 puts pixel centres at integers, hence - 0.5
    uv = grid.to_pixels(graph.x.astype(np.float64), graph.y.astype(np.float64)) - 0.5
    fixed = np.round(uv * (1 << SUBPIXEL_BITS)).astype(np.int32)
    segments = np.stack([fixed[graph.src], fixed[graph.dst]], axis=1)  # (E, 2, 2)
    bins = grid.direction_bin(
        graph.x[graph.dst] - graph.x[graph.src], graph.y[graph.dst] - graph.y[graph.src]
    )
    # one cv2 call per direction bin instead of one per edge (the hot path)
    for b in np.unique(bins).tolist():
        cv2.polylines(
            direction, list(segments[bins == b]), False, b, grid.line_width, cv2.LINE_8, SUBPIXEL_BITS
        )
    # the same segments at the same width cover the same pixels: the mask is where a direction is
    return (direction > 0).view(np.uint8), direction
