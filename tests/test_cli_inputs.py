"""Bad command-line input (issue 30): one line naming the option, file or folder and what was expected,
before any work starts and with nothing written; `cli score --split`.

The data: a tiny synthetic dataset without sensors (2 logs x 3 frames, one train and one val), prepared
for AV2, so that none of this needs ../shared/data.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from cli import app
from pipeline.io import read_table

REPO = Path(__file__).resolve().parents[1]


def cli(*args: object):
    return CliRunner().invoke(app, [str(a) for a in args])


def one_error_line(result, *words: str) -> str:
    """The command failed (click's usage error: 2, ours: 1) with one error line holding `words`, no
    traceback; the line."""
    assert result.exit_code in (1, 2), result.output
    errors = [line for line in result.output.splitlines() if line.lower().startswith("error:")]
    assert len(errors) == 1 and "Traceback" not in result.output, result.output
    assert all(word in errors[0] for word in words), errors[0]
    return errors[0]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> dict[str, Path]:
    """{"raw": synth output, "av2": its AV2 root, "nuscenes": its dataroot, "prepared": the AV2 root
    prepared with the default options}."""
    from pipeline.prepare import prepare
    from pipeline.synth import synth
    from pipeline.targets import TargetOptions

    raw = tmp_path_factory.mktemp("inputs_raw")
    synth(
        raw, logs=2, frames_per_log=3, seed=0, sensors=False, frame_period=1.0, worlds=2, val_frames_per_log=3
    )
    prepared = tmp_path_factory.mktemp("inputs_prepared") / "av2"
    prepare("av2", raw / "av2" / "sensor", prepared, TargetOptions())
    return {"raw": raw, "av2": raw / "av2" / "sensor", "nuscenes": raw / "nuscenes", "prepared": prepared}


@pytest.mark.parametrize(
    "option, value",
    [("--path-points", 0), ("--piece-points", 0), ("--path-points", 1)],
)
def test_prepare_point_counts_below_two_are_refused_not_a_segfault(tiny, tmp_path, option, value):
    """A subprocess: 0 points crashed the interpreter (numba, exit 139) before any message."""
    out = tmp_path / "out"
    command = [sys.executable, "-m", "cli", "prepare", "--dataset", "av2", "--root", str(tiny["av2"]),
               "--out", str(out), option, str(value)]  # fmt: skip
    done = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, (done.returncode, done.stderr)
    errors = [line for line in done.stderr.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1 and f"'{option}'" in errors[0] and "greater than or equal to 2" in errors[0], (
        done.stderr
    )
    assert not out.exists()


@pytest.mark.parametrize(
    "option, value, expected",
    [
        ("--frame-stride", 0, "greater than or equal to 1"),
        ("--resolution", 0, "x>0"),
        ("--resolution", -1, "x>0"),
        ("--workers", -3, "greater than or equal to 1"),
        ("--line-width", 0, "greater than or equal to 1"),
        ("--max-paths", 0, "greater than or equal to 1"),
        ("--dataset", "kitti", "'av2', 'nuscenes'"),
        ("--on-error", "ignore", "'fail', 'skip'"),
        ("--executor", "dask", "'local', 'ray'"),
    ],
)
def test_prepare_refuses_out_of_range_options_before_any_work(tiny, tmp_path, option, value, expected):
    out = tmp_path / "out"
    args = {"--dataset": "av2", "--root": tiny["av2"], "--out": out, option: value}
    one_error_line(cli("prepare", *(a for item in args.items() for a in item)), f"'{option}'", expected)
    assert not out.exists()


def test_prepare_a_resolution_without_one_raster_cell_is_refused(tiny, tmp_path):
    out = tmp_path / "out"
    error = one_error_line(cli("prepare", "--dataset", "av2", "--root", tiny["av2"], "--out", out,
                               "--resolution", 100), "--resolution 100", "--range 30x60")  # fmt: skip
    assert "raster" in error
    assert not out.exists()


@pytest.mark.parametrize("dataset, root", [("av2", "nuscenes"), ("nuscenes", "av2")])
def test_prepare_with_a_wrong_root_names_root_dataset_and_what_was_looked_for(tiny, tmp_path, dataset, root):
    out = tmp_path / "out"
    result = cli("prepare", "--dataset", dataset, "--root", tiny[root], "--out", out,
                 "--version", "v1.0-mini")  # fmt: skip
    error = one_error_line(result, str(tiny[root].resolve()))
    assert ("AV2 log" in error and "map/" in error) if dataset == "av2" else "v1.0-mini" in error
    assert not out.exists()  # no manifest of zero frames that a correct run would then be refused by


def test_prepare_a_split_without_logs_is_an_error(tiny, tmp_path):
    out = tmp_path / "out"
    (tiny["raw"] / "empty" / "val").mkdir(parents=True)
    result = cli(
        "prepare", "--dataset", "av2", "--root", tiny["raw"] / "empty", "--out", out, "--split", "val"
    )
    one_error_line(result, str((tiny["raw"] / "empty").resolve()), "AV2 log", "split val", "map/")
    assert not out.exists()


def test_prepare_refusal_names_only_the_differing_options(tiny, tmp_path):
    result = cli("prepare", "--dataset", "av2", "--root", tiny["av2"], "--out", tiny["prepared"],
                 "--path-points", 20, "--line-width", 3)  # fmt: skip
    error = one_error_line(
        result, str(tiny["prepared"]), "--path-points 30 (now 20)", "--line-width 5 (now 3)"
    )
    for other in ("piece", "max", "resolution", "range", "stride", "{"):
        assert other not in error, error


def test_roundtrip_refuses_out_of_range_options(tiny):
    cases = [
        ("--frame-stride", 0, "greater than or equal to 1"),
        ("--merge-radius", -1, "greater than or equal to 0"),
        ("--workers", -1, "greater than or equal to 0"),
        ("--via", "graph", "'path', 'piece'"),
    ]
    for option, value, expected in cases:
        result = cli("roundtrip", "--data", tiny["prepared"], "--via", "path", option, value)
        one_error_line(result, f"'{option}'", expected)


@pytest.mark.parametrize(
    "args, words",
    [
        (["--logs", 0], ["'--logs'", "greater than or equal to 1"]),
        (["--logs", 35], ["--logs", "1 to 34"]),
        (["--worlds", 9], ["'--worlds'", "less than or equal to 4"]),
        (["--frames-per-log", 0], ["'--frames-per-log'", "greater than or equal to 1"]),
        (["--seed", -1], ["'--seed'", "greater than or equal to 0"]),
        (["--val-worlds", 5], ["--val-worlds 5", "--worlds 4"]),
        (["--worlds", 2, "--val-worlds", 2], ["--val-worlds 2", "--worlds 2"]),
        (["--frame-period", 0.03], ["--frame-period 0.03", "0.02"]),
        (["--frame-period", 0], ["'--frame-period'", "greater than or equal to 0.02"]),
    ],
)
def test_synth_errors_are_one_line_and_write_nothing(tmp_path, args, words):
    out = tmp_path / "raw"
    one_error_line(cli("synth", "--out", out, "--no-sensors", *args), *words)
    assert not out.exists()


def test_train_refuses_bad_options_in_one_line(tiny, tmp_path):
    out = tmp_path / "run"
    cases = [
        (["--path-points", 7], ["'--path-points'", "'10', '20', '30', '40'"]),
        (["--set", "train.epochs=abc"], ["--set train.epochs=abc", "an integer"]),
        (["--set", "train.lr=fast"], ["--set train.lr=fast", "a number"]),
        (["--set", "train.epochs=1.5"], ["--set train.epochs=1.5", "an integer"]),
        (["--set", "encoder.kernel_size=3,x"], ["--set encoder.kernel_size=3,x", "integers"]),
        (["--set", "train.epochs"], ["--set train.epochs", "section.field=value"]),
        (["--set", "optimiser.lr=1"], ["--set optimiser.lr=1", "encoder, decoder, data, train"]),
        (["--epochs", 0], ["'--epochs'", "greater than or equal to 1"]),
        (["--batch-size", 0], ["'--batch-size'", "greater than or equal to 1"]),
        (["--bezier-points", 1], ["'--bezier-points'", "0 (polyline)", "x>=2"]),
        (["--model", "detr"], ["'--model'", "'lanegap'"]),
        (["--preset", "huge"], ["'--preset'", "'paper', 'tiny'"]),
        (["--modality", "radar"], ["'--modality'", "'camera', 'lidar', 'fusion'"]),
    ]
    for args, words in cases:
        one_error_line(
            cli("train", "--data", tiny["prepared"], "--out", out, "--preset", "tiny", *args), *words
        )
        assert not out.exists(), args
    one_error_line(cli("train", "--out", tmp_path / "nope", "--resume"), str(tmp_path / "nope"), "cli train")


def test_eval_refuses_a_bad_device_and_a_missing_run_in_one_line(tmp_path):
    import torch

    one_error_line(cli("eval", "--run", tmp_path, "--device", "foo"), "'--device'", "'cpu', 'cuda'")
    one_error_line(cli("eval", "--run", tmp_path / "nope"), str(tmp_path / "nope"), "no such folder")
    one_error_line(cli("eval", "--run", tmp_path), str(tmp_path), "config.json", "cli train")
    if not torch.cuda.is_available():
        one_error_line(cli("eval", "--run", tmp_path, "--device", "cuda"), "--device cuda", "CUDA")


def write_predictions(tiny, path: Path, frame_ids: list[str]) -> Path:
    """The ground truth of `frame_ids` as a prediction file."""
    graphs = read_table(tiny["prepared"], "graphs")
    pq.write_table(graphs.filter(pc.field("frame_id").isin(frame_ids)), path)
    return path


def frames_of(tiny, split: str) -> list[str]:
    frames = read_table(tiny["prepared"], "frames", columns=["frame_id", "split"]).to_pylist()
    return sorted(f["frame_id"] for f in frames if f["split"] == split)


def test_score_scores_the_split_of_the_predicted_frames(tiny, tmp_path):
    """Predictions equal to the ground truth of the val split score 1.0 (the train frames are not
    counted as empty predictions); a val frame without a prediction is an empty one."""
    val = frames_of(tiny, "val")
    assert len(val) == 3 and len(frames_of(tiny, "train")) == 3
    pred = write_predictions(tiny, tmp_path / "pred.parquet", val)
    result = json.loads(cli("score", "--pred", pred, "--gt", tiny["prepared"], "--json").stdout)
    assert result["directed"]["topo"]["f1"] == 1.0 and result["splits"] == ["val"]
    assert (result["frames"], result["frames_predicted"], result["frames_missing"]) == (3, 3, 0)
    table = cli("score", "--pred", pred, "--gt", tiny["prepared"], "--split", "val")
    assert table.exit_code == 0 and "split val: 3 frames scored, 3 predicted, 0 missing" in table.output

    fewer = write_predictions(tiny, tmp_path / "fewer.parquet", val[:2])
    result = json.loads(cli("score", "--pred", fewer, "--gt", tiny["prepared"], "--json").stdout)
    assert (result["frames"], result["frames_predicted"], result["frames_missing"]) == (3, 2, 1)
    assert result["directed"]["topo"]["precision"] == 1.0 and result["directed"]["topo"]["recall"] < 1.0

    one_error_line(cli("score", "--pred", pred, "--gt", tiny["prepared"], "--split", "train"),
                   str(pred), val[0], "'val'", "--split train")  # fmt: skip
    one_error_line(cli("score", "--pred", pred, "--gt", tiny["prepared"], "--split", "test"),
                   "--split test", "train, val")  # fmt: skip
    graph_file = write_predictions(tiny, tmp_path / "gt.parquet", val + frames_of(tiny, "train"))
    one_error_line(
        cli("score", "--pred", pred, "--gt", graph_file, "--split", "val"), "--split", str(graph_file)
    )
    whole = json.loads(cli("score", "--pred", pred, "--gt", graph_file, "--json").stdout)
    assert (whole["frames"], whole["frames_missing"], whole["splits"]) == (6, 3, None)  # no splits known


def test_every_command_says_what_it_wrote_and_json_is_one_line(tmp_path):
    """synth -> prepare -> roundtrip -> score from the command line: with --json stdout is one JSON line
    and the paths written go to stderr; without it, tables with headers and a `wrote` line."""
    raw, data = tmp_path / "raw", tmp_path / "prepared"
    tiny_synth = [
        "--logs",
        2,
        "--frames-per-log",
        2,
        "--val-frames-per-log",
        2,
        "--worlds",
        2,
        "--no-sensors",
    ]
    runs = [
        ("synth", ["--out", raw, *tiny_synth], [raw / "av2/sensor"]),
        ("prepare", ["--dataset", "av2", "--root", raw / "av2/sensor", "--out", data], [data]),
        (
            "roundtrip",
            ["--data", data, "--via", "piece", "--out", tmp_path / "rt.json"],
            [tmp_path / "rt.json"],
        ),
    ]
    for name, args, wrote in runs:
        result = cli(name, *args, "--json")
        assert result.exit_code == 0, result.output
        lines = result.stdout.strip().splitlines()
        assert len(lines) == 1 and isinstance(json.loads(lines[0]), dict), result.stdout
        assert all(str(path) in result.stderr for path in wrote), result.stderr
    assert json.loads(cli("roundtrip", "--data", data, "--via", "piece", "--json").stdout)["frames"] == 4
    pred = tmp_path / "pred.parquet"
    pq.write_table(read_table(data, "graphs"), pred)
    table = cli("score", "--pred", pred, "--gt", data, "--out", tmp_path / "score.json", "--bootstrap", 0)
    assert table.exit_code == 0 and f"wrote {tmp_path / 'score.json'}" in table.stdout
    assert "metric" in table.stdout and "precision" in table.stdout  # the table's header
    assert "split train, val: 4 frames scored, 4 predicted, 0 missing" in table.stdout
