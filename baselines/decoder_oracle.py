"""Diagnosis: LaneGAP's decoder with perfect perception. Its BEV input is the ground-truth raster (lane
mask and unit direction, pooled to cells of `pool` x 0.15 m) through a two-layer conv stem instead of the
sensor encoder; trained as `cli train` trains (loss, AdamW, warm-up + cosine), scored on both splits.
If this cannot reach a learning check's bar, no encoder will help: the decoder, its loss or its schedule
is the limit.

    python -m baselines.decoder_oracle --data prepared [--preset tiny] [--steps 480] [--pool 4]
        [--set decoder.layers=6]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from rich.console import Console
from rich.table import Table
from torch import nn

from baselines.config import resolve_config
from baselines.data import PreparedDataset, Targets
from baselines.models.lanegap import LaneGAP, LaneGAPLoss, select_paths
from baselines.train import build_optimizer, lr_factor
from benchmark.metrics import MetricParams
from benchmark.path2graph import path2graph
from benchmark.score import default_range, graphs_from_table, read_graph_table, score_pairs
from pipeline.io import decode_raster, read_table
from pipeline.raster import direction_vectors


def oracle_bev(row: dict, pool: int) -> torch.Tensor:
    """(3, H / pool, W / pool): lane mask, cos and sin of the lane direction, averaged over pool x pool."""
    mask, direction = decode_raster(row)
    vectors = direction_vectors()[direction]  # (H, W, 2), zero off the lanes
    channels = np.concatenate([mask[None].astype(np.float32), vectors.transpose(2, 0, 1).astype(np.float32)])
    return F.avg_pool2d(torch.from_numpy(channels)[None], pool)[0]


class OracleLaneGAP(nn.Module):
    def __init__(self, config, channels: int):
        super().__init__()
        self.stem = nn.Sequential(
            nn.Conv2d(3, channels, 3, padding=1), nn.ReLU(True), nn.Conv2d(channels, channels, 3, padding=1)
        )
        self.lanegap = LaneGAP(config)
        self.lanegap.encoder = nn.Identity()  # the sensor encoder is what this replaces

    def forward(self, bev: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.lanegap.decode(self.stem(bev))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--steps", type=int, default=480)
    parser.add_argument("--pool", type=int, default=4, help="raster cells (0.15 m) per oracle BEV cell side")
    parser.add_argument("--set", action="append", default=[], help="config override, as `cli train --set`")
    args = parser.parse_args()

    torch.manual_seed(0)
    config = resolve_config(args.preset, modality="lidar", overrides=["decoder.aux_seg=false", *args.set])
    if config.train.threads:
        torch.set_num_threads(config.train.threads)
    rasters = {row["frame_id"]: row for row in read_table(args.data, "rasters").to_pylist()}
    splits = {}
    for split in (config.train.train_split, config.train.val_split):
        dataset = PreparedDataset(args.data, split, config)
        ids = [frame["frame_id"] for frame in dataset.frames]
        splits[split] = [
            (
                i,
                oracle_bev(rasters[i], args.pool),
                torch.from_numpy(np.stack(dataset.paths[i]))
                if dataset.paths[i]
                else torch.zeros(0, config.decoder.path_points, 2),
            )
            for i in ids
        ]
    model = OracleLaneGAP(config, config.encoder.channels)
    optimizer = build_optimizer(model, config)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: lr_factor(step, args.steps, config))
    criterion = LaneGAPLoss(config.decoder)
    rng = np.random.default_rng(config.train.seed)
    train = splits[config.train.train_split]
    start = time.perf_counter()
    for _ in range(args.steps):
        chosen = rng.choice(len(train), config.train.batch_size, replace=False)
        outputs = model(torch.stack([train[k][1] for k in chosen]))
        targets = Targets([train[k][2] for k in chosen], torch.zeros(0))  # no aux segmentation here
        loss = criterion(outputs, targets)["loss"]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), config.train.grad_clip)
        optimizer.step()
        scheduler.step()
    seconds = time.perf_counter() - start

    truth = graphs_from_table(read_graph_table(args.data), args.data)
    params = MetricParams(bev_range=default_range(args.data))
    model.eval()
    table = Table(
        title=f"LaneGAP {args.preset} decoder on the GT raster: {args.steps} steps in {seconds:.0f} s"
    )
    for column in ("split", "threshold", "TOPO F1", "Junction TOPO F1", "TOPO P", "TOPO R"):
        table.add_column(column)
    for split, items in splits.items():
        with torch.no_grad():
            points = [select_paths(model(bev[None]), 0.0)[0] for _, bev, _ in items]
        for threshold in (0.4, 0.5, 0.6):
            pairs = [
                (
                    path2graph(
                        [
                            config.encoder.unit_to_metres(p.numpy().astype(np.float64))
                            for p in paths[scores > threshold]
                        ]
                    ),
                    truth[frame_id],
                )
                for (frame_id, _, _), (scores, paths) in zip(items, points, strict=True)
            ]
            directed = score_pairs(pairs, params)["directed"]
            table.add_row(
                split,
                f"{threshold}",
                *(
                    f"{v:.3f}"
                    for v in (
                        directed["topo"]["f1"],
                        directed["junction_topo"]["f1"],
                        directed["topo"]["precision"],
                        directed["topo"]["recall"],
                    )
                ),
            )
    Console().print(table)


if __name__ == "__main__":
    main()
