"""pipeline.synth.openlanev2_writer: AV2 logs written in OpenLane-V2's layout (subset A), from `cli synth`'s
synthetic logs and from hand-made lane maps, checked against the av2 API, shapely and hand-computed values."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import DataError
from pipeline.lane_graph import LaneMap, crop_lane_graph, graph_of_annotated
from pipeline.records import AnnotatedLanes, Lane
from pipeline.synth import synth
from pipeline.synth.openlanev2_writer import frame_lanes, write_from_av2

SEED = 1
RING = {"ring_front_center", "ring_front_left", "ring_front_right", "ring_side_left", "ring_side_right",
        "ring_rear_left", "ring_rear_right"}  # fmt: skip
# how far the 201 evenly spaced points of a lane may cut a corner of the map's polyline (1.1 cm at most on
# the real logs of ../shared/data)
CORNER_CUT_M = 0.05
BORDER_M = 0.2


@pytest.fixture(scope="module")
def out(tmp_path_factory) -> Path:
    """`cli synth`'s output: 2 logs (1 train, 1 val) of 3 frames with sensors, and its openlanev2/."""
    root = tmp_path_factory.mktemp("synth_olv2")
    synth(root, logs=2, frames_per_log=3, seed=SEED, val_frames_per_log=3)
    return root


def av2_logs(out: Path) -> list[Path]:
    return sorted((out / "av2" / "sensor").glob("*/*"))


def frame_files(root: Path) -> list[Path]:
    return sorted(root.glob("*/*/info/*.json"))


def annotated(frame: dict) -> AnnotatedLanes:
    lanes = frame["annotation"]["lane_centerline"]
    links = np.array(frame["annotation"]["topology_lclc"], np.float64).reshape(len(lanes), len(lanes))
    points = [np.array(lane["points"]) for lane in lanes]
    return AnnotatedLanes(points, links, [str(lane["id"]) for lane in lanes])


def test_synth_writes_one_frame_file_per_av2_frame_in_the_split_of_its_log(out):
    from pipeline.adapters.av2 import frame_timestamps

    logs = av2_logs(out)
    expected = {
        (log.parent.name, log.name, f"{t}.json") for log in logs for t in frame_timestamps(log).tolist()
    }
    written = {(p.parents[2].name, p.parents[1].name, p.name) for p in frame_files(out / "openlanev2")}
    assert written == expected and len(written) == 6
    assert {split for split, _, _ in written} == {"train", "val"}
    assert json.loads((out / "synth.json").read_text())["openlanev2_root"] == "openlanev2"


def test_frame_files_hold_the_format_with_the_av2_pose_and_calibration(out):
    from av2.geometry.camera.pinhole_camera import PinholeCamera
    from av2.utils.io import read_city_SE3_ego

    root = out / "openlanev2"
    for path in frame_files(root):
        split, log_id, t = path.parents[2].name, path.parents[1].name, int(path.stem)
        log = out / "av2" / "sensor" / split / log_id
        frame = json.loads(path.read_text())
        keys = ["version", "segment_id", "meta_data", "timestamp", "sensor", "pose", "annotation"]
        assert list(frame) == keys
        assert frame["segment_id"] == log_id and frame["timestamp"] == path.stem
        assert frame["meta_data"] == {"source": "av2", "source_id": log_id}
        pose = read_city_SE3_ego(log)[t]  # synth's frames sit on pose times
        np.testing.assert_array_equal(frame["pose"]["rotation"], pose.rotation)
        np.testing.assert_array_equal(frame["pose"]["translation"], pose.translation)
        assert set(frame["sensor"]) == RING
        for name, camera in frame["sensor"].items():
            reference = PinholeCamera.from_feather(log, name)
            np.testing.assert_array_equal(camera["intrinsic"]["K"], reference.intrinsics.K)
            assert camera["intrinsic"]["distortion"] == [0.0, 0.0, 0.0]  # synth's pinhole cameras
            extrinsic = reference.ego_SE3_cam
            np.testing.assert_array_equal(camera["extrinsic"]["rotation"], extrinsic.rotation)
            np.testing.assert_array_equal(camera["extrinsic"]["translation"], extrinsic.translation)
            assert camera["image_path"] == f"{split}/{log_id}/image/{name}/{t}.jpg"
            image, source = root / camera["image_path"], log / "sensors" / "cameras" / name / f"{t}.jpg"
            assert os.path.samefile(image, source)  # hard-linked, not copied


def test_lanes_lie_in_range_and_topology_has_their_shape(out):
    lanes_seen = 0
    for path in frame_files(out / "openlanev2"):
        annotation = json.loads(path.read_text())["annotation"]
        lanes = annotation["lane_centerline"]
        n = len(lanes)
        lanes_seen += n
        assert np.array(annotation["topology_lclc"]).reshape(n, -1).shape == (n, n)
        assert annotation["topology_lcte"] == [[]] * n and annotation["traffic_element"] == []
        assert len({lane["id"] for lane in lanes}) == n and all(type(lane["id"]) is int for lane in lanes)
        for lane in lanes:
            points = np.array(lane["points"])
            assert points.ndim == 2 and points.shape[1] == 3 and len(points) >= 2
            assert (np.abs(points[:, 0]) <= 50).all() and (np.abs(points[:, 1]) <= 25).all()
        assert set(np.unique(annotation["topology_lclc"])) <= {0, 1}
    assert lanes_seen > 100


def test_links_join_coinciding_points_and_every_inside_successor_is_linked(out):
    """Each link i -> j joins i's last point to j's first (the same map point, which synth rounds to the
    centimetre); and every pair of map successors whose shared point lies inside the range is one link:
    counted on the av2 API's map in the av2 API's ego frame (a point within 1 cm of the border either way)."""
    from av2.map.map_api import ArgoverseStaticMap
    from av2.utils.io import read_city_SE3_ego

    links = 0
    for path in frame_files(out / "openlanev2"):
        log = out / "av2" / "sensor" / path.parents[2].name / path.parents[1].name
        lanes = annotated(json.loads(path.read_text()))
        for i, j in zip(*np.nonzero(lanes.links)):
            assert np.abs(lanes.points[i][-1] - lanes.points[j][0]).max() < 0.01
        links += int(lanes.links.sum())
        static_map = ArgoverseStaticMap.from_map_dir(log / "map", build_raster=False)
        city_to_ego = read_city_SE3_ego(log)[int(path.stem)].inverse()
        surely, maybe = 0, 0  # successor pairs inside by 1 cm, inside or within 1 cm outside
        for lane_id, segment in static_map.vector_lane_segments.items():
            centerline = static_map.get_lane_segment_centerline(lane_id)
            x, y, _ = city_to_ego.transform_point_cloud(centerline[-1:])[0]
            pairs = sum(s in static_map.vector_lane_segments for s in segment.successors)
            surely += pairs * (abs(x) < 49.99 and abs(y) < 24.99)
            maybe += pairs * (abs(x) < 50.01 and abs(y) < 25.01)
        ends = [p[-1] for p in lanes.points]
        starts = [p[0] for p in lanes.points]
        joined = sum(np.abs(ends[i] - starts[j]).max() < 0.01 for i, j in zip(*np.nonzero(lanes.links)))
        assert joined == lanes.links.sum() and surely <= joined <= maybe, path
    assert links > 50


def test_lanes_are_the_map_clipped_to_the_range_and_resampled(out):
    """The lanes of a frame are the map's centerlines within the range, resampled: every written point lies on
    shapely's clip of the av2 API's centerlines moved by the av2 API's inverse pose, every vertex of that clip
    lies within CORNER_CUT_M of the lanes (corners that 201 points cut), their length the clip's to 1e-4."""
    import shapely
    from av2.map.map_api import ArgoverseStaticMap
    from av2.utils.io import read_city_SE3_ego
    from shapely.geometry import LineString, MultiLineString, box

    for path in frame_files(out / "openlanev2"):
        log = out / "av2" / "sensor" / path.parents[2].name / path.parents[1].name
        static_map = ArgoverseStaticMap.from_map_dir(log / "map", build_raster=False)
        city_to_ego = read_city_SE3_ego(log)[int(path.stem)].inverse()
        area = box(-50, -25, 50, 25)
        clipped = shapely.union_all([
            LineString(city_to_ego.transform_point_cloud(static_map.get_lane_segment_centerline(i))[:, :2])
            .intersection(area)
            for i in static_map.vector_lane_segments
        ])  # fmt: skip
        lanes = annotated(json.loads(path.read_text()))
        written = MultiLineString([p[:, :2] for p in lanes.points])
        points = shapely.points(np.concatenate(lanes.points)[:, :2])
        assert shapely.distance(points, clipped).max() < 1e-9
        assert 0 < clipped.hausdorff_distance(written) < CORNER_CUT_M
        assert written.length == pytest.approx(clipped.length, rel=1e-4)


def test_written_lanes_have_201_points_evenly_along(out):
    """OpenLane-V2's annotations: 201 points a lane, even in arc length (ground plane): every step the
    spacing except the chords that cut a corner of the map's polyline (shorter)."""
    lanes_seen = 0
    for path in frame_files(out / "openlanev2"):
        lanes = annotated(json.loads(path.read_text()))
        for points in lanes.points:
            assert points.shape == (201, 3)
            steps = np.hypot(*np.diff(points[:, :2], axis=0).T)
            even = np.isclose(steps, steps.max(), rtol=1e-6, atol=0)
            assert even.mean() > 0.9 and steps.min() > 0
        lanes_seen += len(lanes)
    assert lanes_seen > 100


def graph_matches(ours, av2, rng) -> None:
    """graph_of_annotated's graph of resampled lanes against crop_lane_graph's of the map, both cropped to
    rng: the same junctions (vertices of in- or out-degree >= 2, the lanes' shared end points, at the same
    float32 positions) and each graph's vertices within CORNER_CUT_M of the other's edges, those within
    BORDER_M of the range's edge aside (a lane along the edge may fall either side once its corners move)."""
    import shapely

    def junctions(graph) -> set:
        n = len(graph.x)
        fork = (np.bincount(graph.src, minlength=n) >= 2) | (np.bincount(graph.dst, minlength=n) >= 2)
        return {(graph.x[v], graph.y[v]) for v in np.flatnonzero(fork)}

    def edges(graph):
        ends = np.stack([graph.x, graph.y], axis=1).astype(np.float64)
        return shapely.multilinestrings(np.stack([ends[graph.src], ends[graph.dst]], axis=1))

    assert junctions(ours) == junctions(av2) and len(junctions(av2)) > 0
    for a, b in ((ours, av2), (av2, ours)):
        inside = (a.x > rng.x_min + BORDER_M) & (a.x < rng.x_max - BORDER_M)
        inside &= (a.y > rng.y_min + BORDER_M) & (a.y < rng.y_max - BORDER_M)
        vertices = shapely.points(np.stack([a.x, a.y], axis=1)[inside].astype(np.float64))
        assert shapely.distance(vertices, edges(b)).max() < CORNER_CUT_M


def test_graph_of_the_written_lanes_is_the_av2_crop(out):
    """graph_of_annotated of each written frame at 30 x 60 m is the graph that prepare crops from the AV2 log,
    its lanes resampled: the same junctions, the same lanes within CORNER_CUT_M (graph_matches)."""
    from pipeline.adapters.av2 import frame_poses, frame_timestamps, read_lanes
    from pipeline.geometry import Range
    from pipeline.targets import rigid_inverse

    rng = Range.parse("30x60")
    for log in av2_logs(out):
        lane_map = LaneMap.from_lanes(read_lanes(log)[0])
        timestamps = frame_timestamps(log)
        for t, pose in zip(timestamps.tolist(), frame_poses(log, timestamps)):
            path = out / "openlanev2" / log.parent.name / log.name / "info" / f"{t}.json"
            ours = graph_of_annotated(annotated(json.loads(path.read_text())), rng)
            av2 = crop_lane_graph(lane_map, rigid_inverse(pose), rng)
            assert len(av2.src) > 10
            graph_matches(ours, av2, rng)


def test_same_log_same_bytes_and_a_rewrite_removes_stale_frames(out, tmp_path):
    log = av2_logs(out)[0]
    for root in (tmp_path / "a", tmp_path / "b"):
        written = write_from_av2(log, root, "train")
        assert (written.frames, written.images_linked, written.images_absent) == (3, 21, 0)
    files = [p.relative_to(tmp_path / "a") for p in sorted((tmp_path / "a").rglob("*")) if p.is_file()]
    assert len(files) == 3 + 21
    for name in files:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
        if name.suffix == ".json":
            assert (tmp_path / "a" / name).read_bytes() == (out / "openlanev2" / name).read_bytes()
    written = write_from_av2(log, tmp_path / "a", "train", frame_stride=2)
    assert written.frames == 2 and len(frame_files(tmp_path / "a")) == 2
    assert len(list((tmp_path / "a").rglob("*.jpg"))) == 14


def test_a_log_without_sensors_names_absent_images_or_no_cameras(tmp_path):
    """Without calibration (synth --no-sensors) a frame has no cameras; its lanes are still written."""
    synth(tmp_path / "raw", logs=1, frames_per_log=2, seed=SEED, sensors=False)
    (frame,) = [json.loads(p.read_text()) for p in frame_files(tmp_path / "raw" / "openlanev2")][:1]
    assert frame["sensor"] == {} and frame["annotation"]["lane_centerline"]


def test_bad_input_is_refused_in_one_line_before_anything_is_written(out, tmp_path):
    log = av2_logs(out)[0]
    with pytest.raises(ValueError, match="split 'a/b' must be a plain folder name"):
        write_from_av2(log, tmp_path / "root", "a/b")
    with pytest.raises(ValueError, match="frame_stride must be at least 1"):
        write_from_av2(log, tmp_path / "root", "train", frame_stride=0)
    with pytest.raises(DataError, match="no map/"):
        write_from_av2(tmp_path, tmp_path / "root", "train")
    assert not (tmp_path / "root").exists()


def test_clipped_lanes_hand_computed():
    """One map in the BEV frame (pose the identity): lane a runs forward from y = -60 (z 0) through y = 0
    (z 6) to y = 40 (z 10), its successor b on to y = 80 (z 14); lane c leaves the range sideways and comes
    back; lane d lies outside. OpenLane-V2's range is y (forward) in [-50, 50], x in [-25, 25]."""
    lanes = [
        Lane("a", np.array([[0.0, -60, 0], [0, 0, 6], [0, 40, 10]]), ["b"]),
        Lane("b", np.array([[0.0, 40, 10], [0, 80, 14]]), []),
        Lane("c", np.array([[-20.0, 0, 0], [30, 0, 0], [30, 10, 0], [-20, 10, 0]]), []),
        Lane("d", np.array([[40.0, 0, 0], [40, 10, 0]]), []),
    ]
    ids: dict = {}
    got = frame_lanes(LaneMap.from_lanes(lanes), np.eye(4), ids)
    # ego frame x forward = BEV y, y left = -BEV x; the clip at y = -50 lies 1/6 of the way to z 6: z 1;
    # the clip at y = 50 a quarter of the way from z 10 to z 14: z 11; each piece 201 points evenly along,
    # and along a and b z = 6 + x / 10 (both slopes are 1 in 10)
    x = np.linspace(-50, 40, 201), np.linspace(40, 50, 201)
    across = np.linspace(20, -25, 201)
    expected = [
        np.column_stack([x[0], np.zeros(201), 6 + x[0] / 10]),
        np.column_stack([x[1], np.zeros(201), 6 + x[1] / 10]),
        np.column_stack([np.zeros(201), across, np.zeros(201)]),
        np.column_stack([np.full(201, 10.0), across[::-1], np.zeros(201)]),
    ]
    assert len(got) == 4
    for points, want in zip(got.points, expected, strict=True):
        np.testing.assert_allclose(points, want, atol=1e-12)
    np.testing.assert_array_equal(got.points[0][-1], [40, 0, 10])  # the shared point, exactly
    np.testing.assert_array_equal(got.points[1][0], got.points[0][-1])
    np.testing.assert_array_equal(got.links, [[0, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]])
    assert got.ids == ["0", "1", "2", "3"]
    # a later frame keeps the ids of the pieces it shares: lane b alone in range is still lane 1
    later = frame_lanes(LaneMap.from_lanes(lanes), np.array([[1.0, 0, 0, 0], [0, 1, 0, -100], [0, 0, 1, 0],
                                                             [0, 0, 0, 1]]), ids)  # fmt: skip
    assert later.ids == ["1"] and later.links.shape == (1, 1)


def test_resampled_lane_cuts_a_corner_by_its_spacing_hand_computed():
    """An L of legs 10 m (z 0 -> 1) and 5 m (z 1 -> 1): 201 points 0.075 m apart along it; point 133 lies
    9.975 m up the first leg, point 134 0.05 m along the second, so the corner (10, 0) is cut; ends kept."""
    from pipeline.synth.openlanev2_writer import resampled_lane

    got = resampled_lane(np.array([[0.0, 0, 0], [10, 0, 1], [10, 5, 1]]), 201)
    k = np.arange(201)
    s = 0.075 * k
    expected = np.where((s <= 10)[:, None], np.column_stack([s, 0 * s, s / 10]),
                        np.column_stack([np.full(201, 10.0), s - 10, np.ones(201)]))  # fmt: skip
    np.testing.assert_allclose(got, expected, atol=1e-12)
    np.testing.assert_allclose(got[133], [9.975, 0, 0.9975], atol=1e-12)
    np.testing.assert_allclose(got[134], [10, 0.05, 1], atol=1e-12)
    np.testing.assert_array_equal(got[[0, -1]], [[0, 0, 0], [10, 5, 1]])
