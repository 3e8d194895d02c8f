"""The nuScenes map expansion (`maps/expansion/<map>.json`, version 1.3) and semantic prior of the world.

As nuscenes-devkit 1.2.0 reads them (`NuScenesMap`, `arcline_path_utils`): every lane and lane
connector has a polygon, an `arcline_path_3` list with one record per straight or arc, and a
`connectivity` entry. Junction lanes (AV2 is_intersection) are lane connectors.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np

from pipeline.synth.geometry import Piece, wrap_angle
from pipeline.synth.ids import uuid_like
from pipeline.synth.world import World

MAP_VERSION = "1.3"  # the devkit refuses maps older than 1.3
SEMANTIC_PRIOR_RESOLUTION_M = 0.1  # the devkit's MapMask default
STRAIGHT_RADIUS = 999.999  # what the real maps give straights


def arcline(piece: Piece) -> dict:
    """One arcline_path_3 record: an arc is all first segment (LSL / RSR), a straight all middle segment."""
    end = piece.end
    if piece.curvature == 0.0:
        shape, radius, lengths = "LSR", STRAIGHT_RADIUS, [0.0, piece.length, 0.0]
    else:
        shape = "LSL" if piece.curvature > 0 else "RSR"
        radius, lengths = 1.0 / abs(piece.curvature), [piece.length, 0.0, 0.0]
    return {
        "start_pose": [piece.start.x, piece.start.y, wrap_angle(piece.start.heading)],
        "end_pose": [end.x, end.y, wrap_angle(end.heading)],
        "shape": shape,
        "radius": radius,
        "segment_length": lengths,
    }


class _Geometry:
    """The node / line / polygon layers that the other layers point into."""

    def __init__(self, seed: int):
        self.seed, self.node, self.line, self.polygon = seed, [], [], []

    def _token(self, kind: str, index: int) -> str:
        return uuid_like(self.seed, "map", kind, index)

    def nodes(self, xy: np.ndarray) -> list[str]:
        tokens = []
        for x, y in xy:
            tokens.append(self._token("node", len(self.node)))
            self.node.append({"token": tokens[-1], "x": float(x), "y": float(y)})
        return tokens

    def add_line(self, node_tokens: list[str]) -> str:
        self.line.append({"token": self._token("line", len(self.line)), "node_tokens": node_tokens})
        return self.line[-1]["token"]

    def add_polygon(self, node_tokens: list[str]) -> str:
        self.polygon.append(
            {
                "token": self._token("polygon", len(self.polygon)),
                "exterior_node_tokens": node_tokens,
                "holes": [],
            }
        )
        return self.polygon[-1]["token"]


def map_expansion(world: World) -> dict:
    geometry = _Geometry(world.seed)
    lanes, connectors, arclines, connectivity, lane_polygons = [], [], {}, {}, []
    for lane in world.lanes.values():
        left, right = (lane.boundary(side).points()[:, :2] for side in ("left", "right"))
        left_nodes, right_nodes = geometry.nodes(left), geometry.nodes(right)
        polygon = geometry.add_polygon(right_nodes + left_nodes[::-1])
        lane_polygons.append(polygon)
        tok = world.token_of(lane.id)
        if lane.is_intersection:
            connectors.append({"token": tok, "polygon_token": polygon})
        else:
            lanes.append(
                {
                    "token": tok,
                    "polygon_token": polygon,
                    "lane_type": "CAR",
                    "from_edge_line_token": geometry.add_line([left_nodes[0], right_nodes[0]]),
                    "to_edge_line_token": geometry.add_line([left_nodes[-1], right_nodes[-1]]),
                    "left_lane_divider_segments": [],
                    "right_lane_divider_segments": [],
                }
            )
        arclines[tok] = [arcline(piece) for piece in lane.path.pieces]
        connectivity[tok] = {
            "incoming": [world.token_of(i) for i in lane.predecessors],
            "outgoing": [world.token_of(i) for i in lane.successors],
        }
    crossings = []
    for index, crossing in enumerate(world.crosswalks):
        corners = np.stack([crossing.edge1[0], crossing.edge1[1], crossing.edge2[1], crossing.edge2[0]])
        crossings.append(
            {
                "token": uuid_like(world.seed, "map", "ped_crossing", index),
                "polygon_token": geometry.add_polygon(geometry.nodes(corners)),
                "road_segment_token": "",
            }
        )
    drivable = [{"token": uuid_like(world.seed, "map", "drivable_area"), "polygon_tokens": lane_polygons}]
    return {
        "version": MAP_VERSION,
        "canvas_edge": list(world.canvas),
        "polygon": geometry.polygon,
        "line": geometry.line,
        "node": geometry.node,
        "drivable_area": drivable,
        "road_segment": [],
        "road_block": [],
        "lane": lanes,
        "ped_crossing": crossings,
        "walkway": [],
        "stop_line": [],
        "carpark_area": [],
        "road_divider": [],
        "lane_divider": [],
        "traffic_light": [],
        "lane_connector": connectors,
        "arcline_path_3": arclines,
        "connectivity": connectivity,
    }


def write_map(root: Path, world: World, map_name: str, prior_filename: str) -> None:
    (root / "maps" / "expansion").mkdir(parents=True, exist_ok=True)
    (root / "maps" / "expansion" / f"{map_name}.json").write_text(json.dumps(map_expansion(world)))
    write_semantic_prior(root / prior_filename, world)


def write_semantic_prior(path: Path, world: World) -> None:
    """The drivable area as a 0 / 255 PNG over the whole canvas, row 0 at the top (largest y)."""
    scale = 1.0 / SEMANTIC_PRIOR_RESOLUTION_M
    width, height = (math.ceil(v * scale) for v in world.canvas)
    mask = np.zeros((height, width), np.uint8)
    for lane in world.lanes.values():
        outline = np.concatenate(
            [lane.boundary("right").points()[:, :2], lane.boundary("left").points()[::-1, :2]]
        )
        pixels = np.column_stack([outline[:, 0] * scale, height - outline[:, 1] * scale])
        cv2.fillPoly(mask, [np.round(pixels).astype(np.int32)], 255)  # one call each: overlaps would cancel
    cv2.imwrite(str(path), mask)
