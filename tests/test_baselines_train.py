"""Data loading, training loop, resume and DDP of the baselines on a toy prepared dataset.

The toy dataset is written here (Parquet tables in the docs/guide/prepare.md schema, JPEG images, AV2-style
LiDAR feathers), so these tests need neither `cli synth` nor `cli prepare`.
"""

from __future__ import annotations

import json
import os
import socket
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pyarrow.parquet as pq
import pytest
import torch
import torch.multiprocessing as mp

from baselines.config import Config
from baselines.data import PreparedDataset, collate, resample_polyline
from baselines.models import build, load_config, resolve_config
from baselines.train import lr_factor, train, use_dataset_range
from pipeline import io
from pipeline.camera import scaled_intrinsics
from pipeline.geometry import Range
from pipeline.lane_graph import LaneGraph
from pipeline.manifest import PreparedData
from pipeline.raster import Grid, rasterize


def front_camera_pose(yaw: float) -> np.ndarray:
    forward = np.array([np.sin(yaw), np.cos(yaw), 0.0])
    right = np.array([np.cos(yaw), -np.sin(yaw), 0.0])
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, [0.0, 0.0, -1.0], forward], 1)
    pose[2, 3] = 1.5
    return pose


def cli_train_toy(data: Path, run: Path) -> None:
    """`cli train` of a tiny LiDAR LaneGAP for one epoch on a toy dataset, validated on its train split."""
    from typer.testing import CliRunner

    from cli import app

    args = ["train", "--data", str(data), "--out", str(run), "--preset", "tiny", "--modality", "lidar",
            "--epochs", "1", "--batch-size", "2", "--path-points", "10", "--no-aux-seg",
            "--set", "train.threads=1", "--set", "train.val_split=train"]  # fmt: skip
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "final loss" in result.output and "{" not in result.output  # a summary table, not raw JSON


def write_toy_dataset(root: Path, frames: int = 6, split: str = "train") -> Path:
    """A prepared dataset at root/prepared whose sensors lie under root/raw: straight lanes at random x."""
    rng = np.random.default_rng(0)
    raw, out = root / "raw", root / "prepared"
    intrinsics = np.array([[60.0, 0, 79.5], [0, 60.0, 47.5], [0, 0, 1]])
    frame_rows, path_rows = [], []
    for i in range(frames):
        frame_id = f"av2/toy/{i}"
        cameras = []
        for c, yaw in enumerate((0.0, np.pi)):
            relative = f"toy/{i}_{c}.jpg"
            (raw / "toy").mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(raw / relative), rng.integers(0, 255, (96, 160, 3), dtype=np.uint8))
            cameras.append(
                {
                    "name": f"cam{c}",
                    "image_path": relative,
                    "intrinsics": intrinsics.flatten().tolist(),
                    "sensor_to_ego": front_camera_pose(yaw).flatten().tolist(),
                    "width": 160,
                    "height": 96,
                }
            )
        points = rng.uniform([-20, -20, -1, 0], [20, 35, 1, 255], (3000, 4)).astype(np.float32)
        lidar = f"toy/{i}.feather"
        feather.write_feather(pa.table({k: points[:, j] for j, k in enumerate("xyz")} | {
            "intensity": points[:, 3].astype(np.uint8)}), str(raw / lidar))  # fmt: skip
        for p, x in enumerate(rng.uniform(-12, 12, 2)):
            ys = np.linspace(-30, 30, 7, dtype=np.float32)
            xs = np.full(7, x, np.float32)
            r = resample_polyline(np.stack([xs, ys], 1), 20).astype(np.float32)
            path_rows.append(
                {"frame_id": frame_id, "path_index": p, "vertex_ids": list(range(p * 7, p * 7 + 7)),
                 "x": xs.tolist(), "y": ys.tolist(), "rx": r[:, 0].tolist(), "ry": r[:, 1].tolist(),
                 "length": 60.0}
            )  # fmt: skip
        frame_rows.append(
            {"frame_id": frame_id, "dataset": "av2", "split": split, "log_id": "toy", "timestamp_ns": i,
             "city": "toy", "pose_translation": [0.0, 0.0, 0.0], "pose_rotation": [1.0, 0.0, 0.0, 0.0],
             "cameras": cameras, "lidar_path": lidar, "lidar_to_ego": np.eye(4).flatten().tolist(),
             "ground_z": 0.0, "ground_slope": [0.0, 0.0], "n_vertices": 14, "n_edges": 12, "n_paths": 2,
             "n_pieces": 2, "n_junctions": 0, "path_cap_hit": False}
        )  # fmt: skip
    graph_rows = []
    for frame in frame_rows:
        lines = [r for r in path_rows if r["frame_id"] == frame["frame_id"]]
        src = [7 * i + j for i in range(len(lines)) for j in range(6)]
        graph_rows.append(
            {"frame_id": frame["frame_id"], "x": sum((r["x"] for r in lines), []),
             "y": sum((r["y"] for r in lines), []), "src": src, "dst": [v + 1 for v in src]}
        )  # fmt: skip
    grid = Grid(Range(-15.0, 15.0, -30.0, 30.0))  # the prepared rasters: the fine BEV level's targets
    raster_rows = []
    for row in graph_rows:
        graph = LaneGraph(*(np.array(row[k], np.float32) for k in "xy"),
                          *(np.array(row[k], np.int32) for k in ("src", "dst")))  # fmt: skip
        mask, direction = rasterize(graph, grid)
        raster_rows.append(
            {"frame_id": row["frame_id"], "height": grid.shape[0], "width": grid.shape[1],
             "resolution": grid.resolution, "line_width": grid.line_width, "mask": io.encode_mask(mask),
             "direction": io.encode_raster(direction)}
        )  # fmt: skip
    tables = {
        "frames": pa.Table.from_pylist(frame_rows, io.SCHEMAS["frames"]),
        "paths": pa.Table.from_pylist(path_rows, io.SCHEMAS["paths"]),
        "graphs": pa.Table.from_pylist(graph_rows, io.SCHEMAS["graphs"]),
        "rasters": pa.Table.from_pylist(raster_rows, io.SCHEMAS["rasters"]),
    }
    io.write_shard(out, f"{split}__toy", tables)
    (out / "manifest.json").write_text(json.dumps({"root": str(raw)}))
    return out


def toy_config(modality: str = "lidar", epochs: int = 2) -> Config:
    config = resolve_config("tiny")
    config.encoder.modality = modality
    config.data.image_scale_av2 = 0.25  # the toy data is no `cli synth` output: its real-data settings
    config.data.image_crop_top = 0.4
    config.train.epochs = epochs
    config.train.batch_size = 2
    config.train.warmup_iters = 2
    config.train.log_every = 1
    config.train.threads = 1
    return config


def test_lr_schedule_warms_up_then_decays():
    config = resolve_config("tiny")
    config.train.warmup_iters = 10
    factors = [lr_factor(step, 100, config) for step in range(101)]
    assert factors[0] == pytest.approx(config.train.warmup_ratio)
    assert factors[10] == pytest.approx(0.5 * (1 + np.cos(np.pi * 0.1)) * (1 - 1e-3) + 1e-3)
    assert factors[100] == pytest.approx(config.train.min_lr_ratio)
    assert all(a >= b for a, b in zip(factors[10:], factors[11:], strict=False))


def test_scaled_intrinsics_keep_projections_consistent():
    k = np.array([[100.0, 0, 79.5], [0, 100.0, 47.5], [0, 0, 1]])
    scaled = scaled_intrinsics(k, 0.5, 0.5)
    point = np.array([1.0, -0.5, 4.0])
    pixel = (k @ point)[:2] / point[2]
    assert np.allclose((scaled @ point)[:2] / point[2], (pixel + 0.5) * 0.5 - 0.5)


def test_dataset_reads_sensors_and_targets(tmp_path):
    data = write_toy_dataset(tmp_path, frames=2)
    config = toy_config("fusion")
    dataset = PreparedDataset(PreparedData.open(data), "train", config)
    sample = dataset[0]
    # 96 x 160 at 0.25 -> 24 x 40, the top 9 rows cut (image_crop_top 0.4) -> 15 x 40,
    # padded to 32 x 64
    assert sample.images.shape == (2, 3, 32, 64)
    assert sample.image_sizes.tolist() == [[15, 40], [15, 40]]
    assert sample.paths.shape == (2, 20, 2) and 0 <= sample.paths.min() and sample.paths.max() <= 1
    assert np.allclose(sample.paths[:, 0, 1], 1.0) and np.allclose(sample.paths[:, -1, 1], 0.0)  # y=-30 .. 30
    assert sample.seg.shape == (40, 20) and sample.seg.sum() > 0
    points = sample.points
    assert points.shape[1] == 4 and np.all(np.abs(points[:, 0]) <= 15) and np.all(points[:, 3] <= 1)
    config.decoder.path_points = 10  # a different N is resampled from the full polylines
    assert PreparedDataset(PreparedData.open(data), "train", config)[0].paths.shape == (2, 10, 2)
    batch = collate([dataset[0], dataset[1]])
    assert batch.sensors.images.shape == (2, 2, 3, 32, 64) and batch.sensors.points_mask.any(1).all()
    with pytest.raises(ValueError, match="no frames in split 'mini_train'; its splits are train"):
        PreparedDataset(PreparedData.open(data), "mini_train", config)


def test_training_resumes_exactly(tmp_path):
    data = write_toy_dataset(tmp_path, frames=4)
    config = toy_config("camera", epochs=2)
    straight = train(config, data, tmp_path / "straight")
    assert straight["steps"] == 4
    train(config, data, tmp_path / "resumed", stop_after=1)
    assert torch.load(tmp_path / "resumed" / "checkpoint.pt", weights_only=True)["epoch"] == 1
    train(load_config(tmp_path / "resumed" / "config.json"), data, tmp_path / "resumed", resume=True)
    a = torch.load(tmp_path / "straight" / "checkpoint.pt", weights_only=True)
    b = torch.load(tmp_path / "resumed" / "checkpoint.pt", weights_only=True)
    assert a["step"] == b["step"] == 4
    for name, tensor in a["model"].items():
        assert torch.equal(tensor, b["model"][name]), name
    log = [json.loads(line) for line in (tmp_path / "resumed" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == [1, 2, 3, 4] and all(np.isfinite(r["loss"]) for r in log)
    assert load_config(tmp_path / "straight" / "config.json") == config


def test_a_run_stopped_before_its_first_log_line_logs_its_last_step(tmp_path):
    """--stop-after 1 of 2 epochs with train.log_every past the epoch: the run's last step is logged, so its
    loss is known (the summary's final_loss was nan and log.jsonl empty)."""
    data = write_toy_dataset(tmp_path, frames=4)
    config = toy_config("camera", epochs=2)
    config.train.log_every = 10
    summary = train(config, data, tmp_path / "run", stop_after=1)
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == [2] and np.isfinite(summary["final_loss"])
    assert summary["final_loss"] == log[0]["loss"]
    config.train.log_every = 1  # logging reads the losses only: the same weights
    train(config, data, tmp_path / "every", stop_after=1)
    a, b = (torch.load(tmp_path / r / "checkpoint.pt", weights_only=True)["model"] for r in ("run", "every"))
    assert all(torch.equal(a[name], b[name]) for name in a)


def _ddp_worker(rank: int, world_size: int, port: int, data: str, out: str) -> None:
    os.environ.update(
        {"MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port), "WORLD_SIZE": str(world_size),
         "RANK": str(rank), "LOCAL_RANK": str(rank)}
    )  # fmt: skip
    config = toy_config("lidar", epochs=1)
    config.train.batch_size = 4
    summary = train(config, Path(data), Path(out))
    Path(out, f"summary_{rank}.json").write_text(json.dumps(summary))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_ddp_two_processes_on_cpu(tmp_path):
    data = write_toy_dataset(tmp_path, frames=8)
    out = tmp_path / "ddp"
    mp.spawn(_ddp_worker, args=(2, free_port(), str(data), str(out)), nprocs=2, join=True)
    summaries = [json.loads((out / f"summary_{rank}.json").read_text()) for rank in range(2)]
    assert [s["steps"] for s in summaries] == [2, 2]  # 8 frames, 4 per step over 2 processes
    assert json.loads((out / "run.json").read_text())["world_size"] == 2
    checkpoint = torch.load(out / "checkpoint.pt", weights_only=True)
    assert checkpoint["epoch"] == 1 and len(checkpoint["rng"]) == 2
    assert len((out / "log.jsonl").read_text().splitlines()) == 2  # rank 0 writes


def test_cli_train_then_eval(tmp_path):
    from typer.testing import CliRunner

    from cli import app

    data = write_toy_dataset(tmp_path, frames=4)
    run = tmp_path / "run"
    cli_train_toy(data, run)
    config = load_config(run / "config.json")
    assert config.preset == "tiny" and config.decoder.path_points == 10 and not config.decoder.aux_seg
    result = CliRunner().invoke(app, ["eval", "--run", str(run), "--device", "cpu"])
    assert result.exit_code == 0, result.output
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["frames"] == 4 and metrics["split"] == "train" and metrics["device"] == "cpu"
    assert 0 <= metrics["directed"]["topo"]["f1"] <= 1 and metrics["params"] > 0
    assert metrics["metric_params"]["match_radius"] == 0.45
    assert metrics["fps_net"] >= metrics["fps"] > 0 and metrics["postprocess_ms"] > 0
    assert metrics["model"] == "lanegap" and metrics["modeling"] == "path" and metrics["gflops"] > 0.01
    assert metrics["config"]["encoder"]["modality"] == "lidar"
    predictions = pq.read_table(run / "predictions.parquet")
    assert predictions.schema.equals(io.SCHEMAS["graphs"]) and predictions.num_rows == 4


def test_the_bev_grid_follows_the_dataset_range(tmp_path):
    """A model never reads targets cut to another range: training takes the dataset's, a dataset of
    another range than a trained model's is a clear error."""
    data = write_toy_dataset(tmp_path, frames=4)
    manifest = json.loads((data / "manifest.json").read_text())
    manifest["range"] = {"x_min": -25.0, "x_max": 25.0, "y_min": -50.0, "y_max": 50.0}
    (data / "manifest.json").write_text(json.dumps(manifest))
    config = toy_config(epochs=1)
    with pytest.raises(ValueError, match="cropped to x \\(-25.0, 25.0\\)"):
        PreparedDataset(PreparedData.open(data), "train", config)
    train(config, data, tmp_path / "run")
    saved = load_config(tmp_path / "run" / "config.json")
    assert saved.encoder.x_range == (-25.0, 25.0) and saved.encoder.y_range == (-50.0, 50.0)
    assert (saved.encoder.bev_h, saved.encoder.bev_w) == (67, 33)  # the tiny preset's 1.5 m cells
    assert len(PreparedDataset(PreparedData.open(data), "train", saved)) == 4
    # a fresh run into a folder that holds one is refused before anything is written
    before = {f.name: f.read_bytes() for f in (tmp_path / "run").iterdir() if f.is_file()}
    with pytest.raises(ValueError, match="holds a run already .*: continue it with --resume"):
        train(config, data, tmp_path / "run")
    assert {f.name: f.read_bytes() for f in (tmp_path / "run").iterdir() if f.is_file()} == before


def test_a_checkpoint_that_needs_unpickling_is_refused(tmp_path):
    """Checkpoints load with weights_only=True: one holding other objects (here a numpy array, as runs
    before plain-typed RNG states stored) is a clear error naming the file, and is never unpickled."""
    from baselines.evaluate import load_model

    config = toy_config(epochs=1)
    config.save(tmp_path / "config.json")
    torch.save({"model": {}, "rng": [np.random.get_state()]}, tmp_path / "checkpoint.pt")
    with pytest.raises(ValueError, match="checkpoint.pt: refused"):
        load_model(tmp_path, torch.device("cpu"))


@pytest.mark.parametrize("model", ["lanegap", "hdmapnet", "maptr", "stsu"])
def test_a_training_step_and_post_processing_under_bf16_autocast(synth_prepared, model):
    """The gpu preset trains and predicts under CUDA's bf16 autocast, which CI has no GPU for: under the
    CPU's bf16 autocast the outputs come in bf16 too, and the loss, its gradients and the post-processing
    (every prediction kept) must take them."""
    torch.manual_seed(0)
    config = resolve_config("tiny", model=model)
    # every path or piece kept; HDMapNet's threshold is per cell, and at 0 every cell would be lane
    config.decoder.score_threshold = 0.0 if model != "hdmapnet" else 0.3
    use_dataset_range(config, PreparedData.open(synth_prepared["av2"]), master=False)
    built = build(config)
    dataset = PreparedDataset(PreparedData.open(synth_prepared["av2"]), "train", config, built.needs)
    batch = collate([dataset[0], dataset[10]])
    with torch.autocast("cpu", dtype=torch.bfloat16):
        outputs = built.model(batch.sensors)
    assert torch.bfloat16 in {v.dtype for v in outputs.values() if isinstance(v, torch.Tensor)}
    losses = built.loss(outputs, batch.targets)
    assert all(torch.isfinite(v) for v in losses.values())
    losses["loss"].backward()
    grads = [p.grad for p in built.model.parameters() if p.grad is not None]
    assert len(grads) > 0.9 * sum(1 for _ in built.model.parameters())
    assert all(torch.isfinite(g).all() for g in grads)
    built.model.eval()
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        graphs = built.to_graphs(built.model(batch.sensors))
    assert len(graphs) == 2 and all(len(g.x) > 0 and len(g.src) > 0 for g in graphs)
