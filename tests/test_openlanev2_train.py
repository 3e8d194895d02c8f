"""Training on OpenLane-V2 data (issue 61): camera only (its default there; lidar and fusion refused in one
line before any work), the paper's 24 epochs, the image settings of each rig (subset A: AV2's ring cameras,
subset B: nuScenes' cameras).

The refusals and settings run on the toy prepared dataset of test_baselines_train, marked as OpenLane-V2.
"""

from __future__ import annotations

import json
from pathlib import Path

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
