"""The ground as cameras and LiDAR see it: a raster of materials (grass, asphalt, white and yellow paint)
and its colours, around one log's trajectory.

Paint follows the AV2 lane mark types of the lane boundaries (solid, dashed, double; white, yellow),
so that the lane lines in images and LiDAR intensities are where the map says.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.synth.geometry import Path
from pipeline.synth.world import World

RESOLUTION_M = 0.05
MIP_LEVELS = 6  # texels of 5 cm to 1.6 m
GRASS, ASPHALT, WHITE, YELLOW = 0, 1, 2, 3
COLOURS_BGR = np.array([[62, 96, 84], [92, 92, 96], [225, 225, 225], [40, 185, 225]], np.int16)
PAINT_WIDTH_M = 0.15
DASH_M, GAP_M = 3.0, 6.0
DOUBLE_LINE_OFFSET_M = 0.12
SUBPIXEL_BITS = 2  # cv2 drawing with quarter-pixel precision


@dataclass
class GroundTexture:
    x0: float  # world x of column 0
    y0: float  # world y of row 0 (rows grow with y)
    material: np.ndarray  # (h, w) uint8
    pyramid: list[np.ndarray]  # the colours, (h, w, 3) uint8 BGR, then halved MIP_LEVELS - 1 times

    def pixels(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fractional (column, row) of world points, as cv2.remap takes them."""
        return ((x - self.x0) / RESOLUTION_M).astype(np.float32), ((y - self.y0) / RESOLUTION_M).astype(
            np.float32
        )

    def from_ego(self, pose: np.ndarray, level: int = 0) -> np.ndarray:
        """(2, 3) affine map from ego-frame x, y (the ego at pose x, y, heading) to fractional (column, row)
        of a pyramid level; texel i of a level covers texels 2i and 2i + 1 of the one below."""
        x, y, heading = pose
        scale = 1.0 / (RESOLUTION_M * 2**level)
        c, s, shift = np.cos(heading) * scale, np.sin(heading) * scale, 0.5 / 2**level - 0.5
        return np.array([[c, -s, (x - self.x0) * scale + shift], [s, c, (y - self.y0) * scale + shift]])

    def material_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The material under each world point (the nearest texel); grass beyond the texture."""
        h, w = self.material.shape
        col = np.rint((x - self.x0) / RESOLUTION_M).astype(np.int64)
        row = np.rint((y - self.y0) / RESOLUTION_M).astype(np.int64)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        # clip, then look up all at once: cheaper than indexing with the mask
        found = self.material[np.clip(row, 0, h - 1), np.clip(col, 0, w - 1)]
        return np.where(inside, found, np.uint8(GRASS))


def ground_texture(
    world: World, centre_xy: np.ndarray, half_size: float, rng: np.random.Generator
) -> GroundTexture:
    """The square of ground within half_size (l-infinity) of any of the centre points."""
    low, high = centre_xy.min(axis=0) - half_size, centre_xy.max(axis=0) + half_size
    (x0, y0), (w, h) = low, np.ceil((high - low) / RESOLUTION_M).astype(int)
    material = np.full((h, w), GRASS, np.uint8)
    scale = (1 << SUBPIXEL_BITS) / RESOLUTION_M

    def fixed(xy: np.ndarray) -> np.ndarray:
        return np.round((xy - [x0, y0]) * scale).astype(np.int32)

    def line(xy: np.ndarray, value: int) -> None:
        thickness = max(1, round(PAINT_WIDTH_M / RESOLUTION_M))
        cv2.polylines(material, [fixed(xy)], False, value, thickness, cv2.LINE_8, SUBPIXEL_BITS)

    for lane in world.lanes.values():
        left, right = lane.boundary("left"), lane.boundary("right")
        outline = np.concatenate([right.points()[:, :2], left.points()[::-1, :2]])
        cv2.fillPoly(material, [fixed(outline)], ASPHALT, cv2.LINE_8, SUBPIXEL_BITS)
    for lane in world.lanes.values():  # paint after all asphalt, so that no lane covers its neighbour's line
        for side, mark in (("left", lane.left_mark), ("right", lane.right_mark)):
            _paint(lane.boundary(side), mark, line)
    for crossing in world.crosswalks:
        across = crossing.edge1[1] - crossing.edge1[0]
        width = float(np.linalg.norm(across))
        for a in np.arange(0.25, width - 0.5, 1.0):  # 0.5 m stripes every metre, along the traffic
            b = a + 0.5
            corners = [crossing.edge1[0] + across * t / width for t in (a, b)]
            corners += [crossing.edge2[0] + across * t / width for t in (b, a)]
            cv2.fillPoly(material, [fixed(np.stack(corners))], WHITE, cv2.LINE_8, SUBPIXEL_BITS)
    pyramid = [_colour(material, rng)]
    for _ in range(MIP_LEVELS - 1):
        pyramid.append(cv2.pyrDown(pyramid[-1]))
    return GroundTexture(float(x0), float(y0), material, pyramid)


def _paint(boundary: Path, mark: str, line) -> None:
    """Draw one lane boundary's marking with line(points, material)."""
    if mark in ("NONE", "UNKNOWN"):
        return
    value = YELLOW if mark.endswith("YELLOW") else WHITE
    offsets = (-DOUBLE_LINE_OFFSET_M, DOUBLE_LINE_OFFSET_M) if mark.startswith("DOUBLE") else (0.0,)
    for offset in offsets:
        path = boundary.offset(offset) if offset else boundary
        if "DASH" in mark:
            for start in np.arange(0.0, path.length, DASH_M + GAP_M):
                stations = np.linspace(start, min(start + DASH_M, path.length), 7)
                line(path.at(stations)[:, :2], value)
        else:
            line(path.points(spacing=0.5)[:, :2], value)


def _colour(material: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Material colours with blotches (a coarse noise, upsampled) and grain (a small tile, repeated)."""
    h, w = material.shape
    lut = np.zeros((256, 1, 3), np.uint8)
    lut[: len(COLOURS_BGR), 0] = COLOURS_BGR
    colour = cv2.LUT(cv2.merge([material] * 3), lut)
    coarse = rng.normal(128.0, 9.0, (h // 64 + 2, w // 64 + 2)).astype(np.float32)
    shade = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    grain = rng.normal(0.0, 4.0, (128, 128)).astype(np.float32)
    shade += np.tile(grain, (h // 128 + 1, w // 128 + 1))[:h, :w]
    shade = np.clip(shade, 0, 255).astype(np.uint8)
    return cv2.addWeighted(colour, 1.0, cv2.merge([shade] * 3), 1.0, -128.0)
