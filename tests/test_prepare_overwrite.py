"""`cli prepare --overwrite` starts the output afresh, and a folder is added to only under the split plan
and raw dataset it was prepared from (issue 59): nothing stale left behind, nothing changed silently."""

from __future__ import annotations

import json
import shutil
import types
from pathlib import Path
from unittest import mock

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest

import pipeline.manifest as output_folder
from pipeline.io import read_table
from pipeline.prepare import prepare
from pipeline.targets import TargetOptions
from tests.test_faults import cli, files, one_error_line


@pytest.fixture(scope="module")
def raw(tmp_path_factory) -> Path:
    """A tiny synthetic raw dataset, seed 0, without sensors: 1 training and 1 validation log of 3 frames,
    in AV2 and nuScenes (v1.0-mini) formats."""
    from pipeline.synth import synth

    out = tmp_path_factory.mktemp("raw")
    synth(out, logs=2, frames_per_log=3, val_frames_per_log=3, worlds=2, sensors=False)
    return out


def logs_of(raw: Path) -> dict[str, str]:
    """{split: log id} of the AV2 logs."""
    return {split: next((raw / "av2" / "sensor" / split).iterdir()).name for split in ("train", "val")}


def frames_by_log(out: Path) -> dict[str, str]:
    rows = read_table(out, "frames", columns=["log_id", "split"]).to_pylist()
    return {row["log_id"]: row["split"] for row in rows}


def nan_pose(log: Path) -> bytes:
    """Make the pose of an AV2 log's first frame NaN (the frame is skipped with --on-error skip); returns
    the file's bytes before."""
    from pipeline.adapters.av2 import frame_timestamps

    path = log / "city_SE3_egovehicle.feather"
    before = path.read_bytes()
    poses = feather.read_table(path)
    times = poses.column("timestamp_ns").to_numpy()
    tx = poses.column("tx_m").to_numpy().copy()
    tx[np.argmin(np.abs(times - frame_timestamps(log)[0]))] = np.nan
    column = poses.schema.get_field_index("tx_m")
    feather.write_feather(poses.set_column(column, "tx_m", pa.array(tx)), path)
    return before


def test_overwrite_with_another_plan_leaves_only_this_runs_output(raw, tmp_path):
    root, logs = tmp_path / "sensor", logs_of(raw)
    shutil.copytree(raw / "av2" / "sensor", root)
    out = tmp_path / "out"
    # the earlier run: both logs, one frame of the val log skipped into errors.jsonl
    poses = root / "val" / logs["val"] / "city_SE3_egovehicle.feather"
    before = nan_pose(poses.parent)
    first = cli("prepare", "--dataset", "av2", "--root", root, "--out", out, "--on-error", "skip")
    assert first.exit_code == 0, first.output
    poses.write_bytes(before)
    assert frames_by_log(out) == {logs["train"]: "train", logs["val"]: "val"}
    assert len((out / "errors.jsonl").read_text().splitlines()) == 1
    earlier_picture = (out / "splits.png").read_bytes()
    # the user's own files, in the folder and in a table's folder
    (out / "notes.txt").write_text("mine\n")
    (out / "frames" / "README.txt").write_text("mine too\n")
    (tmp_path / "one_log.txt").write_text(logs["train"] + "\n")
    result = cli("prepare", "--dataset", "av2", "--root", root, "--out", out, "--overwrite", "--split-file",
                 f"train={tmp_path / 'one_log.txt'}", "--json")  # fmt: skip
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout.splitlines()[-1])
    assert summary["logs"] == 1 and summary["frames"] == 3 and summary["logs_in_no_split_file"] == 1
    # exactly what this run wrote: the val log's shards and the earlier errors are gone
    assert frames_by_log(out) == {logs["train"]: "train"}
    for table in ("frames", "graphs", "paths", "pieces", "piece_links", "rasters"):
        assert sorted(p.name for p in (out / table).glob("*.parquet")) == [f"train__{logs['train']}.parquet"]
    assert not (out / "errors.jsonl").exists()
    assert (out / "splits.png").read_bytes() != earlier_picture  # drawn again, of one log
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["rows"]["frames"] == 3 and manifest["leakage"]["splits"] == {}
    assert manifest["parameters"]["split_files"] == {"train": str((tmp_path / "one_log.txt").resolve())}
    # files the project did not write stay, and no work folder is left behind
    assert (out / "notes.txt").read_text() == "mine\n" and (out / "frames" / "README.txt").is_file()
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["manifest.json", "splits.png", "notes.txt", "frames", "graphs", "paths", "pieces", "piece_links",
         "rasters"]
    )  # fmt: skip


def test_a_failing_overwrite_keeps_the_earlier_output(raw, tmp_path):
    root, logs = tmp_path / "sensor", logs_of(raw)
    shutil.copytree(raw / "av2" / "sensor", root)
    out = tmp_path / "out"
    assert prepare("av2", root, out, TargetOptions())["frames"] == 6
    before = files(out)
    # bad input found before any work: one line, nothing removed
    result = cli("prepare", "--dataset", "av2", "--root", root, "--out", out, "--overwrite", "--split-file",
                 f"train={tmp_path / 'missing.txt'}")  # fmt: skip
    one_error_line(result, "missing.txt", "not found")
    assert files(out) == before
    # bad input found while preparing, with other options: the earlier output stays whole, not half
    # replaced by shards of other options under a manifest that does not describe them
    (map_file,) = (root / "val" / logs["val"] / "map").glob("log_map_archive_*.json")
    map_file.write_text(map_file.read_text()[:100])
    other = ["--overwrite", "--path-points", 20]
    result = cli("prepare", "--dataset", "av2", "--root", root, "--out", out, *other)
    one_error_line(result, str(map_file), "cannot be read")
    assert files(out) == before
    kept = ["manifest.json", "splits.png", "frames", "graphs", "paths", "pieces", "piece_links", "rasters"]
    assert sorted(p.name for p in out.iterdir()) == sorted(kept)  # no work folder left behind


def test_a_changed_split_file_is_refused(raw, tmp_path):
    root, logs = raw / "av2" / "sensor", logs_of(raw)
    split_file, out = tmp_path / "train.txt", tmp_path / "out"
    split_file.write_text(logs["train"] + "\n")
    prepare("av2", root, out, TargetOptions(), split_files={"train": split_file})
    digest = json.loads((out / "manifest.json").read_text())["parameters"]["split_file_sha256"]["train"]
    assert len(digest) == 64
    # the same file unchanged: added to (nothing left to do)
    again = prepare("av2", root, out, TargetOptions(), split_files={"train": split_file})
    assert again["logs_already_done"] == 1
    # the same path, other contents: the shards follow the old plan, so adding to them is refused
    split_file.write_text(logs["val"] + "\n")
    before = files(out)
    args = ["prepare", "--dataset", "av2", "--root", root, "--out", out, "--split-file",
            f"train={split_file}"]  # fmt: skip
    said = one_error_line(cli(*args), str(out), "--split-file", "train.txt", "changed", "--overwrite")
    assert digest[:12] in said
    assert files(out) == before
    assert cli(*args, "--overwrite").exit_code == 0
    assert frames_by_log(out) == {logs["val"]: "train"}


def test_a_split_file_manifest_without_digests_is_refused_and_others_read(raw, tmp_path):
    """Manifests written before the digests were recorded: one with split files cannot vouch for their
    contents (refused by name), one without split files is added to as before."""
    root, logs = raw / "av2" / "sensor", logs_of(raw)
    split_file, out = tmp_path / "train.txt", tmp_path / "out"
    split_file.write_text(logs["train"] + "\n")
    prepare("av2", root, out, TargetOptions(), split_files={"train": split_file})
    manifest = json.loads((out / "manifest.json").read_text())
    del manifest["parameters"]["split_file_sha256"]
    (out / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match="no digest of its --split-file contents.*train.txt.*--overwrite"):
        prepare("av2", root, out, TargetOptions(), split_files={"train": split_file})
    plain = tmp_path / "plain"
    prepare("av2", root, plain, TargetOptions())
    manifest = json.loads((plain / "manifest.json").read_text())
    assert "split_file_sha256" not in manifest["parameters"]
    assert prepare("av2", root, plain, TargetOptions())["logs_already_done"] == 2


def test_another_root_or_version_is_refused(raw, tmp_path):
    root = raw / "av2" / "sensor"
    out = tmp_path / "out"
    prepare("av2", root, out, TargetOptions())
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    before = files(out)
    result = cli("prepare", "--dataset", "av2", "--root", copy, "--out", out)
    said = one_error_line(result, "--root", str(copy))
    assert str(root) in said and files(out) == before
    # AV2 has no versions: --version means nothing to it
    assert prepare("av2", root, out, TargetOptions(), version="v1.0-mini")["logs_already_done"] == 2
    scenes = tmp_path / "scenes"
    prepare("nuscenes", raw / "nuscenes", scenes, TargetOptions(), version="v1.0-mini")
    before = files(scenes)
    result = cli("prepare", "--dataset", "nuscenes", "--root", raw / "nuscenes", "--version", "v1.0-trainval",
                 "--out", scenes)  # fmt: skip
    one_error_line(result, "--version v1.0-mini (now v1.0-trainval)")
    assert files(scenes) == before


# An --overwrite run interrupted while its output moves in (issue 59's review): OUT then holds the earlier
# output whole or the new one whole, never a mix, never no manifest.


def failing_replace(at: int, error: BaseException, calls: list[int], for_good: bool = False):
    """pipeline.manifest's os with a replace that raises `error` at its `at`-th call (and every later one
    `for_good`), counting in `calls`, and renames otherwise."""
    import os

    def replace(source, target):
        calls.append(1)
        if len(calls) == at or (for_good and len(calls) > at):
            raise error
        os.replace(source, target)

    return types.SimpleNamespace(replace=replace)


def written(folder: Path) -> dict[str, bytes]:
    """The files `cli prepare` writes in `folder`, by path, with their bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in output_folder.written_files(folder)}


@pytest.fixture(scope="module")
def outputs(raw, tmp_path_factory) -> dict[str, Path]:
    """An earlier output (both logs) with a file of the user's, and a complete staged --overwrite output
    (the training log alone, other path points), each to be copied."""
    root, logs = raw / "av2" / "sensor", logs_of(raw)
    base = tmp_path_factory.mktemp("outputs")
    prepare("av2", root, base / "old", TargetOptions())
    (base / "old" / "notes.txt").write_text("mine\n")
    (base / "one_log.txt").write_text(logs["train"] + "\n")
    prepare("av2", root, base / "new", TargetOptions(path_points=20),
            split_files={"train": base / "one_log.txt"})  # fmt: skip
    return {"old": base / "old", "new": base / "new", "split_file": base / "one_log.txt", "root": root}


def staged(outputs: dict[str, Path], out: Path) -> None:
    shutil.copytree(outputs["old"], out)
    shutil.copytree(outputs["new"], out / output_folder.STAGE)


def test_moving_in_interrupted_at_any_file_leaves_the_old_or_the_new_output_whole(
    outputs, tmp_path, monkeypatch
):
    old, new = files(outputs["old"]), written(outputs["new"])
    moves = len(written(outputs["old"])) + len(new)  # each earlier file set aside, each new one moved in
    for at in range(1, moves + 1):
        out = tmp_path / f"out{at}"
        staged(outputs, out)
        calls: list[int] = []
        # killed at the at-th rename: nothing of the run's own runs after it
        with monkeypatch.context() as patch:
            patch.setattr(output_folder, "os", failing_replace(at, KeyboardInterrupt(), calls))
            with pytest.raises(KeyboardInterrupt):
                output_folder.move_in(out / output_folder.STAGE, out)
        assert len(calls) == at
        assert (out / output_folder.STAGE).is_dir()
        # a run without --overwrite is refused in one line, and changes nothing
        before = files(out)
        with pytest.raises(
            ValueError, match=r"interrupted `cli prepare --overwrite` was replacing.*--overwrite"
        ):
            prepare("av2", outputs["root"], out, TargetOptions())
        assert files(out) == before
        # the next --overwrite run first puts back the earlier output, whole, with the user's file
        said = output_folder.recover_overwrite(out)
        assert said == f"{out}: put back the earlier output that an interrupted `cli prepare --overwrite` " \
                       "was replacing", at  # fmt: skip
        assert files(out) == old, at
    # killed after the new manifest moved in, while the earlier output is deleted: the new output stays
    out = tmp_path / "cleanup"
    staged(outputs, out)
    with monkeypatch.context() as patch:
        patch.setattr(output_folder, "remove_output", mock.Mock(side_effect=KeyboardInterrupt))
        with pytest.raises(KeyboardInterrupt):
            output_folder.move_in(out / output_folder.STAGE, out)
    assert written(out) == new
    assert output_folder.recover_overwrite(out).endswith(
        "finished the clean-up of an interrupted `cli prepare --overwrite` (its output is whole)"
    )
    assert written(out) == new and (out / "notes.txt").is_file() and not (out / output_folder.STAGE).exists()


@pytest.mark.parametrize("at", [3, 20])  # setting the earlier files aside; moving the new ones in
def test_an_overwrite_interrupted_while_moving_in_puts_the_earlier_output_back(outputs, tmp_path, monkeypatch,
                                                                               at):  # fmt: skip
    out = tmp_path / "out"
    shutil.copytree(outputs["old"], out)
    before = files(out)
    args = dict(overwrite=True, split_files={"train": outputs["split_file"]})
    calls: list[int] = []
    with monkeypatch.context() as patch:
        patch.setattr(output_folder, "os", failing_replace(at, KeyboardInterrupt(), calls))
        with pytest.raises(KeyboardInterrupt):
            prepare("av2", outputs["root"], out, TargetOptions(path_points=20), **args)
    assert files(out) == before  # at once, by the run itself
    # a rename that fails for good: the folder is left to the next run, which says what it did
    with monkeypatch.context() as patch:
        patch.setattr(output_folder, "os", failing_replace(at, OSError("disk gone"), [], for_good=True))
        with pytest.raises(OSError, match="disk gone"):
            prepare("av2", outputs["root"], out, TargetOptions(path_points=20), **args)
    assert "manifest.json" not in files(out)  # the first rename failed, and so did putting it back
    said = one_error_line(cli("prepare", "--dataset", "av2", "--root", outputs["root"], "--out", out),
                          str(out / output_folder.STAGE), "--overwrite")  # fmt: skip
    assert "was replacing" in said
    result = cli("prepare", "--dataset", "av2", "--root", outputs["root"], "--out", out, "--overwrite",
                 "--path-points", 20, "--split-file", f"train={outputs['split_file']}")  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "put back the earlier output that an interrupted `cli prepare --overwrite` was replacing" in \
        result.output  # fmt: skip
    assert written(out).keys() == written(outputs["new"]).keys()
    assert frames_by_log(out) == frames_by_log(outputs["new"]) and (out / "notes.txt").is_file()
    assert not (out / output_folder.STAGE).exists()


def test_an_overwrite_killed_while_preparing_is_named_by_the_next_run(outputs, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(outputs["old"], out)
    shutil.copytree(outputs["new"] / "frames", out / output_folder.STAGE / "frames")  # killed part way
    before = files(out)
    result = cli("prepare", "--dataset", "av2", "--root", outputs["root"], "--out", out)
    said = one_error_line(result, str(out / output_folder.STAGE), "--overwrite", "earlier output is whole")
    assert (
        f"delete {out / output_folder.STAGE} to add to the earlier output" in said and files(out) == before
    )
    result = cli("prepare", "--dataset", "av2", "--root", outputs["root"], "--out", out, "--overwrite")
    assert result.exit_code == 0, result.output
    assert "removed the unfinished output of an interrupted `cli prepare --overwrite`" in result.output
    assert frames_by_log(out) == frames_by_log(outputs["old"]) and not (out / output_folder.STAGE).exists()
