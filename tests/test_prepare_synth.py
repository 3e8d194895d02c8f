"""`prepare` on the synthetic world, read through both real formats: the hard cases, and the two
formats agreeing with each other."""

from __future__ import annotations

import math

import networkx as nx
import numpy as np
import shapely

from pipeline.adapters import av2 as av2_adapter
from pipeline.geometry import Range, clip_polylines
from pipeline.io import read_table
from pipeline.lane_graph import LaneMap, crop_lane_graph
from pipeline.pieces import graph_to_pieces
from pipeline.synth.world import build_world

LIDAR_FORWARD_M = 0.943  # the synthetic nuScenes rig: LIDAR_TOP sits this far ahead of the ego origin


def rows_by_frame(out, table):
    rows: dict[str, list] = {}
    for row in read_table(out, table).to_pylist():
        rows.setdefault(row["frame_id"], []).append(row)
    return rows


def to_networkx(g) -> nx.DiGraph:
    graph = nx.DiGraph()
    graph.add_nodes_from(range(len(g["x"])))
    graph.add_edges_from(zip(g["src"], g["dst"]))
    return graph


def bev_of(frame) -> tuple[np.ndarray, np.ndarray]:
    """(rotation, translation) of a frames-table row: BEV frame -> world."""
    from scipy.spatial.transform import Rotation

    w, x, y, z = frame["pose_rotation"]
    return Rotation.from_quat([x, y, z, w]).as_matrix(), np.array(frame["pose_translation"])


def world_to_bev(frame, xy: np.ndarray) -> np.ndarray:
    R, t = bev_of(frame)
    p = np.column_stack([xy, np.zeros(len(xy))]) - t
    return (p @ R)[:, :2]


def test_both_formats_prepare_every_frame(synth_prepared):
    for out in synth_prepared.values():
        frames = read_table(out, "frames")
        assert frames.num_rows == 80
        assert sorted(set(frames["split"].to_pylist())) in (["train", "val"], ["mini_train", "mini_val"])


def test_paths_cover_every_edge_in_every_frame(synth_prepared):
    for out in synth_prepared.values():
        paths = rows_by_frame(out, "paths")
        for g in read_table(out, "graphs").to_pylist():
            covered = {
                e
                for p in paths.get(g["frame_id"], [])
                for e in zip(p["vertex_ids"][:-1], p["vertex_ids"][1:])
            }
            assert covered == set(zip(g["src"], g["dst"])), g["frame_id"]


def test_roundabout_cycle_keeps_all_its_edges(synth_prepared):
    world = build_world(0)
    centre = np.array(world.landmarks.roundabout_centre)
    out = synth_prepared["av2"]
    frames = {f["frame_id"]: f for f in read_table(out, "frames").to_pylist()}
    paths = rows_by_frame(out, "paths")
    seen_whole_ring = 0
    for g in read_table(out, "graphs").to_pylist():
        centre_bev = world_to_bev(frames[g["frame_id"]], centre[None])[0]
        r = world.landmarks.roundabout_radius
        if not (abs(centre_bev[0]) + r < 15 and abs(centre_bev[1]) + r < 30):
            continue
        seen_whole_ring += 1
        cycles = list(nx.simple_cycles(to_networkx(g)))
        assert len(cycles) == 1, g["frame_id"]
        ring = cycles[0]
        ring_edges = set(zip(ring, ring[1:] + ring[:1]))
        xy = np.stack([g["x"], g["y"]], 1)[ring]
        np.testing.assert_allclose(np.hypot(*(xy - centre_bev).T), r, atol=0.05)
        covered = {e for p in paths[g["frame_id"]] for e in zip(p["vertex_ids"][:-1], p["vertex_ids"][1:])}
        assert ring_edges <= covered
    assert seen_whole_ring >= 5


def synthetic_log(synth_raw, route: str):
    import json

    meta = json.loads((synth_raw / "synth.json").read_text())
    log = next(entry for entry in meta["logs"] if entry["route"] == route)
    root = synth_raw / "av2" / "sensor"
    return av2_adapter.load_log(root, log["split"], root / log["split"] / log["log_id"])


def bev_pose(x: float, y: float, heading: float) -> np.ndarray:
    """BEV-frame-to-world transform of an ego at (x, y) heading `heading` (BEV +y is the heading)."""
    yaw = heading - math.pi / 2
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T[:2, 3] = x, y
    return T


def test_fork_has_out_degree_two(synth_raw):
    world = build_world(0)
    log = synthetic_log(synth_raw, "fork")
    lane_map = LaneMap.from_lanes(log.lanes)
    fork_point = world.lanes[world.landmarks.fork_lane].path.end.xy
    checked = 0
    for frame in log.frames:
        graph = crop_lane_graph(lane_map, np.linalg.inv(frame.ego_to_world), Range())
        p = (np.linalg.inv(frame.ego_to_world) @ [*fork_point, 0, 1])[:2]
        if abs(p[0]) > 14 or abs(p[1]) > 29:
            continue
        checked += 1
        v = int(np.argmin(np.hypot(graph.x - p[0], graph.y - p[1])))
        assert np.hypot(graph.x[v] - p[0], graph.y[v] - p[1]) < 0.01
        assert (graph.src == v).sum() == 2 and (graph.dst == v).sum() == 1
    assert checked >= 5


def test_lane_that_reenters_gives_two_pieces(synth_raw):
    world = build_world(0)
    log = synthetic_log(synth_raw, "s_bend")  # its local map holds the S-bend
    lane_map = LaneMap.from_lanes(log.lanes)
    view = world.landmarks.reentering_view
    pose = bev_pose(view.x, view.y, view.heading)
    lane = world.landmarks.reentering_lane
    index = lane_map.ids.index(str(lane))
    centerline = lane_map.points[lane_map.offsets[index] : lane_map.offsets[index + 1]]
    bev = (np.linalg.inv(pose) @ np.column_stack([centerline[:, :3], np.ones(len(centerline))]).T).T[:, :2]
    assert bev[:, 0].max() > 15 and bev[0, 0] < 15 and bev[-1, 0] < 15  # leaves on the right, comes back
    _, offsets, *_ = clip_polylines(
        np.ascontiguousarray(bev), np.array([0, len(bev)]), -15.0, 15.0, -30.0, 30.0
    )
    assert len(offsets) - 1 == 2
    graph = crop_lane_graph(lane_map, np.linalg.inv(pose), Range())
    pieces = graph_to_pieces(graph)
    # the exit and re-entry points on the right border: a leaf and a root, on two different pieces
    on_border = np.flatnonzero(np.isclose(graph.x, 15.0))
    assert len(on_border) == 2
    leaf, root = sorted(on_border, key=lambda v: (graph.src == v).sum())  # the side lane drives either way
    assert (graph.dst == leaf).sum() == 1 and (graph.src == leaf).sum() == 0
    assert (graph.src == root).sum() == 1 and (graph.dst == root).sum() == 0
    piece_of = {int(c[-1]): i for i, c in enumerate(pieces.chains)} | {
        int(c[0]): i for i, c in enumerate(pieces.chains)
    }
    assert piece_of[int(leaf)] != piece_of[int(root)]


def test_av2_and_nuscenes_give_the_same_graphs(synth_prepared):
    """Same world, same poses: in world coordinates the two graphs are the same lines, away from
    the crop border (the two BEV origins differ by the lidar's 0.943 m forward offset)."""
    graphs = {k: {g["frame_id"].split("/")[-1]: g for g in read_table(out, "graphs").to_pylist()}
              for k, out in synth_prepared.items()}  # fmt: skip
    frames = {k: {f["frame_id"].split("/")[-1]: f for f in read_table(out, "frames").to_pylist()}
              for k, out in synth_prepared.items()}  # fmt: skip
    assert graphs["av2"].keys() == graphs["nuscenes"].keys()
    for t in graphs["av2"]:
        world_lines = {}
        for k in ("av2", "nuscenes"):
            g, f = graphs[k][t], frames[k][t]
            R, trans = bev_of(f)
            xy = np.stack([g["x"], g["y"]], 1).astype(np.float64)
            world = (np.column_stack([xy, np.zeros(len(xy))]) @ R.T + trans)[:, :2]
            segments = np.stack([world[g["src"]], world[g["dst"]]], 1)
            world_lines[k] = (world, shapely.multilinestrings(list(segments)) if len(segments) else None)
        # nuScenes BEV origin = AV2 origin + 0.943 m forward; both R agree
        np.testing.assert_allclose(
            frames["nuscenes"][t]["pose_translation"][:2],
            np.array(frames["av2"][t]["pose_translation"][:2])
            + bev_of(frames["av2"][t])[0][:2, 1] * LIDAR_FORWARD_M,
            atol=1e-6,
        )
        for a, b in (("av2", "nuscenes"), ("nuscenes", "av2")):
            points, _ = world_lines[a]
            _, other = world_lines[b]
            # keep the points well inside both crops
            inner = np.ones(len(points), bool)
            for k in ("av2", "nuscenes"):
                local = world_to_bev(frames[k][t], points)
                inner &= (np.abs(local[:, 0]) < 14) & (np.abs(local[:, 1]) < 28.5)
            if inner.any():
                distance = shapely.distance(shapely.points(points[inner]), other)
                # AV2 centerlines are 10 points per segment: on long turns across a 5-arm junction their
                # chords stray up to ~10 cm from the nuScenes arcs (discretised at 0.5 m)
                assert distance.max() < 0.15, (t, a, distance.max())
                assert np.median(distance) < 0.03


def test_no_two_vertices_share_a_point(synth_prepared):
    """Exactly overlapping lanes (nuScenes fork branches leaving along one arc) share vertices."""
    for out in synth_prepared.values():
        for g in read_table(out, "graphs").to_pylist():
            xy = np.stack([g["x"], g["y"]], 1)
            assert len(np.unique(xy, axis=0)) == len(xy), g["frame_id"]
