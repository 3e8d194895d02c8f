"""Training on OpenLane-V2 data (issue 61): camera only (its default there; lidar and fusion refused in one
line before any work), the paper's 24 epochs, the image settings of each rig (subset A: AV2's ring cameras,
subset B: nuScenes' cameras).

The refusals and settings run on the toy prepared dataset of test_baselines_train, marked as OpenLane-V2.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from test_baselines_train import write_toy_dataset
from test_faults import cli, one_error_line

from baselines.config import PAPER_EPOCHS
from baselines.data import PreparedDataset, camera_rig
from baselines.launch import TrainOptions, run_config
from baselines.models import resolve_config
from baselines.train import use_dataset_schedule
from pipeline import io
from pipeline.manifest import PreparedData

AV2_RING = ["ring_front_center", "ring_front_left"]  # two of subset A's seven, as the toy has two cameras
NUSCENES = ["CAM_FRONT", "CAM_BACK"]  # two of subset B's six


def as_openlanev2(data: Path, camera_names: list[str] | None = None) -> Path:
    """The toy prepared dataset `data` marked as OpenLane-V2 (its manifest and frames), its two cameras
    renamed to `camera_names` when given."""
    manifest = json.loads((data / "manifest.json").read_text())
    (data / "manifest.json").write_text(json.dumps({**manifest, "dataset": "openlanev2"}))
    frames = io.read_table(data, "frames").to_pylist()
    for frame in frames:
        frame["dataset"] = "openlanev2"
        for camera, name in zip(frame["cameras"], camera_names or [], strict=False):
            camera["name"] = name
    io.write_shard(data, "train__toy", {"frames": pa.Table.from_pylist(frames, io.SCHEMAS["frames"])})
    return data


@pytest.fixture
def toy_openlanev2(tmp_path) -> Path:
    return as_openlanev2(write_toy_dataset(tmp_path, frames=2), AV2_RING)


def test_the_paper_schedule_on_openlanev2_is_toponets_24_epochs(toy_openlanev2):
    config = resolve_config("paper")
    assert config.train.epochs == 0  # the dataset's schedule
    schedule = use_dataset_schedule(config, PreparedData.open(toy_openlanev2))
    assert schedule == "the paper's openlanev2 schedule"
    assert config.train.epochs == 24 == PAPER_EPOCHS["openlanev2"]
    assert PAPER_EPOCHS["av2"] == 24 and PAPER_EPOCHS["nuscenes"] == 110  # unchanged
    tiny = resolve_config("tiny")
    assert use_dataset_schedule(tiny, PreparedData.open(toy_openlanev2)).startswith("set")
    assert tiny.train.epochs == 11  # a preset's own epochs stay


def test_openlanev2_trains_the_camera_modality_by_default(toy_openlanev2, tmp_path):
    for preset in ("paper", "tiny", "gpu"):
        config, data, _ = run_config(TrainOptions(out=tmp_path / "run", data=toy_openlanev2, preset=preset))
        assert config.encoder.modality == "camera" and data == toy_openlanev2
    # on AV2 data the presets keep theirs (tiny: fusion)
    av2 = write_toy_dataset(tmp_path / "av2", frames=2)
    config = run_config(TrainOptions(out=tmp_path / "run", data=av2, preset="tiny"))[0]
    assert config.encoder.modality == "fusion"


@pytest.mark.parametrize(
    "args, source",
    [
        (["--modality", "lidar"], "--modality lidar"),
        (["--modality", "fusion"], "--modality fusion"),
        (["--set", "encoder.modality=fusion"], "--set encoder.modality=fusion"),
        (["--modality", "camera", "--set", "encoder.modality=lidar"], "--set encoder.modality=lidar"),
    ],
)
def test_lidar_and_fusion_on_openlanev2_are_refused_in_one_line_before_any_work(
    toy_openlanev2, tmp_path, args, source
):
    out = tmp_path / "run"
    result = cli("train", "--data", toy_openlanev2, "--out", out, "--preset", "tiny", *args)
    line = one_error_line(result, source, str(toy_openlanev2), "openlanev2", "no LiDAR", "--modality camera")
    assert line.startswith(f"error: {source}:")
    assert not out.exists()


def test_a_resumed_fusion_run_on_openlanev2_data_is_refused(toy_openlanev2, tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    resolve_config("tiny").save(out / "config.json")  # a fusion run
    (out / "run.json").write_text(json.dumps({"data": str(toy_openlanev2)}))
    with pytest.raises(ValueError, match=f"^the run {out} \\(modality fusion\\): .* no LiDAR"):
        run_config(TrainOptions(out=out, resume=True))


def frame(dataset: str, names: list[str]) -> dict:
    return {"frame_id": f"{dataset}/log/0", "dataset": dataset, "cameras": [{"name": name} for name in names]}


def test_each_openlanev2_rig_takes_its_datasets_image_settings():
    """Subset A (AV2's ring cameras) resizes as AV2 (paper 0.3), subset B (nuScenes' cameras) as nuScenes
    (0.5); nuScenes and AV2 frames keep their dataset's whatever the names."""
    assert camera_rig(frame("openlanev2", AV2_RING)) == "av2"
    assert camera_rig(frame("openlanev2", NUSCENES)) == "nuscenes"
    assert camera_rig(frame("nuscenes", ["cam0"])) == "nuscenes"
    assert camera_rig(frame("av2", ["cam0"])) == "av2"
    data = resolve_config("paper").data
    assert data.image_settings(camera_rig(frame("openlanev2", NUSCENES)), False) == (0.5, 0.0)
    assert data.image_settings(camera_rig(frame("openlanev2", AV2_RING)), False) == (0.3, 0.0)
    for names in ([], ["cam0", "cam1"], [AV2_RING[0], NUSCENES[0]]):
        with pytest.raises(ValueError, match="openlanev2/log/0: cameras .*neither AV2's ring cameras"):
            camera_rig(frame("openlanev2", names))
    with pytest.raises(ValueError, match="no image settings for the camera rig 'openlanev2'"):
        data.image_settings("openlanev2", False)


@pytest.mark.parametrize("names, size", [(AV2_RING, (29, 48)), (NUSCENES, (48, 80))])
def test_the_loader_resizes_each_rigs_images_by_its_settings(tmp_path, names, size):
    """The toy's 160 x 96 images: subset A's at AV2's 0.3 (48 x 29), subset B's at nuScenes' 0.5 (80 x 48)."""
    data = as_openlanev2(write_toy_dataset(tmp_path, frames=2), names)
    config = resolve_config("paper")
    sample = PreparedDataset(PreparedData.open(data), "train", config)[0]
    assert [tuple(s) for s in sample.image_sizes] == [size, size]


# ------------------------------------------------------------------------------------- end to end, cli synth


@pytest.fixture(scope="module")
def synth_root(tmp_path_factory) -> Path:
    """`cli synth`'s smallest dataset with sensors: one train and one val log of 2 frames each, whose
    OpenLane-V2 layout (subset A, from its AV2 logs) is OUT/openlanev2."""
    raw = tmp_path_factory.mktemp("openlanev2_train") / "raw"
    args = ["--logs", 2, "--frames-per-log", 2, "--val-frames-per-log", 2, "--worlds", 2]
    result = cli("synth", "--out", raw, *args)
    assert result.exit_code == 0, result.output
    return raw


def test_synth_prepare_train_eval_score_report_on_openlanev2(synth_root, tmp_path):
    """cli synth -> prepare --dataset openlanev2 -> train (camera, its default) -> eval (RUN/submission.pkl)
    -> score the submission -> report's OpenLane-V2 section. The run keeps every path (score threshold 0),
    so that the submission holds lanes: cli score reads the lanes that cli eval scored, to the same DET_l and
    TOP_ll, with heights on each frame's ground plane."""
    data, run, scored, report = (tmp_path / name for name in ("data", "run", "scored", "report"))
    prepared = cli("prepare", "--dataset", "openlanev2", "--root", synth_root / "openlanev2", "--out", data,
                   "--range", "50x100")  # fmt: skip
    assert prepared.exit_code == 0, prepared.output
    assert PreparedData.open(data).kind == "openlanev2" and PreparedData.open(data).frames_without_images == 0

    trained = cli("train", "--data", data, "--out", run, "--preset", "tiny", "--epochs", 1, "--path-points",
                  10, "--eval-frames", 1, "--set", "decoder.score_threshold=0.0")  # fmt: skip
    assert trained.exit_code == 0, trained.output
    assert "lanegap (tiny, camera) trained on" in trained.output
    assert json.loads((run / "config.json").read_text())["encoder"]["modality"] == "camera"

    evaluated = cli("eval", "--run", run, "--device", "cpu", "--no-floor", "--bootstrap", 0, "--metric",
                    "lanegap,openlanev2")  # fmt: skip
    assert evaluated.exit_code == 0, evaluated.output
    submission = run / "submission.pkl"
    assert f"{submission}: 2 frames in OpenLane-V2's submission format" in evaluated.output
    assert "one point of its precision-recall curve" not in evaluated.output  # LaneGAP keeps its scores
    assert str(submission) in evaluated.output.splitlines()[-1]  # the `wrote` line
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["submission"]["path"] == str(submission) and metrics["submission"]["frames"] == 2
    assert metrics["submission"]["lanes"] > 0
    assert metrics["submission"]["confidence"] == (
        "each lane's confidence is the mean of its edges' scores, each edge's the highest score of the "
        "model's paths that give it"
    )
    check_submission(submission, data, metrics["submission"]["lanes"], path_confidences(run, data))

    score = cli("score", "--pred", submission, "--gt", data, "--metric", "lanegap,openlanev2", "--out",
                scored, "--bootstrap", 0, "--json")  # fmt: skip
    assert score.exit_code == 0, score.output
    result = json.loads(score.stdout)
    assert result["frames"] == 2 and result["external"]["format"] == "openlanev2"
    assert result["external"]["lanes_read"] == metrics["submission"]["lanes"]
    for name in ("det_l", "top_ll"):  # the same lanes, read back from the file
        assert result["openlanev2"][name] == pytest.approx(metrics["openlanev2"][name], abs=1e-12), name

    reported = cli("report", "--runs", run, "--runs", scored, "--out", report, "--reference", "paper",
                   "--bootstrap", 0)  # fmt: skip
    assert reported.exit_code == 0, reported.output
    section = (report / "report.md").read_text().partition("## OpenLane-V2")[2]
    assert "| run | LaneGAP | camera | val split | 2 |" in section
    assert "OpenLane-V2 submission `lanegraph lanegap` (external)" in section


def path_confidences(run: Path, data: Path) -> dict[str, np.ndarray]:
    """Each val frame's lane confidences (by frame id) as the run's LaneGAP scores them: its paths above the
    threshold with their scores, snapped as its post-processing snaps them, each graph edge the highest
    score of the paths that give it (path2graph_scored), each lane the mean over its edges (lanes_of); the
    graph is the very one of the run's plain post-processing. Not all 1.0: a short training's scores."""
    import torch

    from baselines.data import collate
    from baselines.evaluate import load_model
    from baselines.layers.raster_head import lane_probability, snap_polylines
    from baselines.models.lanegap import select_paths
    from benchmark.graphs.path2graph import path2graph_scored
    from benchmark.metric.openlanev2 import lanes_of

    built, config, _ = load_model(run, torch.device("cpu"))
    dataset = PreparedDataset(PreparedData.open(data), "val", config, built.needs)
    confidences, all_scores = {}, []
    for index in range(len(dataset)):
        batch = collate([dataset[index]])
        with torch.no_grad():
            outputs = built.model(batch.sensors)
        [(scores, points)] = select_paths(outputs, config.decoder.score_threshold)
        paths = [config.encoder.polyline_to_metres(p.numpy()) for p in points]
        probability = lane_probability(outputs)[0]
        paths = snap_polylines(paths, probability, config.encoder, config.decoder.snap_radius)
        graph, edge_scores = path2graph_scored(paths, scores.numpy())
        plain = built.to_graphs(outputs)[0]
        assert np.array_equal(graph.src, plain.src) and np.array_equal(graph.dst, plain.dst)
        confidences[batch.frame_ids[0]] = lanes_of(graph, 11, edge_scores).confidence
        all_scores.append(scores.numpy())
    all_scores = np.concatenate(all_scores)
    assert len(all_scores) and np.all(all_scores < 1.0)  # the paths' own scores, each below 1
    return confidences


def check_submission(path: Path, data: Path, lanes: int, confidences: dict[str, np.ndarray]) -> None:
    """The pickle as OpenLane-V2 reads it: the val frames' keys, each lane's 11 points on its frame's ground
    plane (OpenLane-V2's ego frame: x forward, y left), confidences as `confidences` has them by frame id,
    topology_lclc (k, k) of 0/1, no traffic element and a (k, 0) topology_lcte."""
    from benchmark.formats.openlanev2_submission import load_pickle

    payload = load_pickle(path)
    assert payload["method"] == "lanegraph lanegap"
    columns = ["frame_id", "split", "ground_z", "ground_slope"]
    frames = io.read_table(data, "frames", columns=columns).to_pylist()
    keys = io.read_openlanev2_keys(data)
    val = {keys[f["frame_id"]]: f for f in frames if f["split"] == "val"}
    frame_of = {keys[f["frame_id"]]: f["frame_id"] for f in frames}
    assert set(payload["results"]) == set(val) and len(val) == 2
    assert sum(len(r["predictions"]["lane_centerline"]) for r in payload["results"].values()) == lanes
    for key, result in payload["results"].items():
        predictions, ground = result["predictions"], val[key]
        count = len(predictions["lane_centerline"])
        expected = confidences[frame_of[key]]
        written = np.array([lane["confidence"] for lane in predictions["lane_centerline"]])
        assert len(written) == len(expected) and np.allclose(written, expected, rtol=0, atol=1e-12)
        assert np.all(written < 1.0)
        for lane in predictions["lane_centerline"]:
            points = lane["points"]
            assert points.shape == (11, 3)
            x_bev, y_bev = -points[:, 1], points[:, 0]
            a, b = ground["ground_slope"]
            assert np.allclose(points[:, 2], ground["ground_z"] + a * x_bev + b * y_bev, atol=1e-5)
            assert np.all(np.abs(x_bev) <= 25 + 1e-6) and np.all(np.abs(y_bev) <= 50 + 1e-6)
        links = predictions["topology_lclc"]
        assert links.shape == (count, count) and set(np.unique(links)) <= {0.0, 1.0}
        assert predictions["traffic_element"] == [] and predictions["topology_lcte"].shape == (count, 0)
        assert len({lane["id"] for lane in predictions["lane_centerline"]}) == count


def test_train_refuses_a_dataset_whose_frames_lack_images_in_one_line(synth_root, tmp_path):
    """A frame file naming an image that is absent is prepared (cli prepare counts it); training on the
    dataset is refused in one line naming it and the count, before any work."""
    root, data, out = tmp_path / "openlanev2", tmp_path / "data", tmp_path / "run"
    shutil.copytree(synth_root / "openlanev2", root, copy_function=os.link)
    images = sorted((root / "train").glob("*/image/ring_front_center/*.jpg"))
    assert len(images) == 2
    images[0].unlink()  # one camera of one frame
    prepared = cli("prepare", "--dataset", "openlanev2", "--root", root, "--out", data)
    assert prepared.exit_code == 0, prepared.output
    assert PreparedData.open(data).frames_without_images == 1
    for modality in ("camera", None):
        args = ["--modality", modality] if modality else []
        result = cli("train", "--data", data, "--out", out, "--preset", "tiny", *args)
        line = one_error_line(result, str(data), "1 frame(s)", "openlanev2", "lack their images", str(root))
        assert line.startswith(f"error: {data}:")
        assert not out.exists()


def test_an_evaluation_on_other_data_removes_an_earlier_submission(tmp_path):
    """A run folder holds one evaluation: evaluated on AV2 data, an earlier evaluation's submission.pkl (which
    would not match the new metrics.json) goes, and none is written."""
    from baselines.evaluate import openlanev2_submission

    (tmp_path / "submission.pkl").write_bytes(b"an earlier evaluation's")
    (tmp_path / "notes.txt").write_text("the user's")
    av2 = PreparedData(tmp_path / "data", {"dataset": "av2"})
    assert openlanev2_submission(tmp_path, {}, {}, av2, "lanegraph lanegap") is None
    assert sorted(path.name for path in tmp_path.iterdir()) == ["notes.txt"]
