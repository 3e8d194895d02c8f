"""`prepare` on the real AV2 logs of ../shared/data, checked against independent computations."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.feather as feather
import shapely
from av2.map.map_api import ArgoverseStaticMap
from av2.utils.io import read_city_SE3_ego

from pipeline.io import decode_raster, read_table


def table_rows(out, name):
    return read_table(out, name).to_pylist()


def test_every_frame_prepares(prepared_av2, av2_root):
    frames = read_table(prepared_av2, "frames")
    expected = 0
    for log_dir in sorted(av2_root.glob("*/*")):
        path = next(log_dir.glob("annotations*.feather"))
        expected += len(np.unique(feather.read_table(path)["timestamp_ns"].to_numpy()))
    assert frames.num_rows == expected == 313
    assert sorted(set(frames["split"].to_pylist())) == ["train", "val"]
    manifest = json.loads((prepared_av2 / "manifest.json").read_text())
    assert manifest["rows"]["frames"] == 313
    assert manifest["rows"]["graphs"] == 313
    for table in ("graphs", "rasters"):
        assert read_table(prepared_av2, table)["frame_id"].to_pylist() == frames["frame_id"].to_pylist()


def test_vertices_inside_range(prepared_av2):
    for row in table_rows(prepared_av2, "graphs"):
        x, y = np.array(row["x"]), np.array(row["y"])
        assert len(x) > 0
        assert (x >= -15).all() and (x <= 15).all() and (y >= -30).all() and (y <= 30).all()
        assert len(row["src"]) == len(row["dst"]) > 0
        assert not np.any(np.array(row["src"]) == np.array(row["dst"]))


def test_paths_cover_every_edge_exactly(prepared_av2):
    graphs = {r["frame_id"]: r for r in table_rows(prepared_av2, "graphs")}
    path_edges = {f: set() for f in graphs}
    for row in table_rows(prepared_av2, "paths"):
        ids = row["vertex_ids"]
        assert len(set(ids)) == len(ids), "a path revisits a vertex"
        path_edges[row["frame_id"]].update(zip(ids[:-1], ids[1:]))
        g = graphs[row["frame_id"]]
        np.testing.assert_array_equal(np.array(g["x"], np.float32)[ids], np.array(row["x"], np.float32))
        assert len(row["rx"]) == 30
        assert (row["rx"][0], row["ry"][0]) == (row["x"][0], row["y"][0])
        assert (row["rx"][-1], row["ry"][-1]) == (row["x"][-1], row["y"][-1])
    for frame_id, g in graphs.items():
        assert path_edges[frame_id] == set(zip(g["src"], g["dst"])), frame_id


def test_pieces_and_links_rebuild_the_graph(prepared_av2):
    graphs = {r["frame_id"]: r for r in table_rows(prepared_av2, "graphs")}
    pieces: dict[str, list] = {f: [] for f in graphs}
    for row in table_rows(prepared_av2, "pieces"):
        pieces[row["frame_id"]].append(row)
    links: dict[str, set] = {f: set() for f in graphs}
    for row in table_rows(prepared_av2, "piece_links"):
        links[row["frame_id"]].add((row["src_piece"], row["dst_piece"]))
    for frame_id, g in graphs.items():
        # rebuild from coordinates alone: each piece is a chain; a link glues an end to a start
        rebuilt_edges = set()
        for p in pieces[frame_id]:
            pts = list(zip(p["x"], p["y"]))
            rebuilt_edges.update(zip(pts[:-1], pts[1:]))
        gx, gy = g["x"], g["y"]
        truth = {((gx[s], gy[s]), (gx[d], gy[d])) for s, d in zip(g["src"], g["dst"])}
        assert rebuilt_edges == truth, frame_id
        ends = [(p["x"][-1], p["y"][-1]) for p in pieces[frame_id]]
        starts = [(p["x"][0], p["y"][0]) for p in pieces[frame_id]]
        expected = {(i, j) for i, e in enumerate(ends) for j, s in enumerate(starts) if e == s}
        assert links[frame_id] == expected, frame_id
        # interior vertices of a piece are never junctions
        n = len(gx)
        indeg = np.bincount(g["dst"], minlength=n)
        outdeg = np.bincount(g["src"], minlength=n)
        for p in pieces[frame_id]:
            inner = p["vertex_ids"][1:-1]
            assert (indeg[inner] == 1).all() and (outdeg[inner] == 1).all()


def test_centerline_length_matches_shapely(prepared_av2, av2_root):
    """Total edge length per frame == map centerlines clipped by shapely, within 1%."""
    frames = read_table(prepared_av2, "frames").to_pylist()
    graphs = {r["frame_id"]: r for r in table_rows(prepared_av2, "graphs")}
    box = shapely.box(-15, -30, 15, 30)
    for log_dir in sorted(av2_root.glob("*/*")):
        static_map = ArgoverseStaticMap.from_map_dir(log_dir / "map")
        centerlines = [static_map.get_lane_segment_centerline(i) for i in static_map.vector_lane_segments]
        poses = read_city_SE3_ego(log_dir)
        pose_times = np.array(sorted(poses))
        for frame in (f for f in frames if f["log_id"] == log_dir.name):
            t = pose_times[np.argmin(np.abs(pose_times - frame["timestamp_ns"]))]
            ego_from_city = poses[t].inverse()
            lines = []
            for c in centerlines:
                ego = ego_from_city.transform_point_cloud(c)
                # to the BEV axes: x right, y forward
                lines.append(shapely.LineString(np.stack([-ego[:, 1], ego[:, 0]], 1)))
            expected = shapely.length(shapely.intersection(np.array(lines), box)).sum()
            g = graphs[frame["frame_id"]]
            x, y = np.array(g["x"], np.float64), np.array(g["y"], np.float64)
            s, d = np.array(g["src"]), np.array(g["dst"])
            measured = np.hypot(x[d] - x[s], y[d] - y[s]).sum()
            assert abs(measured - expected) <= 0.01 * expected, (frame["frame_id"], measured, expected)


def test_rasters_draw_the_graph(prepared_av2):
    row = read_table(prepared_av2, "rasters").slice(0, 1).to_pylist()[0]
    mask, direction = decode_raster(row)
    assert mask.shape == direction.shape == (400, 200)
    assert set(np.unique(mask)) == {0, 1}
    assert ((direction > 0) == (mask > 0)).all()
    assert direction.max() <= 36
    g = read_table(prepared_av2, "graphs").slice(0, 1).to_pylist()[0]
    # every vertex falls on a drawn pixel
    cols = np.floor((np.array(g["x"]) + 15) / 0.15).clip(0, 199).astype(int)
    rows = np.floor((30 - np.array(g["y"])) / 0.15).clip(0, 399).astype(int)
    assert mask[rows, cols].all()


def test_frames_table_poses_are_bev(prepared_av2, av2_root):
    """The stored pose maps the BEV frame to the city: BEV +y (forward) is the egovehicle's +x."""
    from scipy.spatial.transform import Rotation

    row = read_table(prepared_av2, "frames").slice(0, 1).to_pylist()[0]
    log_dir = next(av2_root.glob(f"*/{row['log_id']}"))
    poses = read_city_SE3_ego(log_dir)
    t = min(poses, key=lambda k: abs(k - row["timestamp_ns"]))
    w, x, y, z = row["pose_rotation"]
    R = Rotation.from_quat([x, y, z, w]).as_matrix()
    np.testing.assert_allclose(R[:, 1], poses[t].rotation[:, 0], atol=1e-9)
    np.testing.assert_allclose(R[:, 0], -poses[t].rotation[:, 1], atol=1e-9)
    np.testing.assert_allclose(row["pose_translation"], poses[t].translation, atol=1e-9)
    assert row["cameras"] == [] and row["lidar_path"] == ""


def test_ground_height_is_the_road_under_the_rear_axle(prepared_av2):
    """AV2's egovehicle origin is the centre of the rear axle: the map's road surface lies about a
    wheel radius below it (measured: -0.39 to -0.29 m on the two logs)."""
    ground = read_table(prepared_av2, "frames", columns=["ground_z"])["ground_z"].to_numpy()
    assert len(ground) == 313 and -0.45 < ground.min() and ground.max() < -0.25
