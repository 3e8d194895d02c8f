"""nuScenes: scenes, samples and the map expansion, read through nuscenes-devkit.

The NuScenes tables are loaded once in the parent process; `prepare` forks its workers, which
inherit them. Each worker discretises a map's lanes once and keeps them.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from pipeline.errors import DataError
from pipeline.geometry import pose_matrix
from pipeline.records import Camera, Frame, Lane, Log, LogIndex

LANE_RESOLUTION_M = 0.5  # arc chord error at 0.5 m spacing is under 1 cm for radii above 3 m

_tables = {}  # (version, dataroot) -> NuScenes, shared with forked workers


@dataclass(frozen=True)
class SceneRef:
    dataroot: Path
    version: str
    split: str
    scene_token: str
    name: str
    n_frames: int


def load_tables(dataroot: Path, version: str):
    from nuscenes import NuScenes

    key = (version, str(dataroot))
    if key not in _tables:
        if not (dataroot / version).is_dir():
            raise DataError(dataroot / version, "tables", "nuScenes table folder not found")
        try:
            _tables[key] = NuScenes(version=version, dataroot=str(dataroot), verbose=False)
        except Exception as error:
            raise DataError(
                dataroot / version, "tables", f"cannot be loaded: {type(error).__name__}: {error}"
            ) from error
    return _tables[key]


def split_names(version: str, split: str | None) -> list[str]:
    """Official split names of a version; 'train'/'val' mean 'mini_train'/'mini_val' for v1.0-mini."""
    if "mini" in version:
        names = ["mini_train", "mini_val"]
        if split in ("train", "val"):
            split = f"mini_{split}"
    elif "test" in version:
        names = ["test"]
    else:
        names = ["train", "val"]
    return [split] if split else names


def find_scenes(dataroot: Path, version: str, split: str | None) -> list[SceneRef]:
    from nuscenes.utils.splits import create_splits_scenes

    nusc = load_tables(dataroot, version)
    official = create_splits_scenes()
    by_name = {scene["name"]: scene for scene in nusc.scene}
    refs = []
    for name in split_names(version, split):
        if name not in official:
            raise DataError(
                dataroot / version, f"split {name}", f"not an official split ({sorted(official)})"
            )
        for scene_name in official[name]:
            if scene_name in by_name:
                scene = by_name[scene_name]
                refs.append(
                    SceneRef(dataroot, version, name, scene["token"], scene_name, scene["nbr_samples"])
                )
    return refs


@lru_cache(maxsize=8)
def open_map(dataroot: Path, map_name: str):
    """The NuScenesMap and this process's cache of its discretised lanes (token -> Lane)."""
    from nuscenes.map_expansion.map_api import NuScenesMap

    path = dataroot / "maps" / "expansion" / f"{map_name}.json"
    if not path.is_file():
        raise DataError(path, f"map {map_name}", "map expansion file not found")
    try:
        nusc_map = NuScenesMap(dataroot=str(dataroot), map_name=map_name)
    except Exception as error:
        raise DataError(
            path, f"map {map_name}", f"cannot be loaded: {type(error).__name__}: {error}"
        ) from error
    return nusc_map, {}


def lanes_near(dataroot: Path, map_name: str, centre: np.ndarray, radius: float) -> list[Lane]:
    """Lanes of the map that can reach within radius of centre, discretised once per process."""
    from nuscenes.map_expansion.arcline_path_utils import discretize_lane, length_of_lane

    nusc_map, cache = open_map(dataroot, map_name)
    path = dataroot / "maps" / "expansion" / f"{map_name}.json"
    lanes = []
    for record in nusc_map.lane + nusc_map.lane_connector:
        token = record["token"]
        arcs = nusc_map.arcline_path_3.get(token)
        if not arcs:
            raise DataError(path, f"lane {token}", "has no arcline_path_3 record")
        start = np.array(arcs[0]["start_pose"][:2])
        if np.linalg.norm(start - centre) > radius + length_of_lane(arcs):
            continue
        if token not in cache:
            poses = np.array(discretize_lane(arcs, LANE_RESOLUTION_M), np.float64).reshape(-1, 3)
            if len(poses) < 2 or not np.isfinite(poses).all():
                raise DataError(path, f"lane {token}", "arcline path does not discretise to a finite line")
            xyz = np.concatenate([poses[:, :2], np.zeros((len(poses), 1))], axis=1)
            try:
                outgoing = nusc_map.get_outgoing_lane_ids(token)
            except ValueError as error:
                raise DataError(path, f"lane {token}", "missing from connectivity") from error
            cache[token] = Lane(token, xyz, list(outgoing))
        lanes.append(cache[token])
    return lanes


def sensor_to_world(nusc, sample_data: dict) -> np.ndarray:
    calib = nusc.get("calibrated_sensor", sample_data["calibrated_sensor_token"])
    ego = nusc.get("ego_pose", sample_data["ego_pose_token"])
    return pose_matrix(ego["rotation"], ego["translation"]) @ pose_matrix(
        calib["rotation"], calib["translation"]
    )


def ground_plane(calib: dict) -> tuple[float, list[float]]:
    """The ego's ground plane in the LIDAR_TOP (BEV) frame as z = ground_z + a x + b y: (ground_z, [a, b]).
    A nuScenes ego pose sits on the ground (ego z = 0), and LIDAR_TOP is mounted tilted on the ego (pitched
    1.4 deg nose-down on the real rig), so the ground is the plane of the points p with (R p + t)_z = 0
    (R, t: the calibrated lidar -> ego): up . p = -t_z, where up, R's last row, is the ego's z axis in
    LIDAR_TOP coordinates. ground_z is its z at the BEV origin, a and b its rises dz/dx and dz/dy."""
    lidar_to_ego = pose_matrix(calib["rotation"], calib["translation"])
    up, height = lidar_to_ego[2, :3], lidar_to_ego[2, 3]
    return float(-height / up[2]), [float(-up[0] / up[2]), float(-up[1] / up[2])]


def index_log(ref: SceneRef) -> LogIndex:
    """Every key frame's time, position (LIDAR_TOP, the BEV origin) and sample token, and the scene's map,
    from the tables alone."""
    nusc = load_tables(ref.dataroot, ref.version)
    scene = nusc.get("scene", ref.scene_token)
    times, xy, tokens = [], [], []
    token = scene["first_sample_token"]
    while token:
        sample = nusc.get("sample", token)
        times.append(int(sample["timestamp"]) * 1000)
        xy.append(sensor_to_world(nusc, nusc.get("sample_data", sample["data"]["LIDAR_TOP"]))[:2, 3])
        tokens.append(token)
        token = sample["next"]
    city = nusc.get("log", scene["log_token"])["location"]
    return LogIndex(city, np.array(times, np.int64), np.array(xy, np.float64).reshape(-1, 2), tokens)


def load_log(ref: SceneRef, margin: float) -> Log:
    """One scene as a Log; margin is the crop's radius (lanes farther from every pose are left out)."""
    nusc = load_tables(ref.dataroot, ref.version)
    scene = nusc.get("scene", ref.scene_token)
    map_name = nusc.get("log", scene["log_token"])["location"]
    frames = []
    token = scene["first_sample_token"]
    while token:
        sample = nusc.get("sample", token)
        lidar = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])
        lidar_to_world = sensor_to_world(nusc, lidar)
        lidar_calib = nusc.get("calibrated_sensor", lidar["calibrated_sensor_token"])
        world_to_lidar = np.linalg.inv(lidar_to_world)
        cameras = []
        for channel in sorted(k for k in sample["data"] if k.startswith("CAM")):
            data = nusc.get("sample_data", sample["data"][channel])
            calib = nusc.get("calibrated_sensor", data["calibrated_sensor_token"])
            # through the world frame: the camera and lidar ego poses differ by their time offset
            cameras.append(
                Camera(channel, data["filename"], np.array(calib["camera_intrinsic"], np.float64),
                       world_to_lidar @ sensor_to_world(nusc, data), int(data["width"]), int(data["height"]))
            )  # fmt: skip
        t = int(sample["timestamp"]) * 1000
        ground_z, ground_slope = ground_plane(lidar_calib)
        frames.append(
            Frame(
                frame_id=f"nuscenes/{scene['name']}/{t}",
                dataset="nuscenes",
                split=ref.split,
                log_id=scene["name"],
                timestamp_ns=t,
                city=map_name,
                ego_to_world=lidar_to_world,
                cameras=cameras,
                lidar_path=lidar["filename"],
                lidar_to_ego=np.eye(4),
                ground_z=ground_z,
                ground_slope=ground_slope,
                sample_token=token,
            )
        )
        token = sample["next"]
    if not frames:
        return Log("nuscenes", ref.split, scene["name"], str(ref.dataroot / ref.version), [], [], True)
    positions = np.array([f.ego_to_world[:2, 3] for f in frames])
    centre = (positions.min(0) + positions.max(0)) / 2
    radius = np.linalg.norm(positions.max(0) - positions.min(0)) / 2 + margin
    lanes = lanes_near(ref.dataroot, map_name, centre, radius)
    tables = str(ref.dataroot / ref.version)
    return Log("nuscenes", ref.split, scene["name"], tables, lanes, frames, True, f"{tables}/ego_pose.json")
