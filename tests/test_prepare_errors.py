"""Bad input: each case gets correct output or a clear error naming the file and record, and a
failed run leaves no partial shard behind."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pyarrow.parquet as pq
import pytest

from pipeline.errors import DataError
from pipeline.io import read_table
from pipeline.prepare import prepare, prepare_log
from pipeline.targets import TargetOptions

TRAIN_LOG = "adcf7d18-0510-35b0-a2fa-b4cea13a6d76"


@pytest.fixture
def root(av2_root, tmp_path):
    """A writable copy of the real train log (and the val log) to damage."""
    copy = tmp_path / "sensor"
    shutil.copytree(av2_root, copy)
    return copy


def run(root, out, **kw):
    return prepare("av2", root, out, TargetOptions(), **kw)


def no_partial_files(out):
    return not [p for p in out.rglob("*") if p.name.startswith(".") or p.name.endswith(".tmp")]


def test_missing_map_file(root, tmp_path):
    for f in (root / "train" / TRAIN_LOG / "map").glob("log_map_archive_*.json"):
        f.unlink()
    with pytest.raises(DataError, match="log_map_archive"):
        run(root, tmp_path / "out", split="train")


def test_malformed_map_json_fails_cleanly_and_skip_goes_on(root, tmp_path):
    (path,) = (root / "train" / TRAIN_LOG / "map").glob("log_map_archive_*.json")
    whole = path.read_text()
    path.write_text(whole[:5000])
    out = tmp_path / "out"
    with pytest.raises(DataError) as error:
        run(root, out)
    assert path.name in str(error.value) and "cannot be read" in str(error.value)
    assert no_partial_files(out)
    assert not list((out / "frames").glob("train__*")) if (out / "frames").exists() else True

    summary = run(root, out, on_error="skip")
    assert summary["frames"] == 157 and summary["frames_skipped"] == 156
    lines = [json.loads(line) for line in (out / "errors.jsonl").read_text().splitlines()]
    assert len(lines) == 1 and lines[0]["log"] == TRAIN_LOG and path.name in lines[0]["error"]
    # the failed log is tried again by the next run: its record is replaced, not added again
    assert run(root, out, on_error="skip")["logs_prepared"] == 1
    assert (out / "errors.jsonl").read_text().splitlines() == [json.dumps(lines[0])]
    path.write_text(whole)  # mended: the log is prepared and errors.jsonl holds nothing of it
    assert run(root, out, on_error="skip")["frames_skipped"] == 0
    assert not (out / "errors.jsonl").exists()


def test_missing_pose_file(root, tmp_path):
    (root / "train" / TRAIN_LOG / "city_SE3_egovehicle.feather").unlink()
    with pytest.raises(DataError, match="city_SE3_egovehicle.feather: ego poses: file not found"):
        run(root, tmp_path / "out", split="train")


def test_nan_pose_names_the_frame(root, tmp_path):
    path = root / "train" / TRAIN_LOG / "city_SE3_egovehicle.feather"
    poses = feather.read_table(path).to_pandas()
    poses.loc[100:140, "tx_m"] = np.nan  # 0.2 s of poses at ~200 Hz: the frames there use them
    feather.write_feather(pa.Table.from_pandas(poses, preserve_index=False), path)
    out = tmp_path / "out"
    with pytest.raises(DataError, match=f"frame av2/{TRAIN_LOG}/") as error:
        run(root, out, split="train")
    assert "NaN" in str(error.value)
    assert no_partial_files(out) and not (out / "frames").exists()
    summary = run(root, out, split="train", on_error="skip")
    assert 1 <= summary["frames_skipped"] <= 3 and summary["frames"] == 156 - summary["frames_skipped"]
    errors = [json.loads(line) for line in (out / "errors.jsonl").read_text().splitlines()]
    assert all(e["frame_id"].startswith(f"av2/{TRAIN_LOG}/") for e in errors)


def test_unknown_successor_ids_are_ignored(root, tmp_path):
    (path,) = (root / "train" / TRAIN_LOG / "map").glob("log_map_archive_*.json")
    data = json.loads(path.read_text())
    for segment in data["lane_segments"].values():
        segment["successors"] = segment["successors"] + [999999999]
    path.write_text(json.dumps(data))
    out = tmp_path / "out"
    assert run(root, out, split="train")["frames"] == 156


def test_empty_crop_is_a_valid_empty_frame(root, tmp_path):
    path = root / "train" / TRAIN_LOG / "city_SE3_egovehicle.feather"
    poses = feather.read_table(path).to_pandas()
    poses["tx_m"] += 10_000.0  # drive far away from every lane
    feather.write_feather(pa.Table.from_pandas(poses, preserve_index=False), path)
    out = tmp_path / "out"
    assert run(root, out, split="train")["frames"] == 156
    graphs = read_table(out, "graphs").to_pylist()
    assert all(g["x"] == [] and g["src"] == [] for g in graphs)
    assert read_table(out, "paths").num_rows == 0 and read_table(out, "pieces").num_rows == 0


def test_rerun_skips_finished_shards_and_overwrite_redoes_them(av2_root, tmp_path):
    out = tmp_path / "out"
    first = run(av2_root, out)
    assert first["logs_prepared"] == 2
    second = run(av2_root, out)
    assert second["logs_prepared"] == 0 and second["logs_already_done"] == 2
    assert read_table(out, "frames").num_rows == 313
    third = run(av2_root, out, overwrite=True)
    assert third["logs_prepared"] == 2 and read_table(out, "frames").num_rows == 313


def test_rerun_with_other_options_is_refused(av2_root, tmp_path):
    out = tmp_path / "out"
    run(av2_root, out, split="val")
    with pytest.raises(ValueError, match="prepared with other options"):
        prepare("av2", av2_root, out, TargetOptions(path_points=20), split="val")
    assert (
        prepare("av2", av2_root, out, TargetOptions(path_points=20), split="val", overwrite=True)["frames"]
        == 157
    )


VAL_LOG = "3b3570b4-7b0b-3268-a571-b0889dbf40b6"


def test_split_files_replace_the_dataset_splits(av2_root, tmp_path):
    # both real logs swap splits; a name that is no log here is ignored; comments and blanks too
    (tmp_path / "geo_train.txt").write_text(f"# geo split\n{VAL_LOG}\n\nnot-a-log\n")
    (tmp_path / "geo_val.txt").write_text(f"{TRAIN_LOG}\n")
    files = {"train": tmp_path / "geo_train.txt", "val": tmp_path / "geo_val.txt"}
    out = tmp_path / "out"
    summary = run(av2_root, out, split_files=files)
    assert summary["logs"] == 2 and summary["logs_in_no_split_file"] == 0
    frames = read_table(out, "frames", columns=["split", "log_id"]).to_pylist()
    assert {(f["split"], f["log_id"]) for f in frames} == {("train", VAL_LOG), ("val", TRAIN_LOG)}
    assert sorted(p.name for p in (out / "graphs").iterdir()) == [
        f"train__{VAL_LOG}.parquet",
        f"val__{TRAIN_LOG}.parquet",
    ]
    # --split picks one of the files' splits; a log in no file is left out and counted
    (tmp_path / "geo_val.txt").write_text("")
    only = run(av2_root, tmp_path / "only", split_files=files, split="train")
    assert only["logs"] == 1 and only["logs_in_no_split_file"] == 1 and only["frames"] == 157


def test_a_log_in_two_split_files_is_an_error(av2_root, tmp_path):
    (tmp_path / "a.txt").write_text(f"{TRAIN_LOG}\n")
    (tmp_path / "b.txt").write_text(f"{VAL_LOG}\n{TRAIN_LOG}\n")
    files = {"train": tmp_path / "a.txt", "val": tmp_path / "b.txt"}
    with pytest.raises(DataError, match=f"b.txt.*line 2.*{TRAIN_LOG} is already in split 'train'"):
        run(av2_root, tmp_path / "out", split_files=files)
    with pytest.raises(FileNotFoundError, match="missing.txt: split file of split 'val' not found"):
        run(av2_root, tmp_path / "out", split_files={"val": tmp_path / "missing.txt"})


def test_streammapnet_geo_splits_put_both_real_logs_in_train(av2_root, tmp_path):
    splits = av2_root.parents[1] / "splits"
    files = {"train": splits / "av2_geo_train.txt", "val": splits / "av2_geo_val.txt"}
    summary = run(av2_root, tmp_path / "out", split_files=files)
    assert summary["frames"] == 313 and summary["logs_in_no_split_file"] == 0
    assert set(read_table(tmp_path / "out", "frames", columns=["split"])["split"].to_pylist()) == {"train"}


def test_a_dataset_prepared_before_ground_z_is_refused_by_name(av2_root, tmp_path):
    """Shards of schema 1 lack frames.ground_z: reading them is a clear error (not a column of
    nulls), and so is preparing into them without --overwrite."""
    out = tmp_path / "out"
    run(av2_root, out, split="val")
    (shard,) = (out / "frames").glob("*.parquet")
    pq.write_table(pq.read_table(shard).drop_columns(["ground_z"]), shard)
    manifest = json.loads((out / "manifest.json").read_text())
    (out / "manifest.json").write_text(json.dumps({**manifest, "schema_version": 1}))
    with pytest.raises(DataError, match=f"{shard}: column ground_z: missing.*--overwrite"):
        read_table(out, "frames")
    assert read_table(out, "frames", columns=["frame_id"]).num_rows == 157  # old columns still read
    with pytest.raises(ValueError, match="schema_version 1.*--overwrite"):
        run(av2_root, out, split="val")
    assert run(av2_root, out, split="val", overwrite=True)["frames"] == 157
    assert read_table(out, "frames")["ground_z"].null_count == 0


def test_a_log_prepared_one_split_at_a_time_keeps_the_other_splits_records(root, tmp_path):
    """Split files put the first half of the train log's frames in train and the rest in val; NaN poses
    spoil a few train frames. Preparing --split val after --split train into the same OUT tries that log
    again (its val shard) and must keep the records of its train frames (they were dropped by log name)."""
    from pipeline.adapters.av2 import frame_timestamps

    log_dir = root / "train" / TRAIN_LOG
    path = log_dir / "city_SE3_egovehicle.feather"
    poses = feather.read_table(path).to_pandas()
    poses.loc[100:140, "tx_m"] = np.nan  # early frames: in the first half
    feather.write_feather(pa.Table.from_pandas(poses, preserve_index=False), path)
    times = frame_timestamps(log_dir).tolist()
    half = len(times) // 2
    for split, part in (("train", times[:half]), ("val", times[half:])):
        (tmp_path / f"{split}.txt").write_text("".join(f"av2/{TRAIN_LOG}/{t}\n" for t in part))
    files = {split: tmp_path / f"{split}.txt" for split in ("train", "val")}
    out = tmp_path / "out"
    skipped = run(root, out, split_files=files, split="train", on_error="skip")["frames_skipped"]
    first = (out / "errors.jsonl").read_text().splitlines()
    assert skipped >= 1 and len(first) == skipped
    assert all(json.loads(line)["splits"] == ["train"] for line in first)
    assert run(root, out, split_files=files, split="val", on_error="skip")["frames_skipped"] == 0
    assert (out / "errors.jsonl").read_text().splitlines() == first


def test_a_damaged_errors_jsonl_is_one_line_before_any_work(av2_root, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    damaged_files = ('{"log": "a"}\nnot json\n', '{"frame_id": null}\n', "null\n",
                     '{"log": "a", "splits": "val"}\n')  # fmt: skip
    for damaged in damaged_files:
        (out / "errors.jsonl").write_text(damaged)
        with pytest.raises(DataError, match=r'errors.jsonl: line \d: not a JSON record naming its "log"'):
            run(av2_root, out, split="val", on_error="skip")
        assert not (out / "frames").exists()


def test_an_interrupted_run_keeps_the_records_of_the_logs_it_finished(root, tmp_path, monkeypatch):
    """NaN poses spoil frames of both logs; the run is interrupted as the second log starts. The first log's
    shards are done (the next run does not prepare it again), so its records must be in errors.jsonl already
    (they were written at the run's end only, and lost)."""
    import pipeline.prepare as prepare_module

    for log_dir in (root / "train" / TRAIN_LOG, root / "val" / VAL_LOG):
        path = log_dir / "city_SE3_egovehicle.feather"
        poses = feather.read_table(path).to_pandas()
        poses.loc[100:140, "tx_m"] = np.nan
        feather.write_feather(pa.Table.from_pandas(poses, preserve_index=False), path)
    real, started = prepare_module.prepare_log, []

    def interrupted(job, *args, **kw):
        started.append(job.name)
        if len(started) == 2:
            raise KeyboardInterrupt
        return real(job, *args, **kw)

    out = tmp_path / "out"
    monkeypatch.setattr(prepare_module, "prepare_log", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run(root, out, on_error="skip")
    first = [json.loads(line) for line in (out / "errors.jsonl").read_text().splitlines()]
    assert first and {record["log"] for record in first} == {started[0]}
    monkeypatch.undo()
    summary = run(root, out, on_error="skip")
    assert summary["logs_prepared"] == 1 and summary["frames_skipped"] >= 1
    every = [json.loads(line) for line in (out / "errors.jsonl").read_text().splitlines()]
    assert every[: len(first)] == first and {record["log"] for record in every} == {TRAIN_LOG, VAL_LOG}
    assert sum(record["log"] == started[0] for record in every) == len(first)  # not recorded twice


def slow_train_log(job, *args, **kw):
    """prepare_log, but the train log waits (in its worker) for errors.jsonl in `out`, then breaks."""
    if job.name != TRAIN_LOG:
        return prepare_log(job, *args, **kw)
    for _ in range(600):
        if (kw["out"] / "errors.jsonl").is_file():
            break
        time.sleep(0.1)
    raise RuntimeError("the train log broke")


def test_under_workers_a_log_is_recorded_as_it_finishes(root, tmp_path, monkeypatch):
    """--workers 2: the val log finishes while the train log (first in job order) is still running, then the
    train log fails with an unexpected error. The val log's shards are done, so its records must be written
    already (a pool's results in job order held them behind the train log, and they were lost)."""
    import pipeline.prepare as prepare_module

    path = root / "val" / VAL_LOG / "city_SE3_egovehicle.feather"
    poses = feather.read_table(path).to_pandas()
    poses.loc[100:140, "tx_m"] = np.nan
    feather.write_feather(pa.Table.from_pandas(poses, preserve_index=False), path)
    out = tmp_path / "out"
    monkeypatch.setattr(prepare_module, "prepare_log", slow_train_log)
    with pytest.raises(RuntimeError, match="the train log broke"):
        run(root, out, on_error="skip", workers=2)
    records = [json.loads(line) for line in (out / "errors.jsonl").read_text().splitlines()]
    assert records and {record["log"] for record in records} == {VAL_LOG}


def test_a_record_of_two_splits_is_narrowed_as_each_is_prepared_again():
    """A log that failed as a whole over train and val, then prepared --split val: the record stays for train
    only (it stayed whole, and a failing val was then listed twice)."""
    from pipeline.error_records import ErrorRecords

    whole = {"log": "a", "splits": ["train", "val"], "frame_id": None, "source": "s", "error": "e"}
    records = ErrorRecords(Path("/nonexistent"), [whole])
    records.renewed["a"] = {"val"}
    assert records.kept() == [{**whole, "splits": ["train"]}]
    records.renewed["a"] = {"val", "train"}
    assert records.kept() == []
