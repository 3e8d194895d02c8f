"""`cli prepare --dataset openlanev2` on hand-written frame files (OpenLane-V2's data/README.md format,
built by `frame` below): frame ids, each frame's own lane graph, the annotated lanes kept unchanged, poses,
cameras and the ground, --subset, --cities (leakage, the geographic scheme), split files of OpenLane-V2
frame ids, absent images, and one line for each malformed file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from pipeline.errors import DataError
from pipeline.geometry import Range
from pipeline.io import read_annotated_lanes, read_openlanev2_keys, read_table
from pipeline.lane_graph import BEV_FROM_OPENLANEV2_EGO
from pipeline.manifest import PreparedData
from pipeline.prepare import prepare
from pipeline.targets import TargetOptions

RING = ("ring_front_center", "ring_front_left", "ring_front_right", "ring_side_left", "ring_side_right",
        "ring_rear_left", "ring_rear_right")  # fmt: skip
NUSCENES = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")
T0 = 315970276749927222  # a subset A timestamp (ns)
# an OpenCV camera (x right, y down, z forward) looking along the ego's x (forward), 1.5 m up
CAMERA_TO_EGO = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
K = [[1000.0, 0.0, 800.0], [0.0, 1000.0, 450.0], [0.0, 0.0, 1.0]]

# a fork at (10, 0) and a merge at (20, 0) (ego frame: x forward, y left), and beside them a link whose ends
# lie 2 m apart; heights vary beyond the ego's 5 m, where lane 0 (two points 15 m apart) lies at -0.3 m
LANES = [
    [[-5.0, 0.0, -0.3], [10.0, 0.0, -0.3]],
    [[10.0, 0.0, -0.3], [15.0, 3.0, -0.2], [20.0, 0.0, -0.15]],
    [[10.0, 0.0, -0.3], [15.0, -3.0, -0.2], [20.0, 0.0, -0.15]],
    [[20.0, 0.0, -0.15], [28.0, 0.0, -0.1]],
    [[0.0, -8.0, 0.1], [10.0, -8.0, 0.2]],
    [[12.0, -8.0, 0.3], [25.0, -8.0, 0.4]],
]
LINKS = np.zeros((6, 6))
LINKS[0, 1] = LINKS[0, 2] = LINKS[1, 3] = LINKS[2, 3] = LINKS[4, 5] = 1


def frame(segment: str, timestamp: int, split: str = "train", lanes=None, links=None, cameras=RING,
          translation=(100.0, 200.0, 10.0), yaw: float = 0.0, source: str = "av2",
          source_id: str = "log-a") -> dict:  # fmt: skip
    """One frame file's content as OpenLane-V2's data/README.md lays it out."""
    lanes = LANES if lanes is None else lanes
    links = LINKS if links is None else links
    c, s = np.cos(yaw), np.sin(yaw)
    return {
        "version": "v2.1.0",
        "segment_id": segment,
        "meta_data": {"source": source, "source_id": source_id},
        "timestamp": timestamp,
        "pose": {"rotation": [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], "translation": list(translation)},
        "sensor": {
            name: {
                "image_path": f"{split}/{segment}/image/{name}/{timestamp}.jpg",
                "extrinsic": {"rotation": CAMERA_TO_EGO, "translation": [1.0 + i, 0.1 * i, 1.5]},
                "intrinsic": {"K": K, "distortion": [0.0, 0.0, 0.0]},
            }
            for i, name in enumerate(cameras)
        },
        "annotation": {
            "lane_centerline": [{"id": 100 + i, "points": points} for i, points in enumerate(lanes)],
            "traffic_element": [],
            "topology_lclc": np.asarray(links).tolist(),
            "topology_lcte": [[] for _ in lanes],
        },
    }


def write(root: Path, content: dict, split: str = "train") -> Path:
    path = root / split / content["segment_id"] / "info" / f"{content['timestamp']}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(content))
    return path


def segment(root: Path, name: str, n: int, split: str = "train", step_m: float = 2.0, **kw) -> list[Path]:
    """n frames of a segment driving along the world x axis, 0.1 s apart."""
    x0, y0, z0 = kw.pop("translation", (100.0, 200.0, 10.0))
    return [write(root, frame(name, T0 + i * 100_000_000, split, translation=(x0 + step_m * i, y0, z0), **kw),
                  split) for i in range(n)]  # fmt: skip


def run(root: Path, out: Path, **kw) -> dict:
    return prepare("openlanev2", root, out, TargetOptions(), **kw)


def test_frames_graph_and_annotated_lanes(tmp_path):
    root, out = tmp_path / "olv2", tmp_path / "out"
    segment(root, "00001", 2, yaw=0.3)
    (root / "train" / "00001" / "info" / f"{T0}-ls.json").write_text("not JSON: never read")
    (root / "data_dict_subset_A.pkl").write_bytes(b"\x80\x04 never unpickled")
    summary = run(root, out)
    assert summary["frames"] == 2 and summary["frames_without_images"] == 2

    frames = read_table(out, "frames").to_pylist()
    ids = [f"openlanev2/00001/{T0}", f"openlanev2/00001/{T0 + 100_000_000}"]
    assert [f["frame_id"] for f in frames] == ids
    first = frames[0]
    identity = (first["dataset"], first["split"], first["log_id"], first["timestamp_ns"])
    assert identity == ("openlanev2", "train", "00001", T0)
    assert first["pose_translation"] == [100.0, 200.0, 10.0] and first["city"] == ""
    # the BEV x axis (the ego's right) in the world: the ego's -y turned by the yaw
    w, x, y, z = first["pose_rotation"]
    bev_x_yaw = np.arctan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))
    assert bev_x_yaw == pytest.approx(0.3 - np.pi / 2)
    assert first["ground_z"] == pytest.approx(-0.3) and first["ground_slope"] == [0.0, 0.0]
    assert first["lidar_path"] == "" and first["sample_token"] is None

    # cameras: the extrinsic turned into the BEV frame; the rig's sizes where the images are absent
    cameras = {c["name"]: c for c in first["cameras"]}
    assert list(cameras) == list(RING)
    side = cameras["ring_side_left"]
    extrinsic = np.eye(4)
    extrinsic[:3, :3], extrinsic[:3, 3] = CAMERA_TO_EGO, [4.0, 0.3, 1.5]
    np.testing.assert_allclose(np.reshape(side["sensor_to_ego"], (4, 4)), BEV_FROM_OPENLANEV2_EGO @ extrinsic)
    assert np.reshape(side["intrinsics"], (3, 3)).tolist() == K
    assert side["image_path"] == f"train/00001/image/ring_side_left/{T0}.jpg"
    assert (side["width"], side["height"]) == (2048, 1550)
    assert (cameras["ring_front_center"]["width"], cameras["ring_front_center"]["height"]) == (1550, 2048)

    # the graph: BEV x = -y ego, y = x ego; the fork and the merge are one vertex each, the link whose ends
    # lie 2 m apart joins them at their mean
    graph = read_table(out, "graphs").to_pylist()[0]
    xy = np.stack([graph["x"], graph["y"]], 1)
    src, dst = np.array(graph["src"]), np.array(graph["dst"])
    assert len(xy) == 9 and len(src) == 8
    vertex = {tuple(p): i for i, p in enumerate(np.round(xy, 3).tolist())}
    fork, merge, joined = vertex[(0.0, 10.0)], vertex[(0.0, 20.0)], vertex[(8.0, 11.0)]
    assert (np.sum(src == fork), np.sum(dst == fork)) == (2, 1)
    assert (np.sum(src == merge), np.sum(dst == merge)) == (1, 2)
    assert (np.sum(src == joined), np.sum(dst == joined)) == (1, 1)
    assert frames[0]["n_vertices"] == 9 and frames[0]["n_edges"] == 8

    # the annotated lanes and links, unchanged (heights, ids), and the submission keys
    lanes = read_annotated_lanes(out)
    assert set(lanes) == {f["frame_id"] for f in frames}
    one = lanes[first["frame_id"]]
    assert one.ids == [str(100 + i) for i in range(6)] and one.confidence is None
    assert [p.tolist() for p in one.points] == LANES
    assert one.links.tolist() == LINKS.tolist()
    assert list(read_annotated_lanes(out, [first["frame_id"], "openlanev2/x/1"])) == [first["frame_id"]]
    assert read_openlanev2_keys(out)[first["frame_id"]] == ("train", "00001", str(T0))
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["dataset"] == "openlanev2" and manifest["rows"]["annotated_lanes"] == 2


def test_range_crops_the_graph_not_the_annotated_lanes(tmp_path):
    root, out = tmp_path / "olv2", tmp_path / "out"
    segment(root, "00001", 1)
    prepare("openlanev2", root, out, TargetOptions(bev_range=Range.parse("20x30")))  # y (forward) to 15 m
    graph = read_table(out, "graphs").to_pylist()[0]
    assert max(graph["y"]) == pytest.approx(15.0) and min(graph["y"]) == pytest.approx(-5.0)
    assert max(graph["x"]) == pytest.approx(8.0)
    lanes = read_annotated_lanes(out)[f"openlanev2/00001/{T0}"]
    assert [p.tolist() for p in lanes.points] == LANES


def test_images_present_give_their_size_and_no_missing_count(tmp_path):
    from PIL import Image

    root, out = tmp_path / "olv2", tmp_path / "out"
    (path,) = segment(root, "00001", 1)
    for name, camera in json.loads(path.read_text())["sensor"].items():
        image = root / camera["image_path"]
        image.parent.mkdir(parents=True, exist_ok=True)
        Image.new("RGB", (64, 48) if name != "ring_front_center" else (48, 64)).save(image)
    summary = run(root, out)
    assert summary["frames_without_images"] == 0 and PreparedData.open(out).frames_without_images == 0
    (row,) = read_table(out, "frames").to_pylist()
    cameras = {c["name"]: (c["width"], c["height"]) for c in row["cameras"]}
    assert cameras["ring_front_center"] == (48, 64) and cameras["ring_rear_left"] == (64, 48)
    missing = pq.read_table(out / "annotated_lanes").column("images_missing").to_pylist()
    assert missing == [0]


def test_absent_images_are_counted_and_recorded(tmp_path):
    root, out = tmp_path / "olv2", tmp_path / "out"
    segment(root, "00001", 3)
    summary = run(root, out)
    assert summary["frames"] == 3 and summary["frames_without_images"] == 3
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["frames_without_images"] == 3 and "frames_without_images" not in manifest["last_run"]
    assert PreparedData.open(out).frames_without_images == 3
    assert pq.read_table(out / "annotated_lanes").column("images_missing").to_pylist() == [7, 7, 7]


def test_frames_naming_no_camera_count_as_without_images(tmp_path):
    """A frame file whose `sensor` is empty (as written from an AV2 log without calibration) has no image:
    counted, so that `cli train` refuses the folder before any work rather than at its first frame."""
    root, out = tmp_path / "olv2", tmp_path / "out"
    segment(root, "00001", 2, cameras=())
    summary = run(root, out, subset="A")
    assert summary["frames_without_images"] == 2 and PreparedData.open(out).frames_without_images == 2
    assert pq.read_table(out / "annotated_lanes").column("images_missing").to_pylist() == [1, 1]


def test_subset_narrows_a_mixed_root(tmp_path):
    root = tmp_path / "olv2"
    segment(root, "00001", 2)
    segment(root, "00002", 3, cameras=NUSCENES, source="nuscenes", source_id="scene-0061")
    both = run(root, tmp_path / "both")
    assert both["frames"] == 5
    b = run(root, tmp_path / "b", subset="B")
    frames = read_table(tmp_path / "b", "frames").to_pylist()
    assert b["frames"] == 3 and {f["log_id"] for f in frames} == {"00002"}
    assert {(c["width"], c["height"]) for c in frames[0]["cameras"]} == {(1600, 900)}
    assert [c["name"] for c in frames[0]["cameras"]] == list(NUSCENES)
    a = run(root, tmp_path / "a", subset="A")
    assert a["frames"] == 2
    assert json.loads((tmp_path / "a" / "manifest.json").read_text())["parameters"]["subset"] == "A"


def test_cities_enable_leakage_and_the_geographic_scheme(tmp_path):
    root = tmp_path / "olv2"
    segment(root, "00001", 4, source_id="log-a")
    segment(root, "10001", 4, split="val", translation=(103.0, 200.0, 10.0), source_id="log-b")
    cities = tmp_path / "cities.csv"
    cities.write_text("segment_id,city\n00001,PIT\n# a source id names the other segment\nlog-b,PIT\n")

    without = run(root, tmp_path / "without")
    assert without["leakage"]["splits"] == {} and "no city" in without["leakage"]["not_measured"]
    from pipeline.splits.leakage import leakage_line

    assert "leakage not measured: OpenLane-V2's frame files carry no city" in leakage_line(
        without["leakage"], "original"
    )
    with pytest.raises(ValueError, match="--split-scheme geographic needs each segment's city.*--cities"):
        run(root, tmp_path / "geo", split_scheme="geographic")
    assert not (tmp_path / "geo").exists()

    summary = run(root, tmp_path / "with", cities=cities)
    val = summary["leakage"]["splits"]["val"]
    assert val["frames"] == 4 and val["within_5m"] == 1.0 and list(val["cities"]) == ["PIT"]
    assert {f["city"] for f in read_table(tmp_path / "with", "frames").to_pylist()} == {"PIT"}
    geo = run(root, tmp_path / "geo", cities=cities, split_scheme="geographic", geo_cell=4.0, geo_buffer=0.0)
    assert "split_shares" in geo and list(geo["split_shares"]["cities"]) == ["PIT"]


@pytest.mark.parametrize(
    "text, problem",
    [
        ("segment_id,city\n00001,PIT,extra\n", "line 2: expected ID,CITY"),
        ("00001,\n", "line 1: expected ID,CITY"),
        ("00001,PIT\n00001,MIA\n", "line 2: 00001 is already in city 'PIT'"),
        ("10001,PIT\n", "segment 00001: has no city in this file (nor has its source_id log-a)"),
    ],
)
def test_a_bad_cities_file_is_one_line(tmp_path, text, problem):
    root = tmp_path / "olv2"
    segment(root, "00001", 1)
    cities = tmp_path / "cities.csv"
    cities.write_text(text)
    with pytest.raises(DataError) as error:
        run(root, tmp_path / "out", cities=cities)
    assert str(error.value).startswith(f"{cities}: ") and problem in str(error.value)
    assert "\n" not in str(error.value) and not (tmp_path / "out").exists()


def test_a_folder_is_added_to_only_with_the_same_cities_and_subset(tmp_path):
    root, out = tmp_path / "olv2", tmp_path / "out"
    segment(root, "00001", 1)
    cities = tmp_path / "cities.csv"
    cities.write_text("00001,PIT\n")
    run(root, out, cities=cities)
    digest = json.loads((out / "manifest.json").read_text())["parameters"]["cities_sha256"]
    cities.write_text("00001,MIA\n")
    with pytest.raises(ValueError, match=rf"--cities {cities} changed \(sha256 {digest[:12]}, now "):
        run(root, out, cities=cities)
    with pytest.raises(ValueError, match=r"--subset none \(now A\)"):
        run(root, out, cities=cities, subset="A")


def test_options_are_checked_before_any_work(tmp_path):
    root = tmp_path / "olv2"
    segment(root, "00001", 1)
    with pytest.raises(ValueError, match="--subset must be A or B, not 'C'"):
        run(root, tmp_path / "out", subset="C")
    with pytest.raises(ValueError, match="--cities file not found"):
        run(root, tmp_path / "out", cities=tmp_path / "absent.csv")
    with pytest.raises(ValueError, match="--subset is for --dataset openlanev2, not av2"):
        prepare("av2", root, tmp_path / "out", TargetOptions(), subset="A")
    assert not (tmp_path / "out").exists()


def test_split_files_name_openlanev2_frames_and_segments(tmp_path):
    root = tmp_path / "olv2"
    segment(root, "00001", 3)
    segment(root, "00002", 2)
    (tmp_path / "train.txt").write_text("00002\n")
    (tmp_path / "val.txt").write_text(f"openlanev2/00001/{T0 + 100_000_000}\nopenlanev2/00001/{T0}\n")
    summary = run(root, tmp_path / "out", split_files={"train": tmp_path / "train.txt",
                                                         "val": tmp_path / "val.txt"})  # fmt: skip
    assert summary["frames"] == 4 and summary["frames_in_no_split_file"] == 1
    splits = {f["frame_id"]: f["split"] for f in read_table(tmp_path / "out", "frames").to_pylist()}
    later = T0 + 100_000_000
    assert splits == {f"openlanev2/00001/{T0}": "val", f"openlanev2/00001/{later}": "val",
                      f"openlanev2/00002/{T0}": "train", f"openlanev2/00002/{later}": "train"}  # fmt: skip
    # the submission key keeps the split folder the file lies in
    assert read_openlanev2_keys(tmp_path / "out")[f"openlanev2/00001/{T0}"] == ("train", "00001", str(T0))


def broken_pose(content):
    content["pose"]["rotation"] = [[1.0, 0.0], [0.0, 1.0]]


def nan_point(content):
    content["annotation"]["lane_centerline"][2]["points"][1][2] = float("nan")


def one_point_lane(content):
    content["annotation"]["lane_centerline"][3]["points"] = [[20.0, 0.0, 0.0]]


def short_topology(content):
    content["annotation"]["topology_lclc"] = [row[:5] for row in content["annotation"]["topology_lclc"][:5]]


def no_pose(content):
    del content["pose"]


def other_segment(content):
    content["segment_id"] = "00009"


def no_annotation(content):
    del content["annotation"]


MALFORMED = {
    "pose": (broken_pose, "pose.rotation: has shape 2 x 2, not 3 x 3"),
    "nan": (nan_point, "annotation.lane_centerline[2].points: has non-finite values"),
    "one point": (
        one_point_lane,
        "annotation.lane_centerline[3].points: has 1 point, a lane needs 2 or more",
    ),
    "topology": (short_topology, "annotation.topology_lclc: is 5 x 5, but lane_centerline holds 6 lanes"),
    "missing key": (no_pose, "frame: missing key 'pose'"),
    "segment": (other_segment, "segment_id: is '00009', but the file lies in segment 00001"),
    "test split": (
        no_annotation,
        "annotation: missing: a frame without annotations (as in OpenLane-V2's "
        "test split) gives no lane graph to prepare",
    ),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_a_malformed_frame_file_is_one_line_and_skip_passes_over_it(tmp_path, case):
    edit, problem = MALFORMED[case]
    root, out = tmp_path / "olv2", tmp_path / "out"
    paths = segment(root, "00001", 3)
    content = json.loads(paths[1].read_text(), parse_constant=float)
    edit(content)
    paths[1].write_text(json.dumps(content))
    with pytest.raises(DataError) as error:
        run(root, out)
    assert str(error.value) == f"{paths[1]}: {problem}"
    assert not (out / "frames").exists() and not (out / "manifest.json").exists()
    summary = run(root, out, on_error="skip")
    assert summary["frames"] == 2 and summary["frames_skipped"] == 1
    (line,) = [json.loads(line) for line in (out / "errors.jsonl").read_text().splitlines()]
    assert line["frame_id"] == f"openlanev2/00001/{T0 + 100_000_000}" and line["source"] == str(paths[1])


def test_bad_json_and_a_bad_file_name_are_one_line(tmp_path):
    root, out = tmp_path / "olv2", tmp_path / "out"
    paths = segment(root, "00001", 2)
    paths[0].write_text(paths[0].read_text()[:300])
    with pytest.raises(DataError, match=rf"^{paths[0]}: JSON: cannot be read: "):
        run(root, out)
    odd = paths[1].with_name("latest.json")
    odd.write_text("{}")
    with pytest.raises(DataError, match=rf"^{odd}: file name: is not <timestamp>.json"):
        run(root, out)


def test_the_command_line_says_it_in_one_line(tmp_path):
    from cli import app

    root, out = tmp_path / "olv2", tmp_path / "out"
    segment(root, "00001", 2)
    result = CliRunner().invoke(app, ["prepare", "--dataset", "openlanev2", "--root", str(root), "--out",
                                      str(out), "--range", "50x100"])  # fmt: skip
    assert result.exit_code == 0, result.output
    said = " ".join(result.output.split())
    assert "leakage not measured: OpenLane-V2's frame files carry no city" in said
    assert "│ frames without images │ 2 │" in said
    result = CliRunner().invoke(app, ["prepare", "--dataset", "openlanev2", "--root", str(root), "--out",
                                      str(tmp_path / "geo"), "--split-scheme", "geographic"])  # fmt: skip
    errors = [line for line in result.output.splitlines() if line.lower().startswith("error")]
    assert result.exit_code == 1 and len(errors) == 1 and "--cities FILE" in result.output, result.output


def off_edges(graph: dict, other: dict) -> float:
    """The greatest distance from a vertex of `graph` (a graphs row) to the nearest edge of `other`."""
    points = np.stack([graph["x"], graph["y"]], 1).astype(np.float64)
    xy = np.stack([other["x"], other["y"]], 1).astype(np.float64)
    a, b = xy[other["src"]], xy[other["dst"]]
    along = np.clip(np.einsum("pek,ek->pe", points[:, None] - a, b - a) / ((b - a) ** 2).sum(1), 0, 1)
    nearest = a + along[..., None] * (b - a)
    return float(np.linalg.norm(points[:, None] - nearest, axis=2).min(axis=1).max())


def test_cli_synth_openlanev2_prepares_as_its_av2_logs(tmp_path):
    """`cli synth`'s OpenLane-V2 root (its AV2 logs written as subset A, images linked) prepares to the
    lines, poses and cameras of the same logs prepared as AV2, each image's size read from its header."""
    from pipeline.synth import synth

    raw = tmp_path / "raw"
    synth(raw, logs=2, frames_per_log=3, seed=0, frame_period=1.0, worlds=2, val_frames_per_log=3)
    options = TargetOptions(bev_range=Range.parse("50x100"))
    summary = prepare("openlanev2", raw / "openlanev2", tmp_path / "olv2", options)
    prepare("av2", raw / "av2" / "sensor", tmp_path / "av2", options)
    assert summary["frames"] == 6 and summary["frames_without_images"] == 0

    def rows(folder, table):
        return {r["frame_id"].split("/", 1)[1]: r for r in read_table(tmp_path / folder, table).to_pylist()}

    olv2_graphs, av2_graphs = rows("olv2", "graphs"), rows("av2", "graphs")
    assert sorted(olv2_graphs) == sorted(av2_graphs)
    for key, graph in av2_graphs.items():  # the same lines, which the writer resamples: each graph's vertices
        ours = olv2_graphs[key]  # within a centimetre of the other's edges
        assert len(graph["src"]) > 10
        assert off_edges(ours, graph) < 0.01 and off_edges(graph, ours) < 0.01, key
    olv2_frames, av2_frames = rows("olv2", "frames"), rows("av2", "frames")
    for key, frame in av2_frames.items():
        ours = olv2_frames[key]
        assert (ours["split"], ours["pose_translation"]) == (frame["split"], frame["pose_translation"])
        np.testing.assert_allclose(ours["pose_rotation"], frame["pose_rotation"], atol=1e-12)
        for theirs, mine in zip(frame["cameras"], ours["cameras"], strict=True):
            assert (mine["name"], mine["width"], mine["height"]) == (theirs["name"], theirs["width"],
                                                                     theirs["height"])  # fmt: skip
            np.testing.assert_allclose(mine["sensor_to_ego"], theirs["sensor_to_ego"], atol=1e-12)
            assert mine["intrinsics"] == theirs["intrinsics"]
            image = raw / "openlanev2" / mine["image_path"]
            assert image.read_bytes() == (raw / "av2" / "sensor" / theirs["image_path"]).read_bytes()


def test_a_malformed_file_in_a_worker_process_is_the_same_one_line(tmp_path):
    """With --workers, a worker's DataError reaches prepare whole (it pickles with its three parts): before,
    the pool could not rebuild it and waited for ever."""
    import pickle

    error = DataError("f.json", "pose", "is wrong")
    again = pickle.loads(pickle.dumps(error))
    assert (type(again), str(again), again.source, again.record) == (DataError, str(error), "f.json", "pose")
    root = tmp_path / "olv2"
    segment(root, "00001", 2)
    paths = segment(root, "00002", 2)
    paths[1].write_text("{")
    with pytest.raises(DataError, match=rf"^{paths[1]}: JSON: cannot be read: "):
        run(root, tmp_path / "out", workers=2)
    assert run(root, tmp_path / "out", workers=2, on_error="skip", overwrite=True)["frames"] == 3


def test_a_subset_the_root_lacks_is_named_with_what_the_root_holds(tmp_path):
    """--subset B on a root of subset A segments alone: one line naming the root, `--subset B` and what it
    holds, rather than the line of a root without any segment (which sent the user to check --root)."""
    root = tmp_path / "olv2"
    segment(root, "00001", 2)
    segment(root, "00002", 1)
    with pytest.raises(ValueError) as caught:
        run(root, tmp_path / "out", subset="B")
    holds = "it holds subset A's 2 segments"
    assert str(caught.value) == f"{root}: --subset B: no segment of subset B here; {holds}"
    assert not (tmp_path / "out").exists()
    segment(root, "00003", 1, split="val")
    with pytest.raises(ValueError) as caught:  # with --split: the count is of that split only
        run(root, tmp_path / "out", subset="B", split="val")
    holds = "that split holds subset A's 1 segment"
    assert str(caught.value) == f"{root}: --subset B: no segment of subset B in split val here; {holds}"
