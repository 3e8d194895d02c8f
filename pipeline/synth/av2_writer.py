"""Argoverse 2 sensor-dataset layout: `<root>/<split>/<log_id>/` with the vector map, ego poses and cuboids.

Formats follow av2==0.3.6 (`ArgoverseStaticMap.from_json`, `av2.utils.io.read_city_SE3_ego`,
`CuboidList.from_feather`) and the real files: coordinates rounded to centimetres, one local map per
log holding the lanes near its trajectory (so, as in real logs, some successor ids are not in it).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pyarrow as pa

from pipeline.synth.ids import token
from pipeline.synth.logs import LogPlan, frame_cuboids
from pipeline.synth.world import AV2_CITY, World

LOCAL_MAP_RADIUS_M = 80.0  # l-infinity distance from the trajectory within which a log's map keeps lanes
RASTER_SCALE = 10.0 / 3.0  # AV2 rasters are 30 cm per pixel
DRIVABLE_AREA_ID0 = 100_000_000
CROSSING_ID0 = 200_000_000


def write_feather(path: Path, columns: dict) -> None:
    """Feather v2 (the Arrow IPC file format, lz4) without pyarrow.feather, which imports pandas (0.6 s)."""
    table = pa.table(columns)
    options = pa.ipc.IpcWriteOptions(compression="lz4")
    with pa.OSFile(str(path), "wb") as sink, pa.ipc.new_file(sink, table.schema, options=options) as writer:
        writer.write_table(table)


def yaw_quaternion(heading: np.ndarray) -> np.ndarray:
    """(n, 4) w, x, y, z of rotations about +z; w >= 0 so that the sign is canonical."""
    half = (np.asarray(heading) + np.pi) % (2 * np.pi) / 2 - np.pi / 2
    zeros = np.zeros_like(half)
    return np.stack([np.cos(half), zeros, zeros, np.sin(half)], axis=-1)


def write_log(root: Path, world: World, plan: LogPlan) -> Path:
    log_dir = root / plan.split / plan.log_id
    (log_dir / "map").mkdir(parents=True, exist_ok=True)
    write_map(log_dir / "map", world, plan)
    write_poses(log_dir / "city_SE3_egovehicle.feather", plan)
    write_annotations(log_dir / "annotations.feather", world, plan)
    return log_dir


def _points(xy: np.ndarray) -> list[dict]:
    return [{"x": round(float(x), 2), "y": round(float(y), 2), "z": 0.0} for x, y in xy]


def write_map(map_dir: Path, world: World, plan: LogPlan) -> None:
    trajectory = plan.ego_at(plan.pose_ns)[:, :2]

    def near(xy: np.ndarray) -> bool:
        gap = np.abs(xy[:, None, :] - trajectory[None, :, :]).max(axis=2)
        return bool(gap.min() <= LOCAL_MAP_RADIUS_M)

    lanes, areas = {}, {}
    for index, lane in enumerate(world.lanes.values()):
        left, right = (lane.boundary(side).points()[:, :2] for side in ("left", "right"))
        if not near(np.concatenate([left, right])):
            continue
        lanes[str(lane.id)] = {
            "id": lane.id,
            "is_intersection": lane.is_intersection,
            "lane_type": "VEHICLE",
            "left_lane_boundary": _points(left),
            "left_lane_mark_type": lane.left_mark,
            "right_lane_boundary": _points(right),
            "right_lane_mark_type": lane.right_mark,
            "successors": lane.successors,
            "predecessors": lane.predecessors,
            "right_neighbor_id": lane.right_neighbor,
            "left_neighbor_id": lane.left_neighbor,
        }
        area_id = DRIVABLE_AREA_ID0 + index  # the drivable area is the union of the lane polygons
        areas[str(area_id)] = {"area_boundary": _points(np.concatenate([right, left[::-1]])), "id": area_id}
    crossings = {}
    for index, crossing in enumerate(world.crosswalks):
        if near(np.concatenate([crossing.edge1, crossing.edge2])):
            crossings[str(CROSSING_ID0 + index)] = {
                "edge1": _points(crossing.edge1),
                "edge2": _points(crossing.edge2),
                "id": CROSSING_ID0 + index,
            }
    tile = int(token(world.seed, "city tile", plan.index)[:8], 16) % 90_000 + 10_000
    vector_map = {"pedestrian_crossings": crossings, "lane_segments": lanes, "drivable_areas": areas}
    (map_dir / f"log_map_archive_{plan.log_id}____{AV2_CITY}_city_{tile}.json").write_text(
        json.dumps(vector_map)
    )
    corner = np.floor(
        np.array([[p["x"], p["y"]] for a in areas.values() for p in a["area_boundary"]]).min(axis=0)
    )
    sim2 = {"R": [1.0, 0.0, 0.0, 1.0], "t": [float(-corner[0]), float(-corner[1])], "s": RASTER_SCALE}
    (map_dir / f"{plan.log_id}___img_Sim2_city.json").write_text(json.dumps(sim2))


def write_poses(path: Path, plan: LogPlan) -> None:
    ego = plan.ego_at(plan.pose_ns)
    q = yaw_quaternion(ego[:, 2])
    columns = {"timestamp_ns": pa.array(plan.pose_ns, pa.int64())}
    columns |= {name: pa.array(q[:, i], pa.float64()) for i, name in enumerate(("qw", "qx", "qy", "qz"))}
    columns |= {"tx_m": ego[:, 0], "ty_m": ego[:, 1], "tz_m": np.zeros(len(ego))}
    write_feather(path, columns)


def write_annotations(path: Path, world: World, plan: LogPlan) -> None:
    """Cuboids in the egovehicle frame (x forward, y left); the lead car puts at least one in every frame."""
    rows = []
    for ns, ego, cuboids in zip(
        plan.frame_ns, plan.ego_at(plan.frame_ns), frame_cuboids(world, plan), strict=True
    ):
        cos, sin = math.cos(ego[2]), math.sin(ego[2])
        for c in cuboids:
            dx, dy = c.x - ego[0], c.y - ego[1]
            rows.append(
                (
                    int(ns),
                    c.track,
                    "REGULAR_VEHICLE",
                    c.length,
                    c.width,
                    c.height,
                    c.heading - ego[2],
                    cos * dx + sin * dy,
                    -sin * dx + cos * dy,
                    c.height / 2,
                    int(3000 / (1 + c.distance)),
                )
            )
    (ns, track, category, length, width, height, yaw, tx, ty, tz, points) = map(list, zip(*rows, strict=True))
    q = yaw_quaternion(np.array(yaw))
    columns = {
        "timestamp_ns": pa.array(ns, pa.int64()),
        "track_uuid": track,
        "category": category,
        "length_m": length,
        "width_m": width,
        "height_m": height,
    }
    columns |= {name: pa.array(q[:, i], pa.float64()) for i, name in enumerate(("qw", "qx", "qy", "qz"))}
    columns |= {"tx_m": tx, "ty_m": ty, "tz_m": tz, "num_interior_pts": pa.array(points, pa.int64())}
    write_feather(path, columns)
