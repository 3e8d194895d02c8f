"""`cli train` started by the real launcher: `torchrun --standalone --nproc_per_node 2 -m cli train`, on
the CPU (gloo), a few steps of a tiny LiDAR LaneGAP on a toy prepared dataset."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
from test_baselines_train import toy_config, write_toy_dataset
from torch.utils.data import DistributedSampler
from typer.testing import CliRunner

from baselines.models import load_config
from baselines.train import train
from cli import app
from pipeline import io

REPO = Path(__file__).resolve().parents[1]
FRAMES, SEED = 8, toy_config().train.seed
# Without the lane head: its BatchNorm normalises each process's own frames under DDP (no SyncBatchNorm,
# as HDMapNet's), so 2 x 2 frames would not train exactly as 1 x 4.
TINY = (
    "--preset tiny --modality lidar --epochs 1 --batch-size 4 --path-points 10 --no-aux-seg "
    "--set train.threads=1 --set train.log_every=1 --set train.val_split=train "
    "--set decoder.lane_head_width=0 --set decoder.score_threshold=0.0"  # every path kept: scores above 0
)


def toy_with_one_sweep(root: Path) -> tuple[Path, list[int]]:
    """8 frames that share one LiDAR sweep (so that BatchNorm, which no process synchronises on the CPU,
    sees the same batch statistics however the batch is split) and differ in their number of lanes:
    rank 0's frames of the first step have one, the others two, so the loss normaliser matters."""
    data = write_toy_dataset(root, FRAMES)
    frames_path, paths_path = (next((data / table).glob("*.parquet")) for table in ("frames", "paths"))
    frames = pq.read_table(frames_path)
    sweep = pa.array([frames["lidar_path"][0].as_py()] * frames.num_rows, pa.string())
    pq.write_table(
        frames.set_column(frames.schema.get_field_index("lidar_path"), "lidar_path", sweep), frames_path
    )
    sampler = DistributedSampler(range(FRAMES), num_replicas=2, rank=0, shuffle=True, seed=SEED)
    one_lane = [f"av2/toy/{i}" for i in list(sampler)[:2]]  # the frames sort as av2/toy/0 ... 7
    paths = pq.read_table(paths_path).to_pylist()
    kept = [r for r in paths if r["frame_id"] not in one_lane or r["path_index"] == 0]
    pq.write_table(pa.Table.from_pylist(kept, io.SCHEMAS["paths"]), paths_path)
    lanes = [sum(r["frame_id"] == f"av2/toy/{i}" for r in kept) for i in range(FRAMES)]
    return data, lanes


def test_torchrun_two_processes_match_one_process(tmp_path):
    data, lanes = toy_with_one_sweep(tmp_path)
    run = tmp_path / "ddp"
    args = ["--data", str(data), "--out", str(run), *TINY.split(), "--json"]  # a summary line per process
    torchrun = [str(Path(sys.executable).with_name("torchrun")), "--standalone", "--nproc_per_node", "2"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run([*torchrun, "-m", "cli", "train", *args], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=120)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]

    # (a) rank 0 alone writes: one log line per step, the run's files and nothing else
    assert sorted(p.name for p in run.iterdir()) == [
        "best.pt", "checkpoint.pt", "config.json", "log.jsonl", "run.json", "tb", "val.jsonl"
    ]
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == [1, 2]  # 8 frames, 2 per process and step
    summaries = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    assert [s["steps"] for s in summaries] == [2, 2]  # both processes trained
    assert len(torch.load(run / "checkpoint.pt", weights_only=True)["rng"]) == 2

    # (b) the effective batch size, in the run's record and in metrics.json
    record = json.loads((run / "run.json").read_text())
    assert (record["world_size"], record["batch_per_process"], record["effective_batch_size"]) == (2, 2, 4)
    assert load_config(run / "config.json").train.batch_size == 4
    result = CliRunner().invoke(app, ["eval", "--run", str(run), "--device", "cpu", "--no-floor"])
    assert result.exit_code == 0, result.output
    metrics = json.loads((run / "metrics.json").read_text())
    assert (metrics["world_size"], metrics["effective_batch_size"]) == (2, 4)
    # each process validated its 4 frames; gathered, the scores are one process's cli eval's to the digit
    (validation,) = [json.loads(line) for line in (run / "val.jsonl").read_text().splitlines()]
    assert validation["frames"] == FRAMES and validation["step"] == 2 and validation["directed_topo_f1"] > 0
    for mode in ("directed", "undirected"):
        for metric in ("topo", "junction_topo"):
            assert validation[f"{mode}_{metric}_f1"] == metrics[mode][metric]["f1"], (mode, metric)
    assert validation["miou"] == metrics["miou"]

    # (c) the normaliser is summed over the processes: 2 x 2 frames train as 1 x 4 frames
    first_step = [lanes[i] for i in list(DistributedSampler(range(FRAMES), 1, 0, seed=SEED))[:4]]
    assert first_step[0::2] != first_step[1::2]  # the ranks' lane counts differ: 1 + 1 against 2 + 2
    config = load_config(run / "config.json")
    config.train.threads = 1
    train(config, data, tmp_path / "single")
    single = [json.loads(line) for line in (tmp_path / "single" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in single] == [1, 2]
    for one, two in zip(single, log, strict=True):
        for name in ("loss", "cls", "points", "grad_norm"):
            assert two[name] == pytest.approx(one[name], rel=1e-5, abs=1e-7), (one["step"], name)
