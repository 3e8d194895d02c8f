"""Honest splits through `cli prepare` (issue 52): the leakage of every non-training split in manifest.json,
frame-level split files of each form, the geographic scheme, and bad split inputs as one line each."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from cli import app
from pipeline.errors import DataError
from pipeline.io import read_table
from pipeline.prepare import prepare
from pipeline.targets import TargetOptions

COLUMNS = ["frame_id", "split", "log_id", "timestamp_ns", "sample_token", "city", "pose_translation"]


def frames_of(data) -> list[dict]:
    return sorted(read_table(data, "frames", columns=COLUMNS).to_pylist(), key=lambda f: f["frame_id"])


def nearest_training(frames: list[dict]) -> dict[str, float]:
    """Brute force: each non-training frame's distance to the nearest training frame of its city."""
    train = [f for f in frames if f["split"] == "train"]
    distances = {}
    for frame in frames:
        if frame["split"] != "train":
            same = [t["pose_translation"][:2] for t in train if t["city"] == frame["city"]]
            here = frame["pose_translation"][:2]
            gaps = np.linalg.norm(np.array(same) - here, axis=1) if same else [np.inf]
            distances[frame["frame_id"]] = float(np.min(gaps))
    return distances


def manifest(data) -> dict:
    return json.loads((data / "manifest.json").read_text())


@pytest.fixture(scope="module")
def av2_frames(synth_prepared) -> list[dict]:
    """The synthetic AV2 frames (conftest: 3 training logs and 1 validation log, all in world 0)."""
    return frames_of(synth_prepared["av2"])


def test_validation_that_revisits_training_roads_leaks_by_the_measure(synth_raw, av2_frames, tmp_path):
    # every second frame of one training log goes to val: its neighbours, 0.1 s away, stay in train
    log = sorted({f["log_id"] for f in av2_frames if f["split"] == "train"})[0]
    ours = [f for f in av2_frames if f["log_id"] == log]
    val = [f"{log}_{f['timestamp_ns']}" for f in ours[1::2]]  # the AV2 <log>_<timestamp_ns> form
    train = [f["frame_id"] for f in av2_frames if f["split"] == "train" and f["frame_id"] not in
             {g["frame_id"] for g in ours[1::2]}]  # fmt: skip
    (tmp_path / "train.txt").write_text("\n".join(train) + "\n")
    (tmp_path / "val.txt").write_text("\n".join(val) + "\n")
    out = tmp_path / "out"
    summary = prepare("av2", synth_raw / "av2" / "sensor", out, TargetOptions(),
                      split_files={"train": tmp_path / "train.txt", "val": tmp_path / "val.txt"})  # fmt: skip
    frames = frames_of(out)
    assert {f["frame_id"] for f in frames if f["split"] == "val"} == {g["frame_id"] for g in ours[1::2]}
    assert summary["logs_in_no_split_file"] == 1 and summary["frames_in_no_split_file"] == 0
    # the log cut in two: a shard per split
    assert {p.name for p in (out / "frames").iterdir() if log in p.name} == {
        f"train__{log}.parquet", f"val__{log}.parquet"}  # fmt: skip
    distances = np.array(list(nearest_training(frames).values()))
    leakage = manifest(out)["leakage"]
    assert leakage == summary["leakage"] and leakage["train_splits"] == ["train"]
    val_row = leakage["splits"]["val"]
    assert val_row["frames"] == len(val) == 10
    assert val_row["within_5m"] == pytest.approx(np.mean(distances <= 5.0), abs=1e-4) == 1.0
    assert val_row["median_m"] == pytest.approx(np.median(distances), abs=0.01)


def test_the_geographic_scheme_keeps_every_val_frame_beyond_the_buffer(synth_raw, av2_frames, tmp_path):
    out = tmp_path / "geo"
    summary = prepare("av2", synth_raw / "av2" / "sensor", out, TargetOptions(), split_scheme="geographic",
                      geo_cell=50.0, geo_seed=3)  # fmt: skip
    frames = frames_of(out)
    assert {f["split"] for f in frames} == {"train", "val"}
    assert len(frames) + summary["frames_in_buffer"] == len(av2_frames)
    distances = np.array(list(nearest_training(frames).values()))
    diagonal = float(np.hypot(30.0, 60.0))  # the buffer: no val window shares ground with a training window
    assert distances.min() > diagonal
    row = manifest(out)["leakage"]["splits"]["val"]
    assert row["within_5m"] == row["within_range"] == row["overlapping"] == row["covered"] == 0.0
    parameters = manifest(out)["parameters"]
    assert (parameters["split_scheme"], parameters["geo_cell"], parameters["geo_buffer"],
            parameters["geo_seed"]) == ("geographic", 50.0, pytest.approx(diagonal), 3)  # fmt: skip
    assert (out / "splits.png").is_file()
    # the same inputs and seed: the same split
    again = tmp_path / "again"
    prepare("av2", synth_raw / "av2" / "sensor", again, TargetOptions(), split_scheme="geographic",
            geo_cell=50.0, geo_seed=3)  # fmt: skip
    placed = [(f["frame_id"], f["split"]) for f in frames]
    assert [(f["frame_id"], f["split"]) for f in frames_of(again)] == placed


def test_adding_a_split_keeps_the_leakage_of_the_others_and_overwrite_starts_afresh(synth_raw, tmp_path):
    out = tmp_path / "out"
    whole = prepare("av2", synth_raw / "av2" / "sensor", out, TargetOptions())["leakage"]
    # a run without --overwrite adds to the folder: the leakage is the whole folder's
    again = prepare("av2", synth_raw / "av2" / "sensor", out, TargetOptions(), split="val")
    assert again["logs_already_done"] == 1 and again["leakage"] == whole == manifest(out)["leakage"]
    assert whole["splits"]["val"]["frames"] == 20
    # --overwrite starts afresh: the training logs go, and the leakage says so
    only_val = prepare("av2", synth_raw / "av2" / "sensor", out, TargetOptions(), split="val", overwrite=True)
    assert only_val["leakage"]["splits"] == {} and "no training frames" in only_val["leakage"]["note"]
    assert {f["split"] for f in frames_of(out)} == {"val"} and manifest(out)["rows"]["frames"] == 20


def test_nuscenes_sample_tokens_and_frame_ids_name_frames(synth_raw, synth_prepared, tmp_path):
    frames = frames_of(synth_prepared["nuscenes"])
    scene = sorted({f["log_id"] for f in frames})[0]
    ours = [f for f in frames if f["log_id"] == scene]
    (tmp_path / "a.txt").write_text("\n".join(f["sample_token"] for f in ours[:5]) + "\n")
    (tmp_path / "b.txt").write_text("\n".join(f["frame_id"] for f in ours[5:]) + "\n")
    out = tmp_path / "out"
    files = {"mini_train": tmp_path / "a.txt", "mini_val": tmp_path / "b.txt"}
    summary = prepare("nuscenes", synth_raw / "nuscenes", out, TargetOptions(), version="v1.0-mini",
                      split_files=files)  # fmt: skip
    got = {f["frame_id"]: f["split"] for f in frames_of(out)}
    assert got == {f["frame_id"]: "mini_train" if i < 5 else "mini_val" for i, f in enumerate(ours)}
    assert summary["logs_in_no_split_file"] == len({f["log_id"] for f in frames}) - 1
    assert summary["split_file_lines_unmatched"] == []


def test_frame_lines_that_match_no_frame_are_counted_then_refused(synth_raw, av2_frames, tmp_path):
    log = av2_frames[0]["log_id"]
    wrong = [f"av2/{log}/{f['timestamp_ns'] // 1000}" for f in av2_frames[:6]]  # microseconds, not ns
    right = [f["frame_id"] for f in av2_frames if f["log_id"] == log]
    (tmp_path / "train.txt").write_text("\n".join(right + wrong[:3] + ["elsewhere-log"]) + "\n")
    summary = prepare("av2", synth_raw / "av2" / "sensor", tmp_path / "out", TargetOptions(),
                      split_files={"train": tmp_path / "train.txt"})  # fmt: skip
    assert len(summary["split_file_lines_unmatched"]) == 3
    assert summary["split_file_lines_naming_nothing_here"] == 1
    (tmp_path / "train.txt").write_text("\n".join(right + wrong) + "\n")
    first = rf"train.txt.*line {len(right) + 1}.*{wrong[0]} names no frame.*5 more"
    with pytest.raises(DataError, match=first):
        prepare("av2", synth_raw / "av2" / "sensor", tmp_path / "refused", TargetOptions(),
                split_files={"train": tmp_path / "train.txt"})  # fmt: skip
    assert not (tmp_path / "refused").exists()


def one_error_line(args: list[str]) -> str:
    result = CliRunner().invoke(app, [str(a) for a in args])
    assert result.exit_code != 0, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert "Traceback" not in result.output, result.output
    return "\n".join(lines)


def test_bad_split_inputs_each_one_clear_line(synth_raw, av2_frames, tmp_path):
    root = synth_raw / "av2" / "sensor"
    base = ["prepare", "--dataset", "av2", "--root", root, "--out", tmp_path / "out"]
    (tmp_path / "t.txt").write_text(av2_frames[0]["log_id"] + "\n")
    train_file = f"train={tmp_path / 't.txt'}"
    said = one_error_line(base + ["--split-scheme", "geographic", "--split-file", train_file])
    assert said.count("error:") == 1 and "--split-scheme geographic and --split-file" in said
    said = one_error_line(base + ["--split-scheme", "geographic", "--geo-cell", "0"])
    assert "--geo-cell" in said
    said = one_error_line(base + ["--split-scheme", "nearby"])
    assert "--split-scheme" in said
    # a frame named in val whose log is named whole in train
    (tmp_path / "v.txt").write_text(av2_frames[0]["frame_id"] + "\n")
    said = one_error_line(base + ["--split-file", f"train={tmp_path / 't.txt'}",
                                  "--split-file", f"val={tmp_path / 'v.txt'}"])  # fmt: skip
    assert said.count("error:") == 1 and "v.txt" in said and "named whole in split 'train'" in said
    assert not (tmp_path / "out").exists()
