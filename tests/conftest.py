"""Shared fixtures: the real AV2 fixtures in ../shared/data and datasets prepared from them."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
AV2_ROOT = SHARED_DATA / "av2" / "sensor"


def require_shared_av2() -> Path:
    if not AV2_ROOT.is_dir():
        pytest.skip(f"real AV2 fixtures not found at {AV2_ROOT} (../shared/data beside the repo)")
    return AV2_ROOT


@pytest.fixture(scope="session")
def av2_root() -> Path:
    return require_shared_av2()


@pytest.fixture(scope="session")
def prepared_av2(av2_root, tmp_path_factory) -> Path:
    """The real AV2 logs prepared with the default options."""
    from pipeline.prepare import prepare
    from pipeline.targets import TargetOptions

    out = tmp_path_factory.mktemp("prepared_av2")
    prepare("av2", av2_root, out, TargetOptions())
    return out


@pytest.fixture(scope="session")
def synth_raw(tmp_path_factory) -> Path:
    """A small synthetic raw dataset (both formats), seed 0: 4 logs of 20 frames at 10 Hz in world 0, on its
    roundabout, fork, S-bend and a left turn (3 train, 1 val)."""
    from pipeline.synth import synth

    out = tmp_path_factory.mktemp("synth")
    synth(
        out,
        logs=4,
        frames_per_log=20,
        seed=0,
        frame_period=0.1,
        worlds=1,
        val_frames_per_log=20,
        val_frame_period=0.1,
    )
    return out


@pytest.fixture(scope="session")
def synth_prepared(synth_raw, tmp_path_factory) -> dict[str, Path]:
    """The synthetic dataset prepared from each format: {'av2': dir, 'nuscenes': dir}."""
    from pipeline.prepare import prepare
    from pipeline.targets import TargetOptions

    out = tmp_path_factory.mktemp("synth_prepared")
    prepare("av2", synth_raw / "av2" / "sensor", out / "av2", TargetOptions())
    prepare("nuscenes", synth_raw / "nuscenes", out / "nuscenes", TargetOptions(), version="v1.0-mini")
    return {"av2": out / "av2", "nuscenes": out / "nuscenes"}


def overfit_history(built, sensors, targets, steps: int, lr: float = 3e-3) -> list[dict[str, float]]:
    """The losses of `steps` Adam steps of a model's `Built` record on one fixed batch."""
    import torch

    optimiser = torch.optim.Adam(built.model.parameters(), lr=lr)
    history = []
    for _ in range(steps):
        losses = built.loss(built.model(sensors), targets)
        optimiser.zero_grad()
        losses["loss"].backward()
        optimiser.step()
        history.append({k: v.item() for k, v in losses.items()})
    return history


@pytest.fixture
def overfit():
    """`overfit_history`, for the models' "the loss falls when overfitting one batch" tests."""
    return overfit_history


# Real sensors (tests/test_real_sensors.py): one nuScenes key frame and one AV2 sweep of ../shared/data,
# each as the devkit reads it, prepared by `cli prepare`.
NUSCENES_KEYFRAME = SHARED_DATA / "nuscenes" / "keyframe_scene-0061"
AV2_SWEEP_LOG = SHARED_DATA / "av2" / "sensor_lidar" / "train" / "adcf7d18-0510-35b0-a2fa-b4cea13a6d76"
NUSCENES_LOGFILE = "n015-2018-07-24-11-22-45+0800"  # the log of v1.0-mini's scene-0061


def require_shared(path: Path, what: str) -> Path:
    if not path.exists():
        pytest.skip(f"{what} not found at {path} (../shared/data beside the repo)")
    return path


def _nuscenes_token(*parts: object) -> str:
    import hashlib

    return hashlib.md5("/".join(map(str, ("keyframe_scene-0061", *parts))).encode()).hexdigest()


def _rigid(matrix) -> tuple[list[float], list[float]]:
    """(w, x, y, z) rotation and translation of a 4x4 row-major transform, as the nuScenes tables hold them
    (scipy orthonormalises the float32 rotations of mmdetection3d's info file)."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    matrix = np.asarray(matrix, np.float64)
    x, y, z, w = Rotation.from_matrix(matrix[:3, :3]).as_quat()
    return [float(w), float(x), float(y), float(z)], [float(v) for v in matrix[:3, 3]]


def synthetic_map_around(pose, seed: int = 0) -> dict:
    """The nuScenes map expansion of synth world 1 (`pipeline/synth/nuscenes_map.py`), moved rigidly so
    that the ego pose (a 4x4 ego-to-global transform) stands in the middle of a lane of a road, heading
    along it, 15 m before the world's main junction. The map is synthetic; no real map expansion is here."""
    import numpy as np

    from pipeline.synth.nuscenes_map import map_expansion
    from pipeline.synth.world import build_world

    world = build_world(seed, 1)
    route = next(r for r in world.routes if r.name == "junction_straight")
    line = np.concatenate([world.lanes[i].centerline(0.25)[:, :2] for i in route.lanes])
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))]
    at = int(np.searchsorted(arc, arc[np.argmin(np.linalg.norm(line - route.focus, axis=1))] - 15.0))
    heading = np.arctan2(*(line[at + 1] - line[at])[::-1])
    pose = np.asarray(pose, np.float64)
    turn = np.arctan2(pose[1, 0], pose[0, 0]) - heading
    c, s = np.cos(turn), np.sin(turn)
    rotation = np.array([[c, -s], [s, c]])

    def moved(x: float, y: float) -> list[float]:
        return list(rotation @ (np.array([x, y]) - line[at]) + pose[:2, 3])

    expansion = map_expansion(world)
    for node in expansion["node"]:
        node["x"], node["y"] = moved(node["x"], node["y"])
    for arcs in expansion["arcline_path_3"].values():
        for arc_record in arcs:
            for key in ("start_pose", "end_pose"):
                x, y, yaw = arc_record[key]
                arc_record[key] = [*moved(x, y), float((yaw + turn + np.pi) % (2 * np.pi) - np.pi)]
    expansion["canvas_edge"] = [1585.6, 2025.0]  # the real singapore-onenorth canvas
    return expansion


def write_nuscenes_keyframe(root: Path) -> Path:
    """nuScenes v1.0-mini tables for the one real sample of ../shared/data/nuscenes/keyframe_scene-0061, as
    nuscenes-devkit reads them, with its real sensor files in samples/ (links) and a synthetic map.

    The sensors are real: the LIDAR_TOP sweep, the six 1600 x 900 images, their intrinsics and extrinsics
    (calibrated_sensor) and the ego pose at the LiDAR time (mmdetection3d's info file). Each camera's ego
    pose, at its own timestamp (0.5-43 ms before the LiDAR's), follows from mmdetection3d's `lidar2cam`,
    as the data README says: ego2global_cam = ego2global . lidar2ego . inv(lidar2cam) . inv(cam2ego).
    The map expansion around the ego is SYNTHETIC (`synthetic_map_around`): lanes and the lane graph
    prepared from it are not this street's."""
    import json

    import cv2
    import numpy as np

    source = json.loads((NUSCENES_KEYFRAME / "calibration.json").read_text())
    ego2global = np.array(source["ego2global"], np.float64)
    lidar2ego = np.array(source["lidar"]["lidar2ego"], np.float64)
    sample = source["sample_token"]
    log, scene = _nuscenes_token("log"), _nuscenes_token("scene")
    t = {k: [] for k in "category attribute visibility instance sample_annotation".split()}
    t |= {k: [] for k in "sensor calibrated_sensor ego_pose sample_data".split()}
    t["log"] = [
        dict(token=log, logfile=NUSCENES_LOGFILE, vehicle="n015", date_captured="2018-07-24",
             location="singapore-onenorth")
    ]  # fmt: skip
    t["map"] = [
        dict(token=_nuscenes_token("map"), category="semantic_prior", log_tokens=[log],
             filename="maps/semantic_prior.png")
    ]  # fmt: skip
    t["scene"] = [
        dict(token=scene, log_token=log, nbr_samples=1, name="scene-0061", first_sample_token=sample,
             last_sample_token=sample, description="real sensors of v1.0-mini's first sample, synthetic map")
    ]  # fmt: skip
    t["sample"] = [dict(token=sample, timestamp=source["timestamp_us"], prev="", next="", scene_token=scene)]
    # (channel, modality, file, timestamp in us, sensor -> ego, ego -> global, intrinsics, sample_data token)
    channels = [
        ("LIDAR_TOP", "lidar", source["lidar"]["filename"], source["timestamp_us"], lidar2ego, ego2global, [],
         _nuscenes_token("sample_data", "LIDAR_TOP"))
    ]  # fmt: skip
    for name, camera in source["cameras"].items():
        cam2ego = np.array(camera["cam2ego"], np.float64)
        lidar2cam = np.array(camera["lidar2cam"], np.float64)
        cam_ego2global = ego2global @ lidar2ego @ np.linalg.inv(lidar2cam) @ np.linalg.inv(cam2ego)
        stamp = round(camera["timestamp_s"] * 1e6)
        channels.append(
            (name, "camera", camera["filename"], stamp, cam2ego, cam_ego2global, camera["cam2img"],
             camera["sample_data_token"])
        )  # fmt: skip
    for name, modality, filename, stamp, sensor2ego, pose, intrinsic, data_token in channels:
        (root / "samples" / name).mkdir(parents=True, exist_ok=True)
        (root / "samples" / name / filename).symlink_to(NUSCENES_KEYFRAME / filename)
        sensor, calibrated, ego = (_nuscenes_token(kind, name) for kind in ("sensor", "calibrated", "ego"))
        t["sensor"].append(dict(token=sensor, channel=name, modality=modality))
        rotation, translation = _rigid(sensor2ego)
        t["calibrated_sensor"].append(
            dict(token=calibrated, sensor_token=sensor, rotation=rotation, translation=translation,
                 camera_intrinsic=intrinsic)
        )  # fmt: skip
        rotation, translation = _rigid(pose)
        t["ego_pose"].append(dict(token=ego, timestamp=stamp, rotation=rotation, translation=translation))
        size = (1600, 900) if modality == "camera" else (0, 0)
        t["sample_data"].append(
            dict(token=data_token, sample_token=sample, ego_pose_token=ego,
                 calibrated_sensor_token=calibrated, timestamp=stamp,
                 fileformat="pcd" if modality == "lidar" else "jpg", is_key_frame=True,
                 width=size[0], height=size[1], filename=f"samples/{name}/{filename}", prev="", next="")
        )  # fmt: skip
    (root / "v1.0-mini").mkdir(parents=True)
    for name, records in t.items():
        (root / "v1.0-mini" / f"{name}.json").write_text(json.dumps(records, indent=0))
    (root / "maps" / "expansion").mkdir(parents=True)
    expansion = synthetic_map_around(ego2global)
    (root / "maps" / "expansion" / "singapore-onenorth.json").write_text(json.dumps(expansion))
    cv2.imwrite(str(root / "maps" / "semantic_prior.png"), np.zeros((8, 8), np.uint8))  # never read
    return root


def write_av2_sweep_log(root: Path) -> Path:
    """An AV2 sensor root (`root/train/<log>/`) of the real log with one real sweep of
    ../shared/data/av2/sensor_lidar (map, poses, calibration and sweep linked), and a blank JPEG of each ring
    camera's calibrated size (portrait for ring_front_center) at the sweep's timestamp, standing in for the
    images that no published source holds."""
    import cv2
    import numpy as np
    import pyarrow.feather as feather

    log = root / "train" / AV2_SWEEP_LOG.name
    log.mkdir(parents=True)
    for entry in AV2_SWEEP_LOG.iterdir():
        (log / entry.name).symlink_to(entry)
    (sweep,) = (AV2_SWEEP_LOG / "sensors" / "lidar").glob("*.feather")
    (log / "sensors").unlink()  # a folder of its own, for the cameras
    (log / "sensors" / "lidar").mkdir(parents=True)
    (log / "sensors" / "lidar" / sweep.name).symlink_to(sweep)
    intrinsics = feather.read_table(AV2_SWEEP_LOG / "calibration" / "intrinsics.feather").to_pylist()
    for row in intrinsics:
        if row["sensor_name"].startswith("ring_"):
            folder = log / "sensors" / "cameras" / row["sensor_name"]
            folder.mkdir(parents=True)
            blank = np.full((row["height_px"], row["width_px"], 3), 128, np.uint8)
            cv2.imwrite(str(folder / f"{sweep.stem}.jpg"), blank)
    return root


def cli_prepare(*args: str) -> None:
    from typer.testing import CliRunner

    from cli import app

    result = CliRunner().invoke(app, ["prepare", *args])
    assert result.exit_code == 0, result.output


@pytest.fixture(scope="session")
def real_nuscenes_keyframe(tmp_path_factory) -> Path:
    """The dataroot of `write_nuscenes_keyframe`: real sensors, synthetic map."""
    require_shared(NUSCENES_KEYFRAME, "the real nuScenes key frame")
    return write_nuscenes_keyframe(tmp_path_factory.mktemp("nuscenes_keyframe"))


@pytest.fixture(scope="session")
def real_nuscenes_prepared(real_nuscenes_keyframe, tmp_path_factory) -> Path:
    """`cli prepare --dataset nuscenes --version v1.0-mini` of the real key frame (split mini_train)."""
    out = tmp_path_factory.mktemp("nuscenes_keyframe_prepared")
    cli_prepare("--dataset", "nuscenes", "--root", str(real_nuscenes_keyframe), "--version", "v1.0-mini",
                "--out", str(out), "--overwrite")  # fmt: skip
    return out


@pytest.fixture(scope="session")
def real_av2_sweep_root(tmp_path_factory) -> Path:
    """The AV2 sensor root of `write_av2_sweep_log`: the real sweep and calibration, blank images."""
    require_shared(AV2_SWEEP_LOG / "sensors" / "lidar", "the real AV2 sweep")
    return write_av2_sweep_log(tmp_path_factory.mktemp("av2_sweep"))


@pytest.fixture(scope="session")
def real_av2_sweep_prepared(real_av2_sweep_root, tmp_path_factory) -> Path:
    """`cli prepare --dataset av2` of the one-sweep log (one frame, keyed by its sweep)."""
    out = tmp_path_factory.mktemp("av2_sweep_prepared")
    cli_prepare("--dataset", "av2", "--root", str(real_av2_sweep_root), "--out", str(out), "--overwrite")
    return out


@pytest.fixture(autouse=True)
def torch_threads_restored():
    """torch's thread count as before each test: an in-process `train` or `evaluate` sets the run's
    (config.train.threads), and a later test in the same worker would compute in another summation order
    (test_piece_models' STSU overfitting fell short of its bar after one)."""
    torch = sys.modules.get("torch")
    before = torch.get_num_threads() if torch is not None else None
    yield
    if before is not None and torch.get_num_threads() != before:
        torch.set_num_threads(before)

