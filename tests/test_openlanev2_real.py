"""The real AV2 logs of ../shared/data written in OpenLane-V2's layout: their lanes against the av2 API's map,
and the frames prepared as OpenLane-V2 against the same frames prepared as AV2 (issue 61's equality)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.records import AnnotatedLanes
from pipeline.synth.openlanev2_writer import write_from_av2

# every STRIDE-th frame (0.8 s apart) of each log: each frame's 201-point lanes make its files and graphs
# large, and the test's time follows the frames
STRIDE = 8
LOGS = {
    "adcf7d18-0510-35b0-a2fa-b4cea13a6d76": ("train", 20),  # of 156
    "3b3570b4-7b0b-3268-a571-b0889dbf40b6": ("val", 20),  # of 157
}
FRAMES = sum(frames for _, frames in LOGS.values())


@pytest.fixture(scope="module")
def olv2_root(av2_root, tmp_path_factory) -> Path:
    """Both real logs written as OpenLane-V2, each in its AV2 split."""
    root = tmp_path_factory.mktemp("openlanev2_real")
    for log_id, (split, frames) in LOGS.items():
        written = write_from_av2(av2_root / split / log_id, root, split, frame_stride=STRIDE)
        assert (written.frames, written.images_linked, written.images_absent) == (frames, 0, 0)
    return root


def annotated(path: Path) -> AnnotatedLanes:
    lanes = json.loads(path.read_text())["annotation"]["lane_centerline"]
    links = json.loads(path.read_text())["annotation"]["topology_lclc"]
    links = np.array(links, np.float64).reshape(len(lanes), len(lanes))
    return AnnotatedLanes(
        [np.array(lane["points"]) for lane in lanes], links, [str(lane["id"]) for lane in lanes]
    )


def test_real_lanes_are_the_map_in_the_ego_frame_resampled_with_its_heights(av2_root, olv2_root):
    """Every written lane has 201 points on one of the map's centerlines (the av2 API's, moved by its
    inverse pose), each with the height interpolated along that centerline; every link joins the same point
    (the predecessor's last is the successor's first, to the bit)."""
    import shapely
    from av2.map.map_api import ArgoverseStaticMap
    from av2.utils.io import read_city_SE3_ego

    from pipeline.adapters.av2 import nearest

    for log_id, (split, _) in LOGS.items():
        log = av2_root / split / log_id
        static_map = ArgoverseStaticMap.from_map_dir(log / "map", build_raster=False)
        centerlines = [
            static_map.get_lane_segment_centerline(i) for i in sorted(static_map.vector_lane_segments)
        ]
        poses = read_city_SE3_ego(log)
        times = np.array(sorted(poses))
        files = sorted((olv2_root / split / log_id / "info").glob("*.json"))
        for path in files[:: len(files) // 3]:
            city_to_ego = poses[times[nearest(times, int(path.stem))]].inverse()
            moved = [city_to_ego.transform_point_cloud(c) for c in centerlines]
            lines = shapely.linestrings([c[:, :2] for c in moved])
            lanes = annotated(path)
            for points in lanes.points:
                assert points.shape == (201, 3)
                assert (np.abs(points[:, 0]) <= 50).all() and (np.abs(points[:, 1]) <= 25).all()
                # the centerline that holds every point of the lane
                gap = shapely.distance(shapely.points(points[:, :2])[:, None], lines[None, :]).max(axis=0)
                line = moved[int(gap.argmin())]
                assert gap.min() < 1e-9
                along = shapely.line_locate_point(
                    shapely.linestrings(line[:, :2]), shapely.points(points[:, :2])
                )
                vertices_along = np.concatenate([[0], np.cumsum(np.hypot(*np.diff(line[:, :2], axis=0).T))])
                np.testing.assert_allclose(
                    points[:, 2], np.interp(along, vertices_along, line[:, 2]), atol=1e-9
                )
            heights = np.concatenate(lanes.points)[:, 2]
            assert heights.max() - heights.min() > 0.3  # real heights, not a flat plane
            for i, j in zip(*np.nonzero(lanes.links)):
                np.testing.assert_array_equal(lanes.points[i][-1], lanes.points[j][0])


@pytest.mark.parametrize("bev_range", ["30x60", "50x100"])
def test_real_lanes_give_the_graph_that_prepare_crops_from_av2(av2_root, olv2_root, bev_range):
    """graph_of_annotated of each written frame, cropped to the range, is crop_lane_graph's graph of the AV2
    log at that frame with its lanes resampled: the same junctions at the same float32 positions, each
    graph's vertices within 5 cm of the other's edges away from the range's edge (graph_matches)."""
    from test_openlanev2_writer import graph_matches

    from pipeline.adapters.av2 import frame_poses, frame_timestamps, read_lanes
    from pipeline.geometry import Range
    from pipeline.lane_graph import LaneMap, crop_lane_graph, graph_of_annotated
    from pipeline.targets import rigid_inverse

    rng = Range.parse(bev_range)
    for log_id, (split, frames) in LOGS.items():
        log = av2_root / split / log_id
        lane_map = LaneMap.from_lanes(read_lanes(log)[0])
        timestamps = frame_timestamps(log)[::STRIDE]
        assert len(timestamps) == frames
        for t, pose in zip(timestamps.tolist(), frame_poses(log, timestamps)):
            ours = graph_of_annotated(annotated(olv2_root / split / log_id / "info" / f"{t}.json"), rng)
            av2 = crop_lane_graph(lane_map, rigid_inverse(pose), rng)
            assert len(av2.src) > 10
            graph_matches(ours, av2, rng)


@pytest.fixture(scope="module", params=["30x60", "50x100"])
def prepared_both(request, av2_root, olv2_root, tmp_path_factory) -> tuple[str, Path, Path]:
    """(range, the real logs prepared as AV2, the same logs written as OpenLane-V2 and prepared), both by
    `cli prepare` at that --range."""
    from typer.testing import CliRunner

    from cli import app

    bev_range = request.param
    out = tmp_path_factory.mktemp(f"prepared_{bev_range}")
    for dataset, root in (("av2", av2_root), ("openlanev2", olv2_root)):
        args = ["prepare", "--dataset", dataset, "--root", str(root), "--out", str(out / dataset)]
        stride = ["--frame-stride", str(STRIDE)] if dataset == "av2" else []
        result = CliRunner().invoke(app, [*args, "--range", bev_range, *stride])
        assert result.exit_code == 0, result.output
    return bev_range, out / "av2", out / "openlanev2"


def _graph(row: dict):
    from pipeline.lane_graph import LaneGraph

    return LaneGraph(np.array(row["x"], np.float32), np.array(row["y"], np.float32),
                     np.array(row["src"], np.int32), np.array(row["dst"], np.int32))  # fmt: skip


def test_real_logs_prepared_as_openlanev2_match_the_logs_prepared_as_av2(prepared_both, tmp_path):
    """Issue 61's comparison: every frame prepared from the OpenLane-V2 files has the AV2 frame's split and
    pose, and its graph the AV2 frame's junctions with its lanes within 5 cm (graph_matches); the project's
    metric, one against the other per log, gives mIoU at least 0.99 (the issue's bar). TOPO F1 does not reach
    0.99: it counts vertices, and resampled lanes keep the map's lines but not its vertices; the same lines
    with other vertices score below 0.99 (the next test; docs/EXPERIMENTS.md, 2026-12-06, has the figures)."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    from test_openlanev2_writer import graph_matches

    from benchmark.score import score
    from pipeline.geometry import Range
    from pipeline.io import read_table

    bev_range, av2_dir, olv2_dir = prepared_both

    def by_frame(folder: Path, table: str) -> dict[str, dict]:
        # openlanev2/<segment_id>/<timestamp> and av2/<log_id>/<timestamp> name the same frame here
        return {row["frame_id"].split("/", 1)[1]: row for row in read_table(folder, table).to_pylist()}

    frames_av2, frames_olv2 = by_frame(av2_dir, "frames"), by_frame(olv2_dir, "frames")
    assert frames_av2.keys() == frames_olv2.keys() and len(frames_av2) == FRAMES
    for key, row in frames_av2.items():
        for column in ("split", "log_id", "timestamp_ns", "pose_translation", "pose_rotation"):
            assert frames_olv2[key][column] == row[column], (key, column)
    graphs_av2, graphs_olv2 = by_frame(av2_dir, "graphs"), by_frame(olv2_dir, "graphs")
    assert graphs_av2.keys() == graphs_olv2.keys() == frames_av2.keys()
    for key, row in graphs_av2.items():
        graph_matches(_graph(graphs_olv2[key]), _graph(row), Range.parse(bev_range))
    schema = read_table(olv2_dir, "graphs").schema
    for log_id in LOGS:
        rows = [
            {**row, "frame_id": f"av2/{key}"} for key, row in graphs_olv2.items() if key.startswith(log_id)
        ]
        pred = tmp_path / f"{log_id}.parquet"
        pq.write_table(pa.Table.from_pylist(rows, schema), pred)
        result = score(pred, av2_dir)
        assert result["metric_params"]["bev_range"] == bev_range
        assert result["frames"] == result["frames_predicted"] == len(rows)
        assert result["miou"] >= 0.99, (log_id, result)


@pytest.mark.parametrize("bev_range", ["30x60", "50x100"])
def test_topo_counts_vertices_the_same_lines_with_fewer_vertices_score_below_099(av2_root, bev_range):
    """Why the comparison above cannot reach TOPO F1 0.99: the AV2 map's own graph against the same map
    with only its collinear vertices dropped (shapely's simplify at 1 um: the very same lines, mIoU 1)
    scores TOPO F1 below 0.99, since TOPO densifies each edge into ceil(length / 0.15 m) parts and matches
    vertices one to one; every 5th frame of each log."""
    import shapely

    from benchmark.metric.params import MetricParams
    from benchmark.metric.totals import Totals
    from pipeline.adapters.av2 import frame_poses, frame_timestamps, read_lanes
    from pipeline.geometry import Range
    from pipeline.lane_graph import LaneMap, crop_lane_graph
    from pipeline.records import Lane
    from pipeline.targets import rigid_inverse

    rng = Range.parse(bev_range)
    for log_id, (split, _) in LOGS.items():
        log = av2_root / split / log_id
        lanes = read_lanes(log)[0]
        thinned = []
        for lane in lanes:
            kept = shapely.simplify(shapely.LineString(lane.xyz[:, :2]), 1e-6, preserve_topology=False)
            index = [
                int(np.flatnonzero((lane.xyz[:, :2] == q).all(1))[0]) for q in shapely.get_coordinates(kept)
            ]
            thinned.append(Lane(lane.id, lane.xyz[index], lane.successors))
        assert sum(len(lane.xyz) for lane in thinned) < 0.7 * sum(len(lane.xyz) for lane in lanes)
        full, thin = LaneMap.from_lanes(lanes), LaneMap.from_lanes(thinned)
        totals = Totals(MetricParams(bev_range=bev_range))
        timestamps = frame_timestamps(log)[::5]
        for pose in frame_poses(log, timestamps):
            totals.add_frame(
                crop_lane_graph(thin, rigid_inverse(pose), rng),
                crop_lane_graph(full, rigid_inverse(pose), rng),
            )
        result = totals.result()
        assert result["miou"] > 0.9999 and result["directed"]["topo"]["precision"] > 0.99
        assert 0.9 < result["directed"]["topo"]["f1"] < 0.99, result["directed"]["topo"]


def test_real_frames_submitted_score_as_the_lane_path_scores_them(prepared_both, olv2_root, tmp_path):
    """Issue 61's submission check on the real frames: their annotated lanes as an OpenLane-V2 submission
    (write_submission; confidences 1 - k 1e-4, all distinct; links 0 / 1) scored by `cli score --metric
    openlanev2`, at either --range (the lane path neither clips nor crops), give the lane path's figures of
    the frame files as written (benchmark.metric.openlanev2 on read-back JSON):
    - every 20th point of each lane, as OpenLane-V2's evaluation keeps its GT: a perfect submission, DET_l
      and TOP_ll 1;
    - all 201 points: DET_l and TOP_ll below 1 (at 1 m): the discrete Fréchet distance of 201 points to the
      GT's 11 is up to a twentieth of the lane;
    - every 20th point moved 1.5 m left, every third link given probability 0.1 (the others 0.9): every lane
      missed at 1 m (1.5 m relaxed by at most half), DET_l and TOP_ll strictly between 0 and 1."""
    from typer.testing import CliRunner

    from benchmark.formats.openlanev2_submission import write_submission
    from benchmark.metric.openlanev2 import openlanev2_lanes_frame, openlanev2_result
    from cli import app

    _, _, data = prepared_both
    written = {}
    for path in sorted(olv2_root.glob("*/*/info/*.json")):
        written[(path.parents[2].name, path.parents[1].name, path.stem)] = annotated(path)
    assert len(written) == FRAMES

    def submission(points, links) -> dict:
        frames, k = {}, 0
        for key, lanes in written.items():
            confidence = 1.0 - (k + np.arange(len(lanes))) * 1e-4
            k += len(lanes)
            frames[key] = AnnotatedLanes([points(p) for p in lanes.points], links(lanes.links), lanes.ids,
                                         confidence)  # fmt: skip
        return frames

    def weakened(links):
        out = np.where(links > 0, 0.9, 0.0)
        i, j = np.nonzero(links)
        out[i[::3], j[::3]] = 0.1
        return out

    cases = {
        "every 20th": submission(lambda p: p[::20], lambda links: links),
        "201 points": submission(lambda p: p, lambda links: links),
        "shifted": submission(lambda p: p[::20] + [0.0, 1.5, 0.0], weakened),
    }
    got = {}
    for name, frames in cases.items():
        path = tmp_path / f"{name.replace(' ', '_')}.pkl"
        write_submission(path, name, frames)
        out = tmp_path / f"{name.replace(' ', '_')}.json"
        args = ["score", "--pred", str(path), "--gt", str(data), "--metric", "openlanev2", "--out", str(out)]
        result = CliRunner().invoke(app, args)
        assert result.exit_code == 0, result.output
        got[name] = json.loads(out.read_text())["openlanev2"]
        expected = openlanev2_result([openlanev2_lanes_frame(frames[key], written[key]) for key in written])
        lanes = sum(len(lanes) for lanes in written.values())
        assert got[name]["lanes"] == expected["lanes"] == {"pred": lanes, "gt": lanes} and lanes > 1500
        # equal but for the order of the float64 sum of TOP_ll's APs (score's frames run by frame id)
        for field in ("det_l", "top_ll", "det_l_by_threshold", "top_ll_by_threshold"):
            assert got[name][field] == pytest.approx(expected[field], rel=0, abs=1e-12), (name, field)
        assert "note" not in got[name]  # no GT lane of 20 points or fewer
    assert got["every 20th"]["det_l"] == got["every 20th"]["top_ll"] == 1.0
    assert got["201 points"]["det_l_by_threshold"]["1.0"] < 0.6 and got["201 points"]["det_l"] < 0.9
    assert got["201 points"]["det_l_by_threshold"]["3.0"] == 1.0
    assert got["shifted"]["det_l_by_threshold"]["1.0"] == got["shifted"]["top_ll_by_threshold"]["1.0"] == 0.0
    assert 0 < got["shifted"]["det_l"] < 1 and 0 < got["shifted"]["top_ll"] < 1
