"""Argoverse 2 sensor dataset: `<root>/<split>/<log_id>/` read through the av2 API."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow.feather as feather

from pipeline.errors import DataError
from pipeline.geometry import AV2_EGO_FROM_BEV
from pipeline.records import Camera, Frame, Lane, Log, LogIndex

BEV_FROM_AV2_EGO = np.linalg.inv(AV2_EGO_FROM_BEV)
RING_CAMERAS = (
    "ring_front_center", "ring_front_left", "ring_front_right", "ring_side_left",
    "ring_side_right", "ring_rear_left", "ring_rear_right",
)  # fmt: skip
GROUND_RADIUS_M = 5.0  # lane points this close to the BEV origin (horizontally) give its ground height
GROUND_BAND_M = 2.0  # lane points farther above or below it are another level (a bridge, a ramp)


def find_logs(root: Path, split: str | None) -> list[tuple[str, Path]]:
    """(split, log folder) of every log under root/<split>/, sorted; root holds the split folders."""
    if not root.is_dir():
        raise DataError(root, "root", "is not a folder (expected the folder that holds train/, val/, ...)")
    splits = [split] if split else sorted(p.name for p in root.iterdir() if p.is_dir())
    logs = []
    for name in splits:
        folder = root / name
        if not folder.is_dir():
            raise DataError(folder, f"split {name}", "split folder not found")
        logs += [(name, d) for d in sorted(folder.iterdir()) if (d / "map").is_dir()]
    return logs


def read_lanes(log_dir: Path) -> tuple[list[Lane], str]:
    """Centerlines (av2 API, 10 points each) and successors of the log's vector map, and the city."""
    from av2.map.map_api import ArgoverseStaticMap

    file = vector_map_file(log_dir)
    try:
        static_map = ArgoverseStaticMap.from_json(file)
    except Exception as error:  # the av2 parser raises JSONDecodeError, KeyError, TypeError, ...
        raise DataError(file, "vector map", f"cannot be read: {type(error).__name__}: {error}") from error
    lanes = []
    for lane_id in sorted(static_map.vector_lane_segments):
        segment = static_map.vector_lane_segments[lane_id]
        try:
            xyz = static_map.get_lane_segment_centerline(lane_id)
        except Exception as error:
            raise DataError(file, f"lane segment {lane_id}", f"bad boundaries: {error}") from error
        if not np.isfinite(xyz).all():
            raise DataError(file, f"lane segment {lane_id}", "centerline has non-finite coordinates")
        lanes.append(Lane(str(lane_id), xyz.astype(np.float64), [str(s) for s in segment.successors or []]))
    return lanes, map_city(file)


def vector_map_file(log_dir: Path) -> Path:
    map_dir = log_dir / "map"
    files = sorted(map_dir.glob("log_map_archive_*.json"))
    if len(files) != 1:
        raise DataError(
            map_dir, "log_map_archive_*.json", f"expected one vector map file, found {len(files)}"
        )
    return files[0]


def map_city(file: Path) -> str:
    """The city that a vector map's file name carries (`log_map_archive_<log>____<CITY>_city_<id>.json`)."""
    return file.stem.split("____")[-1].split("_")[0] if "____" in file.stem else ""


def frame_timestamps(log_dir: Path) -> np.ndarray:
    """Lidar sweep times when the log has sweeps, else the annotation times (10 Hz in both cases)."""
    lidar = log_dir / "sensors" / "lidar"
    if lidar.is_dir():
        return np.array(sorted(int(p.stem) for p in lidar.glob("*.feather")), np.int64)
    for name in ("annotations.feather", "annotations_with_ego.feather"):
        if (log_dir / name).is_file():
            try:
                column = feather.read_table(log_dir / name, columns=["timestamp_ns"])["timestamp_ns"]
            except Exception as error:
                raise DataError(log_dir / name, "timestamp_ns", f"cannot be read: {error}") from error
            return np.unique(column.to_numpy()).astype(np.int64)
    raise DataError(log_dir, "frames", "no sensors/lidar/ sweeps and no annotations feather to key frames by")


def read_poses(log_dir: Path) -> tuple[np.ndarray, dict]:
    """Sorted pose timestamps and the av2 API's timestamp -> egovehicle-to-city SE3 mapping."""
    from av2.utils.io import read_city_SE3_ego

    path = log_dir / "city_SE3_egovehicle.feather"
    if not path.is_file():
        raise DataError(path, "ego poses", "file not found")
    try:
        poses = read_city_SE3_ego(log_dir)
    except Exception as error:
        raise DataError(path, "ego poses", f"cannot be read: {type(error).__name__}: {error}") from error
    if not poses:
        raise DataError(path, "ego poses", "no pose rows")
    # a pose with NaN is reported by `prepare` for the frames that use it
    return np.array(sorted(poses), np.int64), poses


def read_cameras(log_dir: Path) -> dict[str, tuple[np.ndarray, np.ndarray, int, int, np.ndarray]]:
    """name -> (intrinsics, camera-to-BEV, width, height, sorted image timestamps) for each ring camera."""
    calibration = log_dir / "calibration"
    if not (calibration / "intrinsics.feather").is_file():
        return {}
    from av2.geometry.camera.pinhole_camera import PinholeCamera

    cameras = {}
    for name in RING_CAMERAS:
        folder = log_dir / "sensors" / "cameras" / name
        if not folder.is_dir():
            continue
        try:
            camera = PinholeCamera.from_feather(log_dir, name)
        except Exception as error:
            raise DataError(calibration, f"camera {name}", f"bad calibration: {error}") from error
        times = np.array(sorted(int(p.stem) for p in folder.glob("*.jpg")), np.int64)
        cam_to_bev = BEV_FROM_AV2_EGO @ camera.ego_SE3_cam.transform_matrix
        cameras[name] = (camera.intrinsics.K, cam_to_bev, camera.width_px, camera.height_px, times)
    return cameras


def ground_height(lane_points: np.ndarray, bev_to_city: np.ndarray) -> float | None:
    """z, in the BEV frame, of the road under its origin: the median height of the map's lane
    centerline points (on the road surface) near it; None where there are none. The egovehicle
    origin is the centre of the rear axle, about 0.34 m above the road on the real logs."""
    local = (lane_points - bev_to_city[:3, 3]) @ bev_to_city[:3, :3]
    near = (np.hypot(local[:, 0], local[:, 1]) < GROUND_RADIUS_M) & (np.abs(local[:, 2]) < GROUND_BAND_M)
    return float(np.median(local[near, 2])) if near.any() else None


def nearest(times: np.ndarray, t: int) -> int:
    i = int(np.clip(np.searchsorted(times, t), 1, len(times) - 1)) if len(times) > 1 else 0
    return i - 1 if len(times) > 1 and t - times[i - 1] <= times[i] - t else i


def frame_poses(log_dir: Path, timestamps: np.ndarray) -> list[np.ndarray]:
    """The BEV frame's pose in the city frame at each timestamp (the pose nearest in time)."""
    pose_times, ego_to_city = read_poses(log_dir)
    return [ego_to_city[pose_times[nearest(pose_times, t)]].transform_matrix @ AV2_EGO_FROM_BEV
            for t in timestamps.tolist()]  # fmt: skip


def index_log(log_dir: Path) -> LogIndex:
    """Every frame's time and position and the log's city, without reading its map or sensors."""
    timestamps = frame_timestamps(log_dir)
    poses = frame_poses(log_dir, timestamps)
    xy = np.array([pose[:2, 3] for pose in poses], np.float64).reshape(-1, 2)
    return LogIndex(map_city(vector_map_file(log_dir)), timestamps, xy)


def load_log(root: Path, split: str, log_dir: Path, frame_stride: int = 1) -> Log:
    lanes, city = read_lanes(log_dir)
    timestamps = frame_timestamps(log_dir)[::frame_stride]
    poses = frame_poses(log_dir, timestamps)
    cameras = read_cameras(log_dir)
    has_lidar = (log_dir / "sensors" / "lidar").is_dir()
    lane_points = np.concatenate([lane.xyz for lane in lanes]) if lanes else np.zeros((0, 3))
    frames, heights = [], []
    for t, pose in zip(timestamps.tolist(), poses):
        frame_cameras = [
            Camera(
                name,
                str((log_dir / f"sensors/cameras/{name}/{times[nearest(times, t)]}.jpg").relative_to(root)),
                K, cam_to_bev, int(w), int(h),
            )
            for name, (K, cam_to_bev, w, h, times) in cameras.items() if len(times)
        ]  # fmt: skip
        frames.append(
            Frame(
                frame_id=f"av2/{log_dir.name}/{t}",
                dataset="av2",
                split=split,
                log_id=log_dir.name,
                timestamp_ns=t,
                city=city,
                ego_to_world=pose,
                cameras=frame_cameras,
                lidar_path=str((log_dir / "sensors" / "lidar" / f"{t}.feather").relative_to(root))
                if has_lidar
                else "",
                lidar_to_ego=BEV_FROM_AV2_EGO.copy(),
            )
        )
        heights.append(ground_height(lane_points, pose))
    # frames far from every lane take the log's typical height (0, the egovehicle plane, if none has one)
    found = [h for h in heights if h is not None]
    typical = float(np.median(found)) if found else 0.0
    for frame, height in zip(frames, heights):
        frame.ground_z = typical if height is None else height
    return Log("av2", split, log_dir.name, str(log_dir), lanes, frames,
               pose_source=str(log_dir / "city_SE3_egovehicle.feather"))  # fmt: skip
