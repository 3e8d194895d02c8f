"""Validation during training (`cli train --eval-every`): the validation split, or a fixed seeded subset
of it (`--eval-frames`), through the model's post-processing into lane graphs and then the metric, with
`cli eval`'s code (baselines/evaluate.py `predict`, benchmark/metric/totals.py `Totals`).

Under torchrun every process predicts and scores its share of the frames; each frame's counts are
gathered and added in frame order, and the metric's sums are exact (FractionSum), so the scores do not
depend on the number of processes. With the whole split they equal `cli eval`'s on the same weights.
"""

from __future__ import annotations

import os
import time
import typing

import numpy as np
import pyarrow.compute as pc
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, Subset

from baselines.config import BestMetric, Config
from baselines.data import PreparedDataset, collate
from baselines.evaluate import predict
from baselines.models.base import Built
from benchmark.graph_table import graphs_from_table
from benchmark.metric.params import MetricParams
from benchmark.metric.totals import Totals
from pipeline import io
from pipeline.manifest import PreparedData

VAL_METRICS = typing.get_args(BestMetric)  # the scores of a validation record (RUN/val.jsonl)


def chosen_frames(count: int, eval_frames: int, seed: int) -> np.ndarray:
    """The indices of the frames validated: all of them, or `eval_frames` of them drawn once by `seed`
    (the same frames at every validation and on every process), in the split's order."""
    if not eval_frames or eval_frames >= count:
        return np.arange(count)
    return np.sort(np.random.default_rng(seed).choice(count, eval_frames, replace=False))


def record_of(totals: Totals) -> dict:
    """The F1s and mIoU of summed counts, under VAL_METRICS' names."""
    result = totals.result()
    record = {
        f"{mode}_{metric}_f1": result[mode][metric]["f1"]
        for mode in ("directed", "undirected")
        for metric in ("topo", "junction_topo")
    }
    return {**record, "miou": result["miou"]}


class Validation:
    """The validation frames of this process, their ground truth and the metric's parameters; calling it
    scores a model. Every process of a torchrun must call it together."""

    def __init__(self, config: Config, data: PreparedData, needs: frozenset[str], device: torch.device,
                 autocast_dtype: torch.dtype | None, rank: int = 0, world_size: int = 1):  # fmt: skip
        train = config.train
        self.split, self.device, self.autocast_dtype = train.val_split, device, autocast_dtype
        dataset = PreparedDataset(data, self.split, config, needs)
        indices = chosen_frames(len(dataset), train.eval_frames, train.seed)
        self.frames = len(indices)
        ids = {dataset.frames[int(i)]["frame_id"] for i in indices}
        table = io.read_table(data.path, "graphs", filter=pc.field("frame_id").isin(sorted(ids)))
        self.ground_truth = graphs_from_table(table, data.path / "graphs")
        self.params = MetricParams(bev_range=data.bev_range)
        workers = min(config.data.num_workers, os.cpu_count() or 1)
        share = Subset(dataset, indices[rank::world_size].tolist())
        self.loader = DataLoader(share, batch_size=1, num_workers=workers, collate_fn=collate)
        self.distributed = world_size > 1

    def __call__(self, built: Built) -> dict:
        """Scores of the model's lane graphs on the validation frames: VAL_METRICS, the split, the frames
        and the seconds it took. The model is in eval mode while it predicts and goes back to train."""
        start = time.perf_counter()
        was_training = built.model.training
        built.model.eval()
        try:
            inference = predict(built, self.loader, self.device, self.autocast_dtype, 0,
                                f"validate {self.split}", count_flops=False)  # fmt: skip
        finally:
            built.model.train(was_training)
        counts = []  # (frame id, its counts): one Totals per frame
        for frame_id, graph in inference.graphs.items():
            frame = Totals(self.params)
            frame.add_frame(graph, self.ground_truth[frame_id])
            counts.append((frame_id, frame))
        if self.distributed:
            shares: list = [None] * dist.get_world_size()
            dist.all_gather_object(shares, counts)
            counts = [item for share in shares for item in share]
        totals = Totals(self.params)
        for _, frame in sorted(counts, key=lambda item: item[0]):
            totals.add(frame)
        return {"split": self.split, "frames": totals.frames, "seconds": time.perf_counter() - start,
                **record_of(totals)}  # fmt: skip

