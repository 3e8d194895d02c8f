"""Argoverse 2 sensor-dataset layout: `<root>/<split>/<log_id>/` with the vector map, ego poses, cuboids
and, with sensors, the calibration, ring camera images and LiDAR sweeps.

Formats follow av2==0.3.6 (`ArgoverseStaticMap.from_json`, `av2.utils.io.read_city_SE3_ego`,
`CuboidList.from_feather`, `PinholeCamera.from_feather`, `Sweep.from_feather`) and the real files:
coordinates rounded to centimetres, one local map per log holding the lanes near its trajectory (so,
as in real logs, some successor ids are not in it), float16 sweep coordinates.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pyarrow as pa

from pipeline.synth.ids import token
from pipeline.synth.lidar import Sweep
from pipeline.synth.logs import LogPlan, frame_cuboids
from pipeline.synth.rig import AV2_CAMERAS, AV2_LIDARS
from pipeline.synth.world import World

LOCAL_MAP_RADIUS_M = 80.0  # l-infinity distance from the trajectory within which a log's map keeps lanes
RASTER_SCALE = 10.0 / 3.0  # AV2 rasters are 30 cm per pixel
DRIVABLE_AREA_ID0 = 100_000_000
CROSSING_ID0 = 200_000_000
ANNOTATION_COLUMNS = (
    "timestamp_ns track_uuid category length_m width_m height_m qw qx qy qz tx_m ty_m tz_m num_interior_pts"
).split()


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
    """Centimetre points, as the real files; a point that rounds onto the one before is dropped (the av2
    API's interpolation divides by the distance between neighbours)."""
    rounded = np.round(xy, 2)
    keep = np.concatenate([[True], np.abs(np.diff(rounded, axis=0)).max(axis=1) > 0])
    return [{"x": float(x), "y": float(y), "z": 0.0} for x, y in rounded[keep]]


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
    name = f"log_map_archive_{plan.log_id}____{world.av2_city}_city_{tile}.json"
    (map_dir / name).write_text(json.dumps(vector_map))
    # the raster (ground height) grid would start at the map's lower left corner, 30 cm per pixel
    corners = [[p["x"], p["y"]] for area in areas.values() for p in area["area_boundary"]]
    x0, y0 = np.floor(np.min(corners, axis=0))
    sim2 = {"R": [1.0, 0.0, 0.0, 1.0], "t": [float(-x0), float(-y0)], "s": RASTER_SCALE}
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
    poses = plan.ego_at(plan.frame_ns)
    for ns, (x, y, heading), cuboids in zip(plan.frame_ns, poses, frame_cuboids(world, plan), strict=True):
        cos, sin = math.cos(heading), math.sin(heading)
        for c in cuboids:
            dx, dy = c.x - x, c.y - y
            rotation = yaw_quaternion(c.heading - heading).tolist()
            translation = [cos * dx + sin * dy, -sin * dx + cos * dy, c.height / 2]
            size = [c.length, c.width, c.height]
            interior_points = int(3000 / (1 + c.distance))  # fewer when far
            rows.append(
                [int(ns), c.track, "REGULAR_VEHICLE", *size, *rotation, *translation, interior_points]
            )
    columns = dict(zip(ANNOTATION_COLUMNS, map(list, zip(*rows, strict=True)), strict=True))
    write_feather(path, columns)  # python ints and floats: int64 and double columns, as in the real files


def write_calibration(log_dir: Path) -> None:
    """calibration/intrinsics.feather (pinhole, no distortion) and egovehicle_SE3_sensor.feather."""
    (log_dir / "calibration").mkdir(parents=True, exist_ok=True)
    names = [c.name for c in AV2_CAMERAS]
    write_feather(log_dir / "calibration" / "intrinsics.feather", {
        "sensor_name": names,
        "fx_px": [c.focal for c in AV2_CAMERAS], "fy_px": [c.focal for c in AV2_CAMERAS],
        "cx_px": [c.cx for c in AV2_CAMERAS], "cy_px": [c.cy for c in AV2_CAMERAS],
        "k1": [0.0] * len(names), "k2": [0.0] * len(names), "k3": [0.0] * len(names),
        "height_px": pa.array([c.height for c in AV2_CAMERAS], pa.int64()),
        "width_px": pa.array([c.width for c in AV2_CAMERAS], pa.int64()),
    })  # fmt: skip
    poses = [(c.name, c.quaternion, c.translation) for c in AV2_CAMERAS]
    poses += [(lidar.name, lidar.quaternion, lidar.translation) for lidar in AV2_LIDARS]
    columns = {"sensor_name": [name for name, _, _ in poses]}
    columns |= {k: [float(q[i]) for _, q, _ in poses] for i, k in enumerate(("qw", "qx", "qy", "qz"))}
    columns |= {k: [float(t[i]) for _, _, t in poses] for i, k in enumerate(("tx_m", "ty_m", "tz_m"))}
    write_feather(log_dir / "calibration" / "egovehicle_SE3_sensor.feather", columns)


def write_sweep(path: Path, sweep: Sweep) -> None:
    """A sweep in the egovehicle frame with the real column types (float16 coordinates)."""
    columns = {axis: pa.array(sweep.xyz[:, i].astype(np.float16)) for i, axis in enumerate("xyz")}
    columns["intensity"] = pa.array(sweep.intensity, pa.uint8())
    columns["laser_number"] = pa.array(sweep.laser, pa.uint8())
    columns["offset_ns"] = pa.array(sweep.offset_ns, pa.uint32())
    write_feather(path, columns)
