"""OpenLane-V2's layout (subset A) written from an AV2 sensor log, real or synthetic:
`ROOT/<split>/<segment_id>/info/<timestamp>.json`, one frame file per frame of the log, its lanes the map's
lane segments in the frame's ego frame (x forward, y left, z up) clipped to +-50 m along and +-25 m across,
each resampled to 201 points evenly along it as OpenLane-V2 annotates its centerlines, its topology_lclc
the map's successors, its seven ring cameras from the log's calibration and its images hard-linked to
`ROOT/<split>/<segment_id>/image/<camera>/<timestamp>.jpg` (OpenLane-V2's data/README.md).

No traffic elements: AV2's maps hold none, so `traffic_element` is empty and `topology_lcte` is (n, 0).
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.adapters import av2
from pipeline.errors import DataError
from pipeline.geometry import AV2_EGO_FROM_BEV, Range, clip_polylines
from pipeline.io import write_atomic
from pipeline.lane_graph import LaneMap
from pipeline.records import AnnotatedLanes
from pipeline.targets import rigid_inverse

FORMAT_VERSION = "v2.0"  # the OpenLane-V2 release whose data/README.md describes this layout
ALONG_M, ACROSS_M = 50.0, 25.0  # OpenLane-V2 annotates lanes within +-50 m along (ego x) and +-25 m across
# the same box in the BEV frame (x right, y forward), where prepare clips: the same arithmetic as its crop
OPENLANEV2_RANGE = Range(-ACROSS_M, ACROSS_M, -ALONG_M, ALONG_M)
# OpenLane-V2's annotated centerlines have 201 points each (its issue #21); its val/test evaluation keeps
# every 20th, so a lane of fewer points would be scored as its first point alone
LANE_POINTS = 201


@dataclass
class RingCamera:
    """One ring camera of an AV2 log as a frame file names it."""

    name: str
    K: np.ndarray  # (3, 3)
    distortion: list[float]  # AV2's radial k1, k2, k3
    ego_from_camera: np.ndarray  # (4, 4), AV2's egovehicle frame (OpenLane-V2's ego frame)
    image_times: np.ndarray  # sorted ns of the log's images of this camera; empty where it has none


@dataclass
class SegmentWritten:
    """What write_from_av2 wrote: one segment of OpenLane-V2 frames."""

    split: str
    segment_id: str
    frames: int
    lanes: int  # lane centerlines over all frames
    links: int  # topology_lclc entries set, over all frames
    images_linked: int  # image files placed under ROOT (hard links, or copies across file systems)
    images_absent: int  # image paths the frame files name whose file the AV2 log lacks (none placed)


def write_from_av2(
    av2_log_dir: Path, out_root: Path, split: str, segment_id: str | None = None, frame_stride: int = 1
) -> SegmentWritten:
    """Write one AV2 log as the OpenLane-V2 segment `out_root/<split>/<segment_id>` (segment_id: the log id),
    one frame file per frame (every frame_stride-th of the log's lidar sweeps, else its annotation times);
    frame files and images are replaced atomically, and those an earlier write left in the segment removed."""
    av2_log_dir, out_root = Path(av2_log_dir), Path(out_root)
    segment_id = av2_log_dir.name if segment_id is None else segment_id
    _check_name("split", split)
    _check_name("segment_id", segment_id)
    if frame_stride < 1:
        raise ValueError(f"frame_stride must be at least 1, not {frame_stride}")
    if not (av2_log_dir / "map").is_dir():
        raise DataError(av2_log_dir, "AV2 log", "is not a log folder (no map/ in it)")
    lanes, _ = av2.read_lanes(av2_log_dir)
    lane_map = LaneMap.from_lanes(lanes)
    timestamps = av2.frame_timestamps(av2_log_dir)[::frame_stride]
    pose_times, ego_to_city = av2.read_poses(av2_log_dir)
    poses = [ego_to_city[pose_times[av2.nearest(pose_times, t)]].transform_matrix
             for t in timestamps.tolist()]  # fmt: skip
    for t, pose in zip(timestamps.tolist(), poses):  # refused before anything is written
        if not np.isfinite(pose).all():
            pose_file = av2_log_dir / "city_SE3_egovehicle.feather"
            raise DataError(pose_file, f"pose at {t}", "has non-finite values")
    cameras = read_ring_cameras(av2_log_dir)

    segment = out_root / split / segment_id
    written = SegmentWritten(split, segment_id, 0, 0, 0, 0, 0)
    piece_ids: dict[tuple[int, int], int] = {}
    placed: set[Path] = set()
    frame_files: set[Path] = set()
    for t, pose in zip(timestamps.tolist(), poses):
        # the BEV pose and its inverse as the AV2 adapter and prepare compute them
        annotated = frame_lanes(lane_map, rigid_inverse(pose @ AV2_EGO_FROM_BEV), piece_ids)
        sensor = {}
        for camera in cameras:
            image_t = camera.image_times[av2.nearest(camera.image_times, t)] if len(camera.image_times) else t
            image_path = f"{split}/{segment_id}/image/{camera.name}/{image_t}.jpg"
            source = av2_log_dir / "sensors" / "cameras" / camera.name / f"{image_t}.jpg"
            if out_root / image_path not in placed:
                if source.is_file():
                    place_file(source, out_root / image_path)
                    written.images_linked += 1
                placed.add(out_root / image_path)
            written.images_absent += not source.is_file()
            sensor[camera.name] = camera_entry(camera, image_path)
        frame = frame_record(segment_id, av2_log_dir.name, str(t), sensor, pose, annotated)
        path = segment / "info" / f"{t}.json"
        write_atomic(path, lambda tmp, text=json.dumps(frame): tmp.write_text(text))
        frame_files.add(path)
        written.frames += 1
        written.lanes += len(annotated)
        written.links += int(annotated.links.sum())
    _remove_stale(segment, frame_files | placed)
    return written


def frame_record(
    segment_id: str, log_id: str, timestamp: str, sensor: dict, pose: np.ndarray, lanes: AnnotatedLanes
) -> dict:
    """One frame file's content, in data/README.md's order; plain lists and numbers only."""
    return {
        "version": FORMAT_VERSION,
        "segment_id": segment_id,
        "meta_data": {"source": "av2", "source_id": log_id},
        "timestamp": timestamp,
        "sensor": sensor,
        "pose": {"rotation": pose[:3, :3].tolist(), "translation": pose[:3, 3].tolist()},
        "annotation": {
            "lane_centerline": [
                {"id": int(i), "points": p.tolist()} for i, p in zip(lanes.ids, lanes.points, strict=True)
            ],
            "traffic_element": [],
            "topology_lclc": lanes.links.astype(np.int64).tolist(),
            "topology_lcte": [[] for _ in lanes.points],
        },
    }


def camera_entry(camera: RingCamera, image_path: str) -> dict:
    return {
        "image_path": image_path,
        "extrinsic": {
            "rotation": camera.ego_from_camera[:3, :3].tolist(),
            "translation": camera.ego_from_camera[:3, 3].tolist(),
        },
        "intrinsic": {"K": camera.K.tolist(), "distortion": camera.distortion},
    }


def frame_lanes(
    lane_map: LaneMap, world_to_bev: np.ndarray, piece_ids: dict[tuple[int, int], int]
) -> AnnotatedLanes:
    """The map's lanes in one frame as OpenLane-V2 annotates them: each lane moved into the BEV frame as
    crop_lane_graph moves it, clipped to OPENLANEV2_RANGE (a lane that leaves and re-enters gives two lanes),
    heights interpolated along the clip, resampled to LANE_POINTS points (resampled_lane: its end points
    kept, so linked lanes still share one), then turned into OpenLane-V2's ego frame (a swap of axes);
    lane i -> j linked where j's lane succeeds i's and i's piece holds its lane's end, j's its lane's start.
    piece_ids: (lane index, piece of that lane) -> id, shared by a log's frames: ids stay in a sequence."""
    ego_xy = -world_to_bev[:3, :3].T @ world_to_bev[:3, 3]
    reach = lane_map.radii + OPENLANEV2_RANGE.radius
    near = np.flatnonzero(np.linalg.norm(lane_map.centers - ego_xy[:2], axis=1) <= reach)
    if len(near) == 0:
        return AnnotatedLanes([], np.zeros((0, 0)), [])
    counts = lane_map.offsets[near + 1] - lane_map.offsets[near]
    take = np.concatenate([np.arange(lane_map.offsets[i], lane_map.offsets[i + 1]) for i in near])
    bev = lane_map.points[take] @ world_to_bev[:3, :3].T + world_to_bev[:3, 3]
    offsets = np.concatenate([[0], np.cumsum(counts)])
    box = OPENLANEV2_RANGE
    points, piece_offsets, piece_lane, has_start, has_end = clip_polylines(
        np.ascontiguousarray(bev[:, :2]), offsets, box.x_min, box.x_max, box.y_min, box.y_max
    )
    lanes, ids = [], []
    end_piece = np.full(len(near), -1, np.int64)
    start_piece = np.full(len(near), -1, np.int64)
    ordinal = np.zeros(len(near), np.int64)
    for k, line in enumerate(piece_lane.tolist()):
        xy = points[piece_offsets[k] : piece_offsets[k + 1]]
        z = clipped_heights(xy, bev[offsets[line] : offsets[line + 1]])
        piece = resampled_lane(np.column_stack([xy, z]), LANE_POINTS)
        # BEV (x right, y forward) -> OpenLane-V2's ego frame (x forward, y left)
        lanes.append(np.stack([piece[:, 1], -piece[:, 0], piece[:, 2]], axis=1))
        ids.append(str(piece_ids.setdefault((int(near[line]), int(ordinal[line])), len(piece_ids))))
        ordinal[line] += 1
        if has_end[k]:
            end_piece[line] = k
        if has_start[k]:
            start_piece[line] = k
    local = np.full(len(lane_map.ids), -1, np.int64)
    local[near] = np.arange(len(near))
    a, b = local[lane_map.link_src], local[lane_map.link_dst]
    ok = (a >= 0) & (b >= 0)
    i, j = end_piece[a[ok]], start_piece[b[ok]]
    ok = (i >= 0) & (j >= 0)
    links = np.zeros((len(lanes), len(lanes)))
    links[i[ok], j[ok]] = 1.0
    return AnnotatedLanes(lanes, links, ids)


def resampled_lane(points: np.ndarray, n: int) -> np.ndarray:
    """The polyline points (m, 3) as n points evenly spaced by arc length in the ground plane (as shapely's
    interpolate, which OpenLane-V2's own resampling uses, measures it), heights interpolated along; its first
    and last points kept to the bit, so a successor's first point stays its predecessor's last."""
    step = np.hypot(*np.diff(points[:, :2], axis=0).T)
    along = np.concatenate([[0.0], np.cumsum(step)])
    at = np.linspace(0.0, along[-1], n)
    out = np.column_stack([np.interp(at, along, points[:, k]) for k in range(points.shape[1])])
    out[0], out[-1] = points[0], points[-1]
    return out


def clipped_heights(xy: np.ndarray, line: np.ndarray) -> np.ndarray:
    """z of the points xy of a clipped piece of the polyline line (n, 3): a point on a vertex of the line
    takes its z, a point the clip put on a border the z interpolated along the segment it lies on."""
    a, b = line[:-1], line[1:]
    d = b[:, :2] - a[:, :2]
    squared = np.einsum("sk,sk->s", d, d)
    rel = xy[:, None, :] - a[None, :, :2]  # (m, segments, 2)
    t = np.clip(np.einsum("msk,sk->ms", rel, d) / np.where(squared > 0, squared, 1.0), 0.0, 1.0)
    gap = rel - t[..., None] * d
    seg = np.argmin(np.einsum("msk,msk->ms", gap, gap), axis=1)
    t = t[np.arange(len(xy)), seg]
    z = a[seg, 2] * (1.0 - t) + b[seg, 2] * t
    on_vertex = (xy[:, None, :] == line[None, :, :2]).all(axis=2)
    hit = on_vertex.any(axis=1)
    z[hit] = line[np.argmax(on_vertex[hit], axis=1), 2]
    return z


def read_ring_cameras(log_dir: Path) -> list[RingCamera]:
    """The ring cameras that the log's calibration holds (none without calibration/), in AV2's order."""
    intrinsics = log_dir / "calibration" / "intrinsics.feather"
    if not intrinsics.is_file():
        return []
    import pyarrow.feather as feather
    from av2.geometry.camera.pinhole_camera import PinholeCamera

    try:
        rows = feather.read_table(intrinsics).to_pydict()
        distortion = {name: [float(rows[k][i]) for k in ("k1", "k2", "k3")]
                      for i, name in enumerate(rows["sensor_name"])}  # fmt: skip
    except Exception as error:
        problem = f"cannot be read: {type(error).__name__}: {error}"
        raise DataError(intrinsics, "camera intrinsics", problem) from error
    cameras = []
    for name in av2.RING_CAMERAS:
        if name not in distortion:
            continue
        try:
            camera = PinholeCamera.from_feather(log_dir, name)
        except Exception as error:
            raise DataError(intrinsics.parent, f"camera {name}", f"bad calibration: {error}") from error
        folder = log_dir / "sensors" / "cameras" / name
        times = np.array(sorted(int(p.stem) for p in folder.glob("*.jpg")), np.int64)
        cameras.append(RingCamera(name, camera.intrinsics.K.astype(np.float64), distortion[name],
                                  camera.ego_SE3_cam.transform_matrix.astype(np.float64), times))  # fmt: skip
    return cameras


def place_file(source: Path, target: Path) -> None:
    """target becomes source's bytes, atomically: a hard link where the file system allows, else a copy."""
    target.parent.mkdir(parents=True, exist_ok=True)
    if target.exists() and os.path.samefile(source, target):
        return
    tmp = target.with_name(f".{target.name}.tmp-{os.getpid()}")
    try:
        try:
            os.link(source, tmp)
        except OSError:  # another file system, or one without hard links
            shutil.copyfile(source, tmp)
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()


def _remove_stale(segment: Path, kept: set[Path]) -> None:
    """Frame files and images of the segment that this write did not write (an earlier, longer write's)."""
    for pattern in ("info/*.json", "image/*/*.jpg"):
        for path in segment.glob(pattern):
            if path not in kept and not path.name.endswith("-ls.json"):
                path.unlink()


def _check_name(what: str, name: str) -> None:
    if not name or name in (".", "..") or "/" in name or "\\" in name:
        raise ValueError(f"{what} {name!r} must be a plain folder name")
