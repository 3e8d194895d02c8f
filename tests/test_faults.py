"""Faults: kill -9 in `cli prepare` and `cli train`, damaged and crafted checkpoints, corrupt and stale
inputs (each a one-line error naming the file, earlier output left as it was), the metric's version.

The data: a synthetic AV2 split without sensors (4 logs) and the toy prepared dataset of
test_baselines_train.py, so that none of this needs ../shared/data.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.feather as feather
import pyarrow.parquet as pq
import pytest
import torch
from test_baselines_train import write_toy_dataset
from typer.testing import CliRunner

from baselines.checkpoint import load_checkpoint
from baselines.run_folder import logged_lines
from benchmark.metric.params import METRIC_VERSION, MetricParams
from benchmark.score import score_pairs
from cli import app
from pipeline.io import SCHEMA_VERSION
from pipeline.lane_graph import LaneGraph
from pipeline.prepare import prepare
from pipeline.targets import TargetOptions

REPO = Path(__file__).resolve().parents[1]
TRAIN = (
    "--preset tiny --modality lidar --epochs 3 --batch-size 2 --path-points 10 --no-aux-seg "
    "--set train.threads=1 --set train.log_every=1 --set train.val_split=train"
).split()
STEPS_PER_EPOCH = 6  # 12 toy frames, 2 per step
PARAMETERS = {"bev_range": "30x60", "path_points": 30, "piece_points": 20, "max_paths": 256,
              "resolution": 0.15, "line_width": 5, "frame_stride": 1, "split": None}  # fmt: skip


def cli(*args: object):
    return CliRunner().invoke(app, [str(a) for a in args])


def one_error_line(result, *names: str) -> str:
    """The command failed with exit code 1 and one `error:` line naming `names`, no traceback."""
    assert result.exit_code == 1, result.output
    errors = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "Traceback" not in result.output, result.output
    assert all(name in errors[0] for name in names), errors[0]
    return errors[0]


def files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def wait_for(condition, process: subprocess.Popen, seconds: float = 90) -> None:
    end = time.monotonic() + seconds
    while not condition():
        assert process.poll() is None, "the process ended before it could be killed"
        assert time.monotonic() < end, "timed out"
        time.sleep(0.002)


# ---------------------------------------------------------------------------------------------- prepare


@pytest.fixture(scope="module")
def synth_av2(tmp_path_factory) -> tuple[Path, Path]:
    """(raw AV2 root, its uninterrupted preparation): 4 logs x 20 frames, no sensors."""
    from pipeline.synth import synth

    raw = tmp_path_factory.mktemp("faults_raw")
    synth(
        raw,
        logs=4,
        frames_per_log=20,
        seed=0,
        sensors=False,
        frame_period=0.5,
        worlds=1,
        val_frames_per_log=20,
        val_frame_period=0.5,
    )
    out = tmp_path_factory.mktemp("faults_prepared") / "av2"
    prepare("av2", raw / "av2" / "sensor", out, TargetOptions())
    return raw / "av2" / "sensor", out


def test_prepare_killed_after_its_first_shard_then_rerun_equals_an_uninterrupted_run(synth_av2, tmp_path):
    root, straight = synth_av2
    out = tmp_path / "out"
    command = [sys.executable, "-m", "cli", "prepare", "--dataset", "av2", "--root", root, "--out", out]
    process = subprocess.Popen(command, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wait_for(lambda: any((out / "frames").glob("*.parquet")), process)
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert not (out / "manifest.json").exists()  # killed mid-run
    shards = sorted(out.glob("*/*.parquet"))
    assert len(list(out.glob("frames/*.parquet"))) < 4
    for shard in shards:  # no half-written shard: every one reads
        pq.read_table(shard)
    assert prepare("av2", root, out, TargetOptions())["logs_already_done"] >= 1
    mine, theirs = files(out), files(straight)
    shard_names = sorted(name for name in theirs if name.endswith(".parquet"))
    assert sorted(name for name in mine if name.endswith(".parquet")) == shard_names
    for name in shard_names:
        assert mine[name] == theirs[name], name  # byte for byte
    manifests = [
        {k: v for k, v in json.loads(m["manifest.json"]).items() if k != "last_run"} for m in (mine, theirs)
    ]
    assert manifests[0] == manifests[1]  # apart from the timings and counts of the last run


def test_preparing_into_a_folder_made_with_other_options_is_refused(synth_av2, tmp_path):
    root, straight = synth_av2
    out = tmp_path / "out"
    shutil.copytree(straight, out)
    result = cli("prepare", "--dataset", "av2", "--root", root, "--out", out, "--path-points", 20)
    one_error_line(result, str(out), "prepared with other options", "--overwrite")
    assert files(out) == files(straight)


def test_corrupt_raw_inputs_are_named_in_one_line_and_earlier_shards_stay(synth_av2, tmp_path):
    root, straight = synth_av2
    raw, out = tmp_path / "sensor", tmp_path / "out"
    shutil.copytree(root, raw)
    shutil.copytree(straight, out)
    before = files(out)
    log = sorted((raw / "train").iterdir())[1]
    (map_file,) = (log / "map").glob("log_map_archive_*.json")
    text = map_file.read_text()
    map_file.write_text(text[: len(text) // 2])  # a truncated map JSON
    result = cli("prepare", "--dataset", "av2", "--root", raw, "--out", out, "--overwrite")
    one_error_line(result, str(map_file), "cannot be read")
    assert files(out) == before
    map_file.write_text(text)
    poses = log / "city_SE3_egovehicle.feather"
    feather.write_feather(feather.read_table(poses).slice(0, 0), poses)  # a log with no poses
    result = cli("prepare", "--dataset", "av2", "--root", raw, "--out", out, "--overwrite")
    one_error_line(result, str(poses), "no pose rows")
    assert files(out) == before


def test_damaged_parquet_shards_are_named_in_one_line(synth_av2, tmp_path):
    _, straight = synth_av2
    data = tmp_path / "data"
    shutil.copytree(straight, data)
    out = tmp_path / "roundtrip.json"
    assert cli("roundtrip", "--data", data, "--via", "path", "--out", out).exit_code == 0
    before = out.read_bytes()
    assert json.loads(before)["metric_version"] == METRIC_VERSION
    shard = sorted((data / "paths").glob("*.parquet"))[1]
    good = shard.read_bytes()
    table = pq.read_table(shard)
    index = table.schema.get_field_index("path_index")
    pq.write_table(table.set_column(index, "path_index", pc.cast(table["path_index"], pa.string())), shard)
    one_error_line(cli("roundtrip", "--data", data, "--via", "path", "--out", out), str(shard), "path_index")
    shard.write_bytes(good[: len(good) // 2])  # truncated
    one_error_line(cli("roundtrip", "--data", data, "--via", "path", "--out", out), str(shard))
    assert out.read_bytes() == before
    graphs = sorted((data / "graphs").glob("*.parquet"))[0]
    graphs.write_bytes(graphs.read_bytes()[:100])
    one_error_line(cli("score", "--pred", graphs.parent, "--gt", data, "--out", out), "graphs")
    assert out.read_bytes() == before


# ---------------------------------------------------------------------------------------------- train


@pytest.fixture(scope="module")
def toy_run(tmp_path_factory) -> tuple[Path, Path]:
    """(toy prepared dataset with its target parameters in manifest.json, a finished 3-epoch run on it)."""
    root = tmp_path_factory.mktemp("faults_toy")
    data = write_toy_dataset(root, frames=12)
    manifest = json.loads((data / "manifest.json").read_text())
    (data / "manifest.json").write_text(
        json.dumps({**manifest, "schema_version": SCHEMA_VERSION, "parameters": PARAMETERS})
    )
    run = root / "straight"
    result = cli("train", "--data", data, "--out", run, *TRAIN)
    assert result.exit_code == 0, result.output
    return data, run


def same_weights(a: Path, b: Path) -> bool:
    first, second = load_checkpoint(a / "checkpoint.pt"), load_checkpoint(b / "checkpoint.pt")
    return first["step"] == second["step"] and all(
        torch.equal(tensor, second["model"][name]) for name, tensor in first["model"].items()
    )


def logged_steps(run: Path) -> list[int]:
    return [json.loads(line)["step"] for line in logged_lines(run / "log.jsonl")]


def test_train_killed_mid_epoch_then_resumed_ends_with_the_same_weights(toy_run, tmp_path):
    data, straight = toy_run
    run = tmp_path / "run"
    command = [sys.executable, "-m", "cli", "train", "--data", data, "--out", run, *TRAIN]
    process = subprocess.Popen(command, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    log = run / "log.jsonl"
    wait_for(lambda: log.is_file() and STEPS_PER_EPOCH + 1 in logged_steps(run), process)
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert load_checkpoint(run / "checkpoint.pt")["epoch"] == 1
    assert max(logged_steps(run)) > STEPS_PER_EPOCH  # killed mid-epoch 2
    result = cli("train", "--out", run, "--resume")
    assert result.exit_code == 0, result.output
    assert logged_steps(run) == list(range(1, 3 * STEPS_PER_EPOCH + 1))
    assert same_weights(run, straight)  # bitwise


def test_a_damaged_checkpoint_is_named_and_resume_falls_back_to_the_previous(toy_run, tmp_path):
    _, straight = toy_run
    truncated, flipped = tmp_path / "truncated", tmp_path / "flipped"
    for run in (truncated, flipped):
        shutil.copytree(straight, run)
    path = truncated / "checkpoint.pt"
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    one_error_line(cli("eval", "--run", truncated, "--device", "cpu"), str(path), "truncated")
    # one bit of a weight flipped: torch loads such a file without a word; the sha256 does not match
    name, weight = max(
        load_checkpoint(straight / "checkpoint.pt")["model"].items(), key=lambda i: i[1].numel()
    )
    content = bytearray((flipped / "checkpoint.pt").read_bytes())
    at = bytes(content).find(weight.numpy().tobytes()[:64])
    assert at > 0
    content[at + 5] ^= 0x10
    (flipped / "checkpoint.pt").write_bytes(bytes(content))
    assert not torch.equal(torch.load(flipped / "checkpoint.pt", weights_only=True)["model"][name], weight)
    one_error_line(cli("eval", "--run", flipped, "--device", "cpu"), "checkpoint.pt", "corrupted")
    assert not (flipped / "metrics.json").exists()

    result = cli("train", "--out", truncated, "--resume")  # epoch 3 again, from checkpoint.prev.pt
    assert result.exit_code == 0, result.output
    (notice,) = [line for line in result.output.splitlines() if "resuming from" in line]  # one line
    assert notice.startswith(f"{path}: unreadable") and notice.endswith(
        "; resuming from checkpoint.prev.pt (epoch 2)"
    )
    assert same_weights(truncated, straight) and (truncated / "checkpoint.bad.pt").is_file()
    assert load_checkpoint(truncated / "checkpoint.prev.pt")["epoch"] == 2


class RunsCode:
    """Unpickled, this object would run os.mkdir(marker): any code could stand there."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return os.mkdir, (self.marker,)


def test_a_checkpoint_whose_pickle_would_run_code_is_refused(toy_run, tmp_path):
    _, straight = toy_run
    run, marker = tmp_path / "run", tmp_path / "code_ran"
    shutil.copytree(straight, run)
    (run / "checkpoint.prev.pt").unlink()
    checkpoint = load_checkpoint(straight / "checkpoint.pt")
    torch.save({**checkpoint, "payload": RunsCode(marker)}, run / "checkpoint.pt")
    one_error_line(
        cli("eval", "--run", run, "--device", "cpu"), "checkpoint.pt: refused", "GLOBAL posix.mkdir"
    )
    one_error_line(cli("train", "--out", run, "--resume"), "checkpoint.pt: refused")
    assert not marker.exists()
    torch.load(run / "checkpoint.pt", weights_only=False)  # what loading it unsafely would do
    assert marker.is_dir()


def test_stale_data_is_refused_by_name(toy_run, tmp_path):
    data, straight = toy_run
    run, other = tmp_path / "run", tmp_path / "data"
    shutil.copytree(straight, run)
    shutil.copytree(data, other)
    assert cli("eval", "--run", run, "--data", other, "--device", "cpu", "--no-floor").exit_code == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["metric_version"] == METRIC_VERSION and metrics["effective_batch_size"] == 2
    before = files(run)
    manifest = json.loads((other / "manifest.json").read_text())
    stale = {**manifest, "parameters": {**PARAMETERS, "path_points": 20}}
    (other / "manifest.json").write_text(json.dumps(stale))
    error = one_error_line(cli("eval", "--run", run, "--data", other, "--device", "cpu"), "stale data")
    assert "path_points=20" in error and "path_points=30" in error and str(other / "manifest.json") in error
    predictions = run / "predictions.parquet"
    one_error_line(cli("score", "--pred", predictions, "--gt", other), "stale data", "path_points=20")
    one_error_line(cli("train", "--out", run, "--data", other, "--resume"), "stale data", "path_points=20")
    assert files(run) == before  # nothing of the run was touched
    (other / "manifest.json").write_text(json.dumps({**manifest, "schema_version": SCHEMA_VERSION + 1}))
    one_error_line(cli("score", "--pred", predictions, "--gt", other), f"schema_version={SCHEMA_VERSION + 1}")
    (other / "manifest.json").write_text(json.dumps(manifest))
    scored = cli("score", "--pred", predictions, "--gt", other, "--json")
    assert json.loads(scored.stdout)["metric_version"] == 1


def test_bad_training_inputs_are_named_in_one_line(toy_run, tmp_path):
    data, straight = toy_run
    other = tmp_path / "data"
    shutil.copytree(data, other)
    root = Path(json.loads((other / "manifest.json").read_text())["root"])
    frame = pq.read_table(next((other / "frames").glob("*.parquet"))).to_pylist()[5]
    image = tmp_path / "raw" / frame["cameras"][1]["image_path"]
    shutil.copytree(root, tmp_path / "raw")
    manifest = json.loads((other / "manifest.json").read_text())
    (other / "manifest.json").write_text(json.dumps({**manifest, "root": str(tmp_path / "raw")}))
    image.unlink()  # a missing camera image, read in a DataLoader worker process
    args = ["train", "--data", other, "--out", tmp_path / "camera", *TRAIN, "--modality", "camera",
            "--set", "data.num_workers=1"]  # fmt: skip
    one_error_line(cli(*args), str(image), "missing")
    args = ["train", "--data", other, "--out", tmp_path / "empty", *TRAIN, "--set", "train.train_split=val"]
    one_error_line(cli(*args), str(other), "no frames in split 'val'")
    one_error_line(cli("eval", "--run", straight, "--split", "val", "--device", "cpu"), "no frames in split")
    # predicted frames that are not in the ground truth are refused, not scored
    pred = tmp_path / "pred.parquet"
    rows = [{"frame_id": "av2/elsewhere/1", "x": [0.0, 0.0], "y": [0.0, 5.0], "src": [0], "dst": [1]}]
    pq.write_table(pa.Table.from_pylist(rows), pred)
    out = tmp_path / "scores.json"
    out.write_text("{}")
    one_error_line(cli("score", "--pred", pred, "--gt", other, "--out", out), "av2/elsewhere/1", "not in the")
    assert out.read_text() == "{}"


class InfiniteGradient(torch.autograd.Function):
    """The loss as it is, its gradient infinite: what fp16 gradients beyond its range do to the scaler."""

    @staticmethod
    def forward(ctx, loss):
        return loss.clone()

    @staticmethod
    def backward(ctx, grad):
        return grad * float("inf")


class OverflowingFrom(torch.nn.Module):
    """The model's loss, whose gradients overflow from its `first` call on."""

    def __init__(self, loss: torch.nn.Module, first: int):
        super().__init__()
        self.loss, self.first, self.count = loss, first, 0

    def forward(self, outputs, targets):
        losses = self.loss(outputs, targets)
        self.count += 1
        if self.count >= self.first:
            losses = {**losses, "loss": InfiniteGradient.apply(losses["loss"])}
        return losses


def stopped_by_fp16_overflows(tmp_path, monkeypatch, first: int, checkpoint_every: int, max_bad_steps: int):
    """The one line that ends a toy fp16 run on the CPU (12 frames, 6 steps an epoch, 3 epochs): the
    GradScaler itself (scale 4, halved at each overflow), gradients infinite from step `first` on while
    the loss stays finite."""
    from test_baselines_train import toy_config

    from baselines import train as train_module
    from baselines.models import build
    from baselines.train import TrainingStopped, train

    def overflowing(config):
        built = build(config)
        built.loss = OverflowingFrom(built.loss, first=first)
        return built

    scaler = torch.amp.GradScaler
    monkeypatch.setattr(train_module, "build", overflowing)
    monkeypatch.setattr(train_module, "amp_settings", lambda device, enabled: (None, True))
    monkeypatch.setattr(torch.amp, "GradScaler", lambda device, enabled: scaler("cpu", init_scale=4.0))
    data = write_toy_dataset(tmp_path, frames=12)
    config = toy_config("lidar", epochs=3)
    config.train.checkpoint_every, config.train.max_bad_steps = checkpoint_every, max_bad_steps
    with pytest.raises(TrainingStopped) as stopped:
        train(config, data, tmp_path / "run")
    return str(stopped.value)


def test_fp16_overflows_that_never_end_stop_the_run_in_one_line(tmp_path, monkeypatch):
    """Gradients infinite from step 3 on: the scaler backs off at scales 4 and 2; at 1 and below the
    overflows count toward --max-bad-steps 3, so step 7 ends the run (before, it skipped every step to the
    end and finished)."""
    message = stopped_by_fp16_overflows(tmp_path, monkeypatch, first=3, checkpoint_every=2, max_bad_steps=3)
    assert message.startswith("step 7: 3 steps in a row with a non-finite loss or gradient norm")
    assert "not finite at this step: grad_norm (fp16 gradients overflowing at a loss scale of 0.25" in message
    # step 6's checkpoint was saved amid the overflows: its weights are step 2's, its loss scale the 0.25 they
    # brought it down to, which a resume under fp16 would go on from (before, it was called the last good one)
    checkpoint = tmp_path / "run" / "checkpoint.pt"
    assert load_checkpoint(checkpoint)["scaler"]["scale"] == 0.25
    assert (f"the last checkpoint is {checkpoint} (step 6; its weights are good, its loss scale 0.25, at "
            "which fp16 overflows at once): --resume from it with --set train.amp=false (fp32) or another "
            "--set train.lr=...") in message  # fmt: skip
    assert "good checkpoint" not in message and "\n" not in message
    skipped = [r for r in map(json.loads, logged_lines(tmp_path / "run" / "log.jsonl")) if "skipped" in r]
    assert [(r["step"], r["skipped"]) for r in skipped] == [(n, "fp16 overflow") for n in range(3, 8)]
    assert all(np.isfinite(r["loss"]) and not np.isfinite(r["grad_norm"]) for r in skipped)


def test_an_fp16_checkpoint_saved_before_the_overflows_began_is_named_the_last_good_one(
    tmp_path, monkeypatch
):
    """Overflows from step 7 on, after the epoch-end checkpoint of step 6 (saved at the scale of 4 the
    steps before applied at): scales 4 and 2 are backed off, the overflow at 1 is --max-bad-steps 1's.
    Before, every fp16 checkpoint was described as saved amid the overflows."""
    message = stopped_by_fp16_overflows(tmp_path, monkeypatch, first=7, checkpoint_every=0, max_bad_steps=1)
    checkpoint = tmp_path / "run" / "checkpoint.pt"
    assert load_checkpoint(checkpoint)["scaler"]["scale"] == 4.0
    assert message.startswith("step 9: 1 steps in a row with a non-finite loss or gradient norm"), message
    assert message.endswith(
        f"none of them applied; the last good checkpoint is {checkpoint} (step 6): --resume from it with "
        "--set train.amp=false (fp32) or another --set train.lr=..."
    )


# ---------------------------------------------------------------------------------------------- metric


def graph(points: list[tuple[float, float]], edges: list[tuple[int, int]]) -> LaneGraph:
    xy = np.array(points, np.float32).reshape(-1, 2)
    pairs = np.array(edges, np.int32).reshape(-1, 2)
    return LaneGraph(xy[:, 0], xy[:, 1], pairs[:, 0], pairs[:, 1])


# A fork, a merge beside a lane the prediction drives the wrong way with a spurious lane, a prediction
# on an empty frame and a missed lane.
FORK = graph([(0, -12), (0, 0), (-3.5, 12), (4, 12)], [(0, 1), (1, 2), (1, 3)])
FORK_PRED = graph([(0.2, -11), (0.1, 0.3), (-3.1, 11.5)], [(0, 1), (1, 2)])
MERGE = graph([(-6, -10), (6, -10), (0, 2), (0, 14), (-6, 14), (-6, -10)], [(0, 2), (1, 2), (2, 3), (4, 5)])
MERGE_PRED = graph(
    [(-5.8, -9.7), (0.3, 1.8), (0.1, 14), (-6.2, -10), (-6.0, 14), (9, 0), (9, 8)],
    [(0, 1), (1, 2), (3, 4), (5, 6)],
)
LONE = graph([(2, -5), (2, 5)], [(0, 1)])
FRAMES = [(FORK_PRED, FORK), (MERGE_PRED, MERGE), (LONE, LaneGraph.empty()), (LaneGraph.empty(), LONE)]


def prf(precision: float, recall: float, f1: float) -> dict:
    return {"precision": precision, "recall": recall, "f1": f1}


# Every digit of the metric on the frames above, per METRIC_VERSION. A change of the metric that moves
# one of them must bump benchmark.metric.params.METRIC_VERSION and add its values here.
GOLDEN = {
    1: {
        "greedy": {
            "directed": {"topo": prf(0.5389237847801223, 0.404024262374012, 0.4618245624003253),
                         "junction_topo": prf(0.9901960784313726, 0.7524752475247525, 0.8551217066785496)},
            "undirected": {"topo": prf(0.7834320366233587, 0.5584314047777214, 0.652067921759093),
                           "junction_topo": prf(0.9900990099009901, 0.6666666666666666, 0.7968127490039841)},
            "miou": 0.41759554140127386,
        },
        "optimal": {
            "directed": {"topo": prf(0.5560359643548854, 0.40914516192654987, 0.47141291614239206),
                         "junction_topo": prf(0.9901960784313726, 0.7524752475247525, 0.8551217066785496)},
            "undirected": {"topo": prf(0.7923029989605197, 0.5638042800191407, 0.65880307378343),
                           "junction_topo": prf(1.0, 0.6733333333333333, 0.8047808764940239)},
            "miou": 0.41759554140127386,
        },
    }
}  # fmt: skip


@pytest.mark.parametrize("matching", ["greedy", "optimal"])
def test_golden_metric_values_pin_the_metric_version(matching):
    assert METRIC_VERSION in GOLDEN, f"METRIC_VERSION {METRIC_VERSION}: add its golden values here"
    result = score_pairs(FRAMES, MetricParams(matching=matching))
    assert result["metric_version"] == METRIC_VERSION and result["frames"] == 4
    scores = {key: result[key] for key in ("directed", "undirected", "miou")}
    assert scores == GOLDEN[METRIC_VERSION][matching], "the metric changed: bump METRIC_VERSION"
