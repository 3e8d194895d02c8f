"""`cli synth`: both formats load through the real devkits and describe the same world."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest

from pipeline.synth import synth
from pipeline.synth.logs import MINI_TRAIN, MINI_VAL, TRAINVAL_TRAIN, TRAINVAL_VAL, plan_logs
from pipeline.synth.world import MAX_WORLDS, build_world

SEED = 3
CROP_X, CROP_Y = 15.0, 30.0  # the default 30 x 60 m range around the BEV origin
FRAMES = 6


@pytest.fixture(scope="module")
def worlds():
    return [build_world(SEED, k) for k in range(MAX_WORLDS)]


@pytest.fixture(scope="module")
def world(worlds):
    return worlds[0]


@pytest.fixture(scope="module")
def out(tmp_path_factory):
    """4 logs (3 train on worlds 0-2, 1 val on world 3) of 6 frames 1 s apart."""
    root = tmp_path_factory.mktemp("synth")
    summary = synth(
        root, logs=4, frames_per_log=FRAMES, seed=SEED, frame_period=1.0, val_frames_per_log=FRAMES
    )
    assert summary["complete"]
    return root


@pytest.fixture(scope="module")
def av2_logs(out):
    return sorted((out / "av2" / "sensor").glob("*/*"))


@pytest.fixture(scope="module")
def world_of(out, worlds):
    """The world of each log, by AV2 log id and by nuScenes scene name, as synth.json records it."""
    logs = json.loads((out / "synth.json").read_text())["logs"]
    return {key: worlds[log["world"]] for log in logs for key in (log["log_id"], log["scene"])}


@pytest.fixture(scope="module")
def nusc(out):
    from nuscenes import NuScenes

    return NuScenes(version="v1.0-mini", dataroot=str(out / "nuscenes"), verbose=False)


@pytest.fixture(scope="module")
def nusc_map(out, world):
    from nuscenes.map_expansion.map_api import NuScenesMap

    return NuScenesMap(dataroot=str(out / "nuscenes"), map_name=world.nuscenes_map)


def distance_to_polyline(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    """Distance from each point (n, 2) to the polyline (m, 2)."""
    a, ab = line[:-1], np.diff(line, axis=0)
    t = np.clip(((points[:, None] - a[None]) * ab[None]).sum(-1) / (ab**2).sum(-1)[None], 0.0, 1.0)
    return np.linalg.norm(points[:, None] - (a[None] + t[..., None] * ab[None]), axis=-1).min(axis=1)


def to_bev(xy: np.ndarray, x: float, y: float, heading: float) -> np.ndarray:
    """World points into the BEV frame of an ego pose: x right, y forward."""
    d = xy - np.array([x, y])
    forward = d @ np.array([math.cos(heading), math.sin(heading)])
    left = d @ np.array([-math.sin(heading), math.cos(heading)])
    return np.column_stack([-left, forward])


def in_crop(bev: np.ndarray) -> np.ndarray:
    return (np.abs(bev[:, 0]) <= CROP_X) & (np.abs(bev[:, 1]) <= CROP_Y)


def yaw_of(rotation: np.ndarray) -> float:
    return math.atan2(rotation[1, 0], rotation[0, 0])


# --- the world -------------------------------------------------------------------------------------


@pytest.mark.parametrize("index", range(MAX_WORLDS))
def test_lanes_join_end_to_start_and_stay_on_the_map(worlds, index):
    world = worlds[index]
    for lane in world.lanes.values():
        # roads are cut at 25 m (27.5 m outside a curve); a left turn across a 5-way junction and the
        # S-bend's middle arc run longer
        assert 5.0 - 1e-6 <= lane.path.length <= 60.0, lane.name
        for nxt in lane.successors:
            a, b = lane.path.end, world.lanes[nxt].path.start
            assert math.hypot(a.x - b.x, a.y - b.y) < 1e-6
            assert abs(math.remainder(a.heading - b.heading, 2 * math.pi)) < 1e-6, (
                lane.name,
                world.lanes[nxt].name,
            )
            assert lane.id in world.lanes[nxt].predecessors
        xy = np.concatenate([lane.boundary(s).points()[:, :2] for s in ("left", "right")])
        assert (xy > 0).all() and (xy < np.array(world.canvas)).all()


LANDMARK_WORLDS = [(seed, k) for seed in range(3) for k in range(MAX_WORLDS)]


@pytest.mark.parametrize(("seed", "index"), LANDMARK_WORLDS)
def test_every_world_holds_every_hard_case(seed, index):
    world = build_world(seed, index)
    lm, lanes = world.landmarks, world.lanes
    assert lm.intersection_arms >= 4 and 3 <= len(lm.roundabout_entries) <= 5
    assert all(lm.intersection_connectors[kind] for kind in ("left", "straight", "right"))
    assert all(lm.t_junction_connectors[kind] for kind in ("left", "straight", "right"))
    # the ring is a cycle, entered and left by every arm, and fits the crop from roundabout_view
    ring = lm.ring_lanes
    for a, b in zip(ring, ring[1:] + ring[:1], strict=True):
        assert b in lanes[a].successors
    assert all(any(e in lanes[r].successors for r in ring) for e in lm.roundabout_exits)
    assert all(any(r in lanes[e].successors for r in ring) for e in lm.roundabout_entries)
    view = lm.roundabout_view
    for lane in ring:
        centre = np.hypot(*(lanes[lane].centerline()[:, :2] - np.array(lm.roundabout_centre)).T)
        assert np.allclose(centre, lm.roundabout_radius)
        assert in_crop(to_bev(lanes[lane].centerline()[:, :2], view.x, view.y, view.heading)).all()
    # fork and merge
    assert lanes[lm.fork_lane].successors == lm.fork_branches and len(lm.fork_branches) == 2
    assert lanes[lm.merge_lane].predecessors == lm.merge_sources and len(lm.merge_sources) == 2
    assert lm.ramp_lanes[0] in lm.fork_branches and lm.ramp_lanes[-1] in lm.merge_sources
    # one lane segment leaves the lateral range and comes back
    view = lm.reentering_view
    inside = in_crop(to_bev(lanes[lm.reentering_lane].centerline()[:, :2], view.x, view.y, view.heading))
    assert inside[0] and inside[-1] and not inside.all()
    assert all(lanes[i].path.pieces[0].curvature != 0 for i in lm.curved_road_lanes)


# sha256 of world 1 of seed 1, every field and every float's bits (world_digest), as drawn when
# world.py's `_draw` was split into one function per road feature (issue 31): the split moved no draw.
WORLD_1_1_SHA256 = "f7ea2ee92d50bfa63b93c1786e97ce539b13317cf173e7bfadf341738e0bd5e3"


def world_digest(world) -> str:
    """sha256 of a world: its dataclasses field by field, arrays by dtype, shape and bytes, floats by
    every bit."""
    digest = hashlib.sha256()

    def feed(value) -> None:
        if dataclasses.is_dataclass(value):
            digest.update(f"{type(value).__name__}(".encode())
            for field in dataclasses.fields(value):
                digest.update(field.name.encode())
                feed(getattr(value, field.name))
        elif isinstance(value, np.ndarray):
            digest.update(f"array {value.dtype} {value.shape};".encode())
            digest.update(np.ascontiguousarray(value).tobytes())
        elif isinstance(value, dict):
            digest.update(f"dict {len(value)};".encode())
            for key, item in value.items():
                feed(key)
                feed(item)
        elif isinstance(value, list | tuple):
            digest.update(f"list {len(value)};".encode())
            for item in value:
                feed(item)
        elif isinstance(value, float):  # numpy's float64 too
            digest.update(f"float {float(value).hex()};".encode())
        else:
            digest.update(f"{type(value).__name__} {value!r};".encode())

    feed(world)
    return digest.hexdigest()


def test_a_seed_draws_the_same_world_bytes():
    assert world_digest(build_world(1, 1)) == WORLD_1_1_SHA256


def test_same_seed_same_world_other_seed_other_layout():
    a, b, c = build_world(1), build_world(1), build_world(2)
    assert list(a.lanes) == list(b.lanes) and a.landmarks == b.landmarks and a.routes == b.routes
    assert not set(a.lanes) & set(c.lanes)

    def shape(world) -> tuple:
        """What a shift or a rotation of the map would keep: lengths, widths, turn sizes, degrees."""
        return (
            sorted(round(lane.path.length, 3) for lane in world.lanes.values()),
            sorted(round(lane.width, 3) for lane in world.lanes.values()),
            round(world.landmarks.roundabout_radius, 3),
            sorted(len(lane.successors) for lane in world.lanes.values()),
        )

    for other in (c, build_world(1, 1)):  # another seed, another world of the same seed
        assert all(x != y for x, y in zip(shape(a)[:3], shape(other)[:3], strict=True))
    # the layout really varies: lane counts per direction, lane widths, junction arms, ring sizes
    drawn = [build_world(seed, k) for seed in range(3) for k in range(2)]
    assert len({w.landmarks.intersection_arms for w in drawn}) == 2
    assert len({len(w.landmarks.roundabout_entries) for w in drawn}) >= 2
    widths = np.array([lane.width for w in drawn for lane in w.lanes.values() if not lane.is_intersection])
    assert widths.min() < 3.3 and widths.max() > 3.5
    counts = {sum(map(len, w.landmarks.intersection_connectors.values())) for w in drawn}
    assert len(counts) >= 4


def test_routes_put_the_ego_in_every_lane_and_through_every_turn(worlds):
    """Over one seed's routes the ego drives the inner and the outer lanes of multi-lane roads in both
    directions, turns left and right at both junctions and goes round the roundabout."""
    lane_positions, kinds = set(), set()
    for world in worlds:
        lm = world.landmarks
        for route in world.routes:
            kinds.add(route.name)
            for i in route.lanes:
                lane = world.lanes[i]
                if lane.left_neighbor is not None or lane.right_neighbor is not None:
                    side = lane.name.split("/")[1][:3]  # "fwd" or "bwd"
                    position = (
                        "inner"
                        if lane.left_neighbor is None
                        else "outer"
                        if lane.right_neighbor is None
                        else "middle"
                    )
                    lane_positions.add((side, position))
            assert all(b in world.lanes[a].successors for a, b in zip(route.lanes, route.lanes[1:]))
            assert len(set(route.lanes)) == len(route.lanes)
        turned = {i for route in world.routes for i in route.lanes}
        assert turned & set(lm.intersection_connectors["left"]) and turned & set(
            lm.intersection_connectors["right"]
        )
        assert turned & set(lm.ring_lanes)
    assert {(s, p) for s in ("fwd", "bwd") for p in ("inner", "outer")} <= lane_positions
    assert {"junction_left", "junction_right", "roundabout", "fork", "merge", "s_bend", "road"} <= kinds


@pytest.mark.parametrize("seed", [SEED, 1, 2])
def test_both_splits_drive_lanes_with_a_lane_on_their_right(seed):
    """The default logs of training and of validation alike put the ego, in some frames, in a lane with
    another lane of its direction on its right: a training set driven in the outer lane alone teaches a
    model that the ego's right is always empty, which validation then contradicts."""
    worlds = [build_world(seed, k) for k in range(MAX_WORLDS)]
    frames_inner = {"train": 0, "val": 0}
    for plan in plan_logs(worlds, 18, 10, seed, 2 * 10**9, 1, 20, 10**9):  # `cli synth`'s defaults
        world = worlds[plan.world]
        ego = plan.ego_at(plan.frame_ns)[:, :2]
        lanes = [world.lanes[i] for i in plan.route.lanes]
        # the route's lane under each frame: the one whose centerline passes closest
        distances = np.stack([distance_to_polyline(ego, lane.centerline()[:, :2]) for lane in lanes])
        on = [lanes[i] for i in distances.argmin(0)]
        frames_inner[plan.split] += sum(lane.right_neighbor is not None for lane in on)
    # measured (seeds 3, 1, 2): 64 / 59 / 27 training and 8 / 7 / 10 validation frames of 160 / 40;
    # before the inner-lane routes, 41 / 29 / 33 and 8 / 0 / 11
    assert frames_inner["train"] >= 20 and frames_inner["val"] >= 5, frames_inner


# --- AV2 -------------------------------------------------------------------------------------------


def test_av2_logs_load_through_the_av2_api(av2_logs, world_of):
    from av2.map.map_api import ArgoverseStaticMap
    from av2.structures.cuboid import CuboidList
    from av2.utils.io import read_city_SE3_ego

    assert sorted(p.parent.name for p in av2_logs) == ["train", "train", "train", "val"]
    crossings = 0
    for log_dir in av2_logs:
        (map_file,) = (log_dir / "map").glob("log_map_archive_*.json")
        world = world_of[log_dir.name]
        assert map_file.name.split("____")[1].split("_")[0] == world.av2_city
        static_map = ArgoverseStaticMap.from_map_dir(log_dir / "map", build_raster=False)
        assert static_map.log_id == log_dir.name and len(static_map.vector_lane_segments) > 40
        for lane_id, segment in static_map.vector_lane_segments.items():
            lane = world.lanes[lane_id]
            centerline = static_map.get_lane_segment_centerline(lane_id)
            assert centerline.shape == (10, 3)
            # the av2 API's centerline (10 points, the mean of the two boundaries at equal fractions of
            # their lengths) strays from the true one on tight turns: up to ~8 cm on a 5 m radius
            tolerance = 0.1 if lane.is_intersection else 0.02
            assert distance_to_polyline(centerline[:, :2], lane.centerline(0.1)[:, :2]).max() < tolerance, (
                lane.name
            )
            assert segment.successors == lane.successors and segment.is_intersection == lane.is_intersection
            assert (
                segment.left_neighbor_id == lane.left_neighbor
                and segment.right_neighbor_id == lane.right_neighbor
            )
        poses = read_city_SE3_ego(log_dir)
        frames = sorted({c.timestamp_ns for c in CuboidList.from_feather(log_dir / "annotations.feather")})
        assert len(frames) == FRAMES and np.all(np.diff(frames) == 1_000_000_000)
        assert set(frames) <= set(poses) and len(poses) > 5 * len(frames)  # poses at a higher rate
        crossings += len(static_map.get_scenario_ped_crossings())
    assert crossings  # the logs near a junction see its crossings


def test_av2_local_maps_cover_the_crop_of_every_frame(av2_logs, world_of):
    """Every world lane that reaches into a frame's 30 x 60 m crop is in that log's local map."""
    from av2.map.map_api import ArgoverseStaticMap
    from av2.utils.io import read_city_SE3_ego

    for log_dir in av2_logs:
        world = world_of[log_dir.name]
        ids = set(ArgoverseStaticMap.from_map_dir(log_dir / "map").vector_lane_segments)
        poses = read_city_SE3_ego(log_dir)
        for ns in list(poses)[::25]:
            pose = poses[ns]
            x, y, heading = pose.translation[0], pose.translation[1], yaw_of(pose.rotation)
            seen = {
                i
                for i, lane in world.lanes.items()
                if in_crop(to_bev(lane.centerline(1.0)[:, :2], x, y, heading)).any()
            }
            assert seen and seen <= ids


# --- nuScenes --------------------------------------------------------------------------------------


def test_nuscenes_tables_load_with_official_split_names(nusc, world_of):
    from nuscenes.utils.splits import create_splits_scenes
    from pyquaternion import Quaternion

    from pipeline.synth.rig import NUSCENES_LIDAR

    splits = create_splits_scenes()
    assert MINI_TRAIN == splits["mini_train"] and MINI_VAL == splits["mini_val"]
    assert TRAINVAL_TRAIN == splits["train"][: len(TRAINVAL_TRAIN)] and TRAINVAL_VAL == splits["val"][:2]
    names = [s["name"] for s in nusc.scene]
    assert names == splits["mini_train"][:3] + splits["mini_val"][:1]
    for scene in nusc.scene:
        assert nusc.get("log", scene["log_token"])["location"] == world_of[scene["name"]].nuscenes_map
        sample = nusc.get("sample", scene["first_sample_token"])
        lidar = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])
        calib = nusc.get("calibrated_sensor", lidar["calibrated_sensor_token"])
        assert calib["translation"] == [0.943, 0.0, 1.84]
        # turned -90 deg about z and tilted as the real rig: the ego's up axis in LIDAR_TOP coordinates is
        # the real calibration's (v1.0-mini scene-0061: lidar2ego's last row)
        assert np.allclose(calib["rotation"], NUSCENES_LIDAR.quaternion)
        up = Quaternion(calib["rotation"]).rotation_matrix[2]
        np.testing.assert_allclose(up, [-0.00589965, -0.02422936, 0.99968904], atol=1e-7)
        assert abs(Quaternion(calib["rotation"]).rotation_matrix[0, 0]) < 1e-12  # its x axis: the ego's right
        assert lidar["is_key_frame"] and sample["anns"]
    # one semantic prior per location, and every ego pose is on its location's drivable area
    assert sorted(len(m["log_tokens"]) for m in nusc.map) == [1, 1, 1, 1]
    prior = {log: m["mask"] for m in nusc.map for log in m["log_tokens"]}
    for sample in nusc.sample:
        log = nusc.get("scene", sample["scene_token"])["log_token"]
        lidar = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])
        assert prior[log].is_on_mask(*nusc.get("ego_pose", lidar["ego_pose_token"])["translation"][:2])


def test_nuscenes_map_matches_the_world(nusc_map, world):
    lanes = {r["token"] for r in nusc_map.lane}
    connectors = {r["token"] for r in nusc_map.lane_connector}
    assert len(lanes) + len(connectors) == len(world.lanes)
    tokens = [world.token_of(i) for i in world.lanes]
    discretized = nusc_map.discretize_lanes(tokens, 0.1)
    for lane, tok in zip(world.lanes.values(), tokens, strict=True):
        assert (tok in connectors) == lane.is_intersection
        poses = np.array(discretized[tok])
        dense = lane.centerline(0.05)[:, :2]
        assert distance_to_polyline(poses[:, :2], dense).max() < 0.005, lane.name
        assert np.abs(poses[[0, -1], :2] - dense[[0, -1]]).max() < 1e-6
        assert nusc_map.get_outgoing_lane_ids(tok) == [world.token_of(i) for i in lane.successors]
        assert nusc_map.get_incoming_lane_ids(tok) == [world.token_of(i) for i in lane.predecessors]
        nusc_map.extract_polygon(
            nusc_map.get("lane_connector" if lane.is_intersection else "lane", tok)["polygon_token"]
        )
    lm = world.landmarks
    # the ring is the nearest lane to its centre; the entry and exit arcs touch it from outside
    roundabout = lm.ring_lanes + lm.roundabout_entries + lm.roundabout_exits
    assert nusc_map.get_closest_lane(*lm.roundabout_centre, radius=13) in {
        world.token_of(i) for i in roundabout
    }


# --- both ------------------------------------------------------------------------------------------


def test_the_formats_share_frames_and_poses(nusc, av2_logs):
    from av2.utils.io import read_city_SE3_ego

    av2 = {p.name: (p, read_city_SE3_ego(p)) for p in av2_logs}
    summary = json.loads((av2_logs[0].parents[3] / "synth.json").read_text())
    assert summary["complete"]
    for log, scene in zip(summary["logs"], nusc.scene, strict=True):
        assert log["scene"] == scene["name"]
        log_dir, poses = av2[log["log_id"]]
        token = scene["first_sample_token"]
        while token:
            sample = nusc.get("sample", token)
            lidar = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])
            ego = nusc.get("ego_pose", lidar["ego_pose_token"])
            pose = poses[sample["timestamp"] * 1000]  # the AV2 pose at exactly the sample's time
            assert np.allclose(ego["translation"], pose.translation, atol=1e-9)
            assert ego["rotation"][1] == ego["rotation"][2] == 0.0  # a yaw: the world is flat
            assert (
                abs(
                    math.remainder(
                        2 * math.atan2(ego["rotation"][3], ego["rotation"][0]) - yaw_of(pose.rotation),
                        2 * math.pi,
                    )
                )
                < 1e-9
            )
            token = sample["next"]


def test_frames_see_the_hard_cases(worlds):
    """Logs on the routes of the roundabout, the S-bend and the fork see the whole ring, the lane that
    leaves the crop and comes back, and the fork, in several frames each."""
    for world in worlds[:2]:
        lm, lanes = world.landmarks, world.lanes

        def frames(kind: str, points: np.ndarray, world=world) -> list[np.ndarray]:
            """Per frame of a 20-frame 10 Hz log on the world's first route of this kind: which points
            lie in the crop."""
            only = dataclasses.replace(world, routes=[r for r in world.routes if r.name == kind])
            (plan,) = plan_logs([only], 1, 20, SEED)
            return [in_crop(to_bev(points, *pose)) for pose in plan.ego_at(plan.frame_ns)]

        ring = np.concatenate([lanes[i].centerline()[:, :2] for i in lm.ring_lanes])
        assert sum(inside.all() for inside in frames("roundabout", ring)) >= 3
        bend = frames("s_bend", lanes[lm.reentering_lane].centerline()[:, :2])
        assert sum(inside[0] and inside[-1] and not inside.all() for inside in bend) >= 3
        fork = lanes[lm.fork_lane].path.end.xy[None]
        assert sum(inside.all() for inside in frames("fork", fork)) >= 3


def test_validation_logs_drive_in_worlds_no_training_log_visits(out):
    summary = json.loads((out / "synth.json").read_text())
    train = {log["world"] for log in summary["logs"] if log["split"] == "train"}
    val = {log["world"] for log in summary["logs"] if log["split"] == "val"}
    assert train == {0, 1, 2} and val == {3}
    assert [w["splits"] for w in summary["worlds"]] == [["train"], ["train"], ["train"], ["val"]]
    assert len({w["nuscenes_map"] for w in summary["worlds"]}) == 4


# --- sensors ---------------------------------------------------------------------------------------


def painted_lines(world, marks=("SOLID_WHITE", "SOLID_YELLOW", "DASHED_WHITE", "DOUBLE_SOLID_YELLOW")):
    """(n, 2) points every 10 cm along the lane boundaries that carry these marks."""
    lines = []
    for lane in world.lanes.values():
        for side, mark in (("left", lane.left_mark), ("right", lane.right_mark)):
            if mark in marks:
                lines.append(lane.boundary(side).points(spacing=0.1)[:, :2])
    return np.concatenate(lines)


def on_crosswalk(world, xy: np.ndarray) -> np.ndarray:
    inside = np.zeros(len(xy), bool)
    for crossing in world.crosswalks:
        origin = crossing.edge1[0]
        across, along = crossing.edge1[1] - origin, crossing.edge2[0] - origin
        a = (xy - origin) @ across / (across @ across)
        b = (xy - origin) @ along / (along @ along)
        inside |= (a > -0.1) & (a < 1.1) & (b > -0.1) & (b < 1.1)
    return inside


def assert_paint_is_bright_in_lidar(world, world_xyz: np.ndarray, intensity: np.ndarray) -> None:
    """High-intensity ground returns lie on lane paint (or a crosswalk), and there are some."""
    from scipy.spatial import cKDTree

    bright = (intensity > 70) & (np.abs(world_xyz[:, 2]) < 0.1)
    xy = world_xyz[bright, :2]
    xy = xy[~on_crosswalk(world, xy)]
    distance, _ = cKDTree(painted_lines(world)).query(xy)
    assert len(xy) > 50 and np.mean(distance < 0.35) > 0.97


def test_av2_sensors_load_through_the_av2_api(av2_logs, world_of):
    from av2.geometry.camera.pinhole_camera import PinholeCamera
    from av2.structures.sweep import Sweep
    from av2.utils.io import read_city_SE3_ego, read_feather

    from pipeline.synth.rig import AV2_CAMERAS

    for log_dir in av2_logs:
        world = world_of[log_dir.name]
        sweeps = sorted((log_dir / "sensors" / "lidar").glob("*.feather"))
        frames = np.unique(read_feather(log_dir / "annotations.feather")["timestamp_ns"])
        assert [int(p.stem) for p in sweeps] == frames.tolist()  # frames are keyed by the sweeps
        poses = read_city_SE3_ego(log_dir)
        xyz, intensity = [], []
        for path in sweeps:
            sweep = Sweep.from_feather(path)
            xyz.append(poses[sweep.timestamp_ns].transform_point_cloud(sweep.xyz))
            assert 80_000 < len(sweep.xyz) < 115_000  # two VLP-32C in a city: ~100,000 points
            intensity.append(sweep.intensity)
        assert_paint_is_bright_in_lidar(world, np.concatenate(xyz), np.concatenate(intensity))
        for spec in AV2_CAMERAS:
            camera = PinholeCamera.from_feather(log_dir, spec.name)
            images = sorted((log_dir / "sensors" / "cameras" / spec.name).glob("*.jpg"))
            assert [int(p.stem) for p in images] == frames.tolist()
            image = cv2_read(images[0])
            assert image.shape == (camera.height_px, camera.width_px, 3)
        # paint projected through the written calibration lands on bright pixels of ring_front_center
        camera = PinholeCamera.from_feather(log_dir, "ring_front_center")
        brightness = []
        for path in sorted((log_dir / "sensors" / "cameras" / "ring_front_center").glob("*.jpg"))[::2]:
            to_ego = poses[int(path.stem)].inverse()

            def project(xyz: np.ndarray, to_ego=to_ego, camera=camera) -> tuple[np.ndarray, np.ndarray]:
                uv, points_camera, _ = camera.project_ego_to_img(to_ego.transform_point_cloud(xyz))
                return uv, points_camera[:, 2]

            brightness.append(paint_contrast(world, cv2_read(path), project))
        assert np.nanmedian(brightness) > 25, brightness


def cv2_read(path: Path) -> np.ndarray:
    import cv2

    image = cv2.imread(str(path))
    assert image is not None, path
    return image


def paint_contrast(world, image: np.ndarray, project) -> float:
    """Median grey level on solid lane lines minus that on lane centres, on the ground 2-20 m from the
    camera; project(world xyz) -> (uv, depth). NaN when the image shows too few of either."""
    h, w = image.shape[:2]
    grey = image.mean(axis=2)
    levels = []
    centres = np.concatenate([lane.centerline(0.1)[:, :2] for lane in world.lanes.values()])
    for xy in (painted_lines(world, ("SOLID_WHITE", "SOLID_YELLOW")), centres):
        uv, depth = project(np.column_stack([xy, np.zeros(len(xy))]))
        seen = (
            (depth > 2) & (depth < 20) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        )
        if seen.sum() < 20:
            return np.nan
        levels.append(np.median(grey[uv[seen, 1].astype(int), uv[seen, 0].astype(int)]))
    return levels[0] - levels[1]


def test_nuscenes_sensors_load_through_the_devkit(nusc, out, world_of):
    from nuscenes.utils.data_classes import LidarPointCloud
    from pyquaternion import Quaternion

    from pipeline.synth.rig import NUSCENES_CAMERAS

    def to_world(record: dict) -> np.ndarray:
        matrix = np.eye(4)
        matrix[:3, :3], matrix[:3, 3] = Quaternion(record["rotation"]).rotation_matrix, record["translation"]
        return matrix

    xyz, intensity, contrast = {}, {}, []
    for sample in nusc.sample:
        world = world_of[nusc.get("scene", sample["scene_token"])["name"]]
        assert sorted(sample["data"]) == sorted(["LIDAR_TOP"] + [c.name for c in NUSCENES_CAMERAS])
        lidar = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])
        cloud = LidarPointCloud.from_file(str(out / "nuscenes" / lidar["filename"]))
        assert 26_000 < cloud.nbr_points() < 38_000  # an HDL-32E in a city: ~34,000 points
        lidar_to_world = to_world(nusc.get("ego_pose", lidar["ego_pose_token"])) @ to_world(
            nusc.get("calibrated_sensor", lidar["calibrated_sensor_token"]))  # fmt: skip
        xyz.setdefault(world.index, []).append(
            cloud.points[:3].T @ lidar_to_world[:3, :3].T + lidar_to_world[:3, 3]
        )
        intensity.setdefault(world.index, []).append(cloud.points[3])
        camera = nusc.get("sample_data", sample["data"]["CAM_FRONT"])
        calib = nusc.get("calibrated_sensor", camera["calibrated_sensor_token"])
        image = cv2_read(out / "nuscenes" / camera["filename"])
        assert image.shape == (camera["height"], camera["width"], 3) == (225, 400, 3)
        world_to_camera = np.linalg.inv(
            to_world(nusc.get("ego_pose", camera["ego_pose_token"])) @ to_world(calib)
        )

        def project(points: np.ndarray, m=world_to_camera, k=np.array(calib["camera_intrinsic"])) -> tuple:
            cam = points @ m[:3, :3].T + m[:3, 3]
            uv = cam @ k.T
            return uv[:, :2] / np.maximum(uv[:, 2:], 1e-9), cam[:, 2]

        contrast.append(paint_contrast(world, image, project))
    for index, clouds in xyz.items():
        world = next(w for w in world_of.values() if w.index == index)
        assert_paint_is_bright_in_lidar(world, np.concatenate(clouds), np.concatenate(intensity[index]))
    assert np.nanmedian(contrast) > 25, contrast


def test_sensors_can_be_left_out(tmp_path):
    synth(tmp_path, logs=2, frames_per_log=3, seed=1, sensors=False, val_frames_per_log=3)
    assert not list((tmp_path / "av2").rglob("sensors")) and not (tmp_path / "nuscenes" / "samples").exists()
    sample_data = json.loads((tmp_path / "nuscenes" / "v1.0-mini" / "sample_data.json").read_text())
    assert {Path(d["filename"]).parent.name for d in sample_data} == {"LIDAR_TOP"}


def test_same_seed_same_bytes_with_one_or_two_workers(tmp_path):
    first, again = tmp_path / "first", tmp_path / "again"
    for out, workers in ((first, 1), (again, 2)):
        synth(out, logs=2, frames_per_log=4, seed=SEED, workers=workers, val_frames_per_log=4)
    files = sorted(p.relative_to(first) for p in first.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    assert any(name.suffix == ".jpg" for name in files) and any(name.suffix == ".bin" for name in files)
    for name in files:
        assert (first / name).read_bytes() == (again / name).read_bytes(), name


def test_rewrites_its_own_output_and_refuses_foreign_folders(tmp_path):
    synth(tmp_path / "a", logs=2, frames_per_log=3, seed=1, sensors=False, val_frames_per_log=3)
    synth(tmp_path / "a", logs=1, frames_per_log=3, seed=2, sensors=False)  # no stale log is left behind
    assert len(list((tmp_path / "a" / "av2" / "sensor").glob("*/*"))) == 1
    (tmp_path / "b" / "nuscenes").mkdir(parents=True)
    with pytest.raises(FileExistsError):
        synth(tmp_path / "b")
    with pytest.raises(ValueError):
        synth(tmp_path / "c", logs=35)
    with pytest.raises(ValueError, match="--workers"):
        synth(tmp_path / "d", workers=0)
    assert not (tmp_path / "d").exists()


def test_more_training_logs_drive_more_routes_and_leave_validation_where_it_was(worlds):
    """`cli synth`'s default 18 logs: 16 training logs 10 frames 2 s apart drive the first 16 routes of the
    training worlds (a roundabout driven through among them); the 2 validation logs, 20 frames 1 s apart,
    drive the routes that the 10 logs' validation drove (a junction from an inner lane, the ring)."""
    few = plan_logs(worlds, 10, 20, SEED, 10**9)
    many = plan_logs(worlds, 18, 10, SEED, 2 * 10**9, 1, 20, 10**9)
    train = [plan for plan in many if plan.split == "train"]
    assert [plan.route for plan in train] == [worlds[k % 3].routes[k] for k in range(16)]
    assert "roundabout_through" in {plan.route.name for plan in train}
    assert {len(plan.frame_ns) for plan in train} == {10} and np.diff(train[0].frame_ns)[0] == 2 * 10**9
    val_few, val_many = ([plan for plan in plans if plan.split == "val"] for plans in (few, many))
    assert [p.route for p in val_many] == [p.route for p in val_few]
    assert [p.route.name for p in val_many] == ["junction_straight", "roundabout_through"]
    assert [len(p.frame_ns) for p in val_many] == [20, 20] and np.diff(val_many[0].frame_ns)[0] == 10**9
    assert [p.scene_name for p in many] == TRAINVAL_TRAIN[:16] + TRAINVAL_VAL


def test_a_longer_frame_period_spreads_the_frames_along_the_route(world):
    dense = plan_logs([world], 2, 20, seed=0)
    sparse = plan_logs([world], 2, 20, seed=0, frame_period_ns=1_000_000_000)
    for d, s in zip(dense, sparse, strict=True):
        assert np.all(np.diff(s.frame_ns) == 1_000_000_000) and np.isin(s.frame_ns, s.pose_ns).all()
        covered = [np.ptp(p.station(p.frame_ns)) for p in (d, s)]
        assert covered[1] > 5 * covered[0]  # the same 20 frames see far more of the road
    with pytest.raises(ValueError, match="multiple of 0.02 s"):
        plan_logs([world], 2, 20, seed=0, frame_period_ns=30_000_000)
