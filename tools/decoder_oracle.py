"""Diagnosis: a query model's decoder with perfect perception. Its BEV input is the ground-truth raster
(lane mask and unit direction, pooled to cells of `pool` x 0.15 m) through a two-layer conv stem instead
of the sensor encoder; trained with the model's own loss and `cli train`'s optimiser and schedule
(AdamW, warm-up + cosine), scored through the model's own post-processing on both splits. If this
cannot reach a learning check's bar, no encoder will help: the decoder, its loss or its schedule is the
limit.

    python -m tools.decoder_oracle --data prepared [--model lanegap|maptr|stsu] [--preset tiny]
        [--steps 880] [--pool 10] [--train-frames N] [--set decoder.layers=6]

--train-frames N trains on N training frames only (drawn with the config's seed): a memorisation check.
A decoder that cannot fit a handful of frames it is shown the answer for in the budget is short of steps
or capacity, whatever the data.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from rich.console import Console
from rich.table import Table
from torch import nn

from baselines.config import Config
from baselines.data import PreparedDataset, collate
from baselines.models import build, resolve_config
from baselines.train import build_optimizer, lr_factor
from benchmark.graph_table import default_range, graphs_from_table, read_graph_table
from benchmark.metric.params import MetricParams
from benchmark.score import score_pairs
from pipeline.io import decode_raster, read_table
from pipeline.manifest import PreparedData
from pipeline.raster import direction_vectors

QUERY_MODELS = ("lanegap", "maptr", "stsu")  # HDMapNet has no decoder to isolate: its head is the raster


def oracle_bev(row: dict, pool: int) -> torch.Tensor:
    """(3, H / pool, W / pool): lane mask, cos and sin of the lane direction, averaged over pool x pool."""
    mask, direction = decode_raster(row)
    vectors = direction_vectors()[direction]  # (H, W, 2), zero off the lanes
    channels = np.concatenate([mask[None].astype(np.float32), vectors.transpose(2, 0, 1).astype(np.float32)])
    return F.avg_pool2d(torch.from_numpy(channels)[None], pool)[0]


class OracleModel(nn.Module):
    """The model's decoder (`decode`) on a conv stem over the ground-truth raster."""

    def __init__(self, model: nn.Module, channels: int):
        super().__init__()
        # BatchNorm at the end: without it the stem's output is small and half a per-channel constant, and
        # the decoder's cross-attention barely reads it at first (docs/EXPERIMENTS.md, 2026-12-03)
        self.stem = nn.Sequential(
            nn.Conv2d(3, channels, 3, padding=1), nn.ReLU(True), nn.Conv2d(channels, channels, 3, padding=1),
            nn.BatchNorm2d(channels),
        )  # fmt: skip
        self.model = model
        self.model.encoder = nn.Identity()  # the sensor encoder is what this replaces

    def forward(self, bev: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.model.decode(self.stem(bev))


def oracle_config(model: str, preset: str, overrides: list[str]) -> Config:
    if model not in QUERY_MODELS:
        raise ValueError(f"the decoder oracle takes a query model ({', '.join(QUERY_MODELS)}), not {model!r}")
    # LiDAR keeps the data loader off the camera images, which the oracle never reads; LaneGAP's
    # auxiliary segmentation and the fine BEV level's loss would be read off the very raster it is fed.
    extra = ["decoder.fine_scale=0", *(["decoder.aux_seg=false"] if model == "lanegap" else [])]
    return resolve_config(preset, modality="lidar", model=model, overrides=[*extra, *overrides])


def train_oracle(
    config: Config, data: Path, steps: int, pool: int | None = None, train_frames: int | None = None
) -> tuple[OracleModel, dict, float]:
    """The oracle trained for `steps` on the training split; (model, {split: [(sample, bev)]}, seconds).
    pool None: the raster pooled to the config's BEV grid, as coarse as the encoder's map; train_frames:
    only that many training frames (drawn with the config's seed), which the returned split then holds."""
    torch.manual_seed(config.train.seed)
    built = build(config)
    rasters = {row["frame_id"]: row for row in read_table(data, "rasters").to_pylist()}
    if pool is None:
        raster_rows = decode_raster(next(iter(rasters.values())))[0].shape[0]
        pool = max(1, round(raster_rows / config.encoder.bev_h))
    splits = {}
    rng = np.random.default_rng(config.train.seed)
    for split in (config.train.train_split, config.train.val_split):
        dataset = PreparedDataset(PreparedData.open(data), split, config, built.needs)
        indices = range(len(dataset))
        if split == config.train.train_split and train_frames is not None:
            if not 1 <= train_frames <= len(dataset):
                raise ValueError(
                    f"train_frames must be 1 to {len(dataset)} (the {split} split), not {train_frames}"
                )
            indices = sorted(rng.choice(len(dataset), train_frames, replace=False).tolist())
        samples = [dataset[k] for k in indices]
        splits[split] = [(sample, oracle_bev(rasters[sample.frame_id], pool)) for sample in samples]
    model = OracleModel(built.model, config.encoder.channels)
    optimizer = build_optimizer(model, config)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: lr_factor(step, steps, config))
    train = splits[config.train.train_split]
    batch_size = min(config.train.batch_size, len(train))
    start = time.perf_counter()
    for _ in range(steps):
        chosen = rng.choice(len(train), batch_size, replace=False)
        outputs = model(torch.stack([train[k][1] for k in chosen]))
        loss = built.loss(outputs, collate([train[k][0] for k in chosen]).targets)["loss"]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), config.train.grad_clip)
        optimizer.step()
        scheduler.step()
    return model.eval(), splits, time.perf_counter() - start


@torch.no_grad()
def score_oracle(model: OracleModel, config: Config, splits: dict, data: Path, thresholds) -> list[dict]:
    """Directed TOPO / Junction TOPO of every split at every score threshold, through the model's own
    post-processing."""
    truth = graphs_from_table(read_graph_table(data), data)
    params = MetricParams(bev_range=default_range(data))
    post_processing = {  # built once per threshold (a build makes a whole model), used on every split
        threshold: build(dataclasses.replace(config, decoder=dataclasses.replace(
            config.decoder, score_threshold=threshold))).to_graphs
        for threshold in thresholds
    }  # fmt: skip
    rows = []
    for split, items in splits.items():
        outputs = [model(bev[None]) for _, bev in items]
        for threshold, to_graphs in post_processing.items():
            pairs = [(to_graphs(out)[0], truth[sample.frame_id]) for (sample, _), out in zip(items, outputs)]
            directed = score_pairs(pairs, params)["directed"]
            rows.append({"split": split, "threshold": threshold, **{
                f"{metric} {field}": directed[metric][field]
                for metric in ("topo", "junction_topo") for field in ("f1", "precision", "recall")
            }})  # fmt: skip
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--model", default="lanegap", choices=QUERY_MODELS)
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--steps", type=int, default=880, help="the tiny preset's steps on cli synth's data")
    parser.add_argument(
        "--pool",
        type=int,
        help="raster cells (0.15 m) per oracle cell side; default: as "
        "coarse as the preset's BEV grid (tiny: 10, 1.5 m cells)",
    )
    parser.add_argument("--train-frames", type=int, help="train on this many training frames (memorisation)")
    parser.add_argument("--set", action="append", default=[], help="config override, as `cli train --set`")
    args = parser.parse_args()

    config = oracle_config(args.model, args.preset, args.set)
    if config.train.threads:
        torch.set_num_threads(config.train.threads)
    model, splits, seconds = train_oracle(config, args.data, args.steps, args.pool, args.train_frames)
    height, width = next(iter(splits.values()))[0][1].shape[1:]
    table = Table(
        title=f"{args.model} {args.preset} decoder on the GT raster ({height} x {width} cells): "
        f"{args.steps} steps in {seconds:.0f} s"
        + (f", {args.train_frames} training frames" if args.train_frames else "")
    )
    columns = ("topo f1", "junction_topo f1", "topo precision", "topo recall")
    for column in ("split", "threshold", *columns):
        table.add_column(column.replace("junction_topo", "Junction TOPO").replace("topo", "TOPO"))
    thresholds = sorted({0.4, 0.5, 0.6, config.decoder.score_threshold})  # and the preset's own
    for row in score_oracle(model, config, splits, args.data, thresholds):
        table.add_row(row["split"], f"{row['threshold']}", *(f"{row[c]:.3f}" for c in columns))
    Console().print(table)


if __name__ == "__main__":
    main()
