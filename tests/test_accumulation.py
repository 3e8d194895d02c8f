"""Gradient accumulation: one optimiser step over K micro-batches of b frames equals one over a batch of
K x b frames, when the micro-batches hold as many targets (each loss is normalised by its own count, as
mmcv's GradientCumulativeOptimizerHook) and BatchNorm sees the same statistics: here K copies of one
batch. And the split of a batch into micro-batches, as `cli train --accumulate` and the paper preset's
4 frames per device give it."""

from __future__ import annotations

import pytest
import torch

from baselines.config import TrainConfig
from baselines.data import collate
from baselines.models import resolve_config
from baselines.train import setup
from pipeline.manifest import PreparedData


@pytest.mark.parametrize("model", ["lanegap", "stsu"])
def test_k_micro_batches_give_the_update_of_one_k_times_larger_batch(synth_prepared, model):
    trainers, samples = [], None
    for accumulate in (1, 3):
        # the camera branch: the LiDAR pillars' max over tied points routes gradients by the frames' order
        config = resolve_config("tiny", modality="camera", model=model)
        config.train.batch_size, config.train.accumulate, config.train.threads = 6, accumulate, 1
        s = setup(config, PreparedData.open(synth_prepared["av2"]))
        assert s.loader.batch_size == 6 // accumulate and s.accumulate == accumulate
        samples = samples or [s.dataset[0], s.dataset[1]]
        trainers.append(s.trainer)
    whole, split = trainers
    step_whole, step_split = (
        whole.train_step([collate(samples * 3)]),
        split.train_step([collate(samples)] * 3),
    )
    (losses_whole, norm_whole), (losses_split, norm_split) = (
        (s.losses, s.grad_norm) for s in (step_whole, step_split)
    )
    assert float(norm_whole) > 0 and float(norm_split) == pytest.approx(float(norm_whole), rel=1e-4)
    assert float(losses_split["loss"]) == pytest.approx(float(losses_whole["loss"]), rel=1e-5)
    pairs = [
        (a.grad, b.grad) for a, b in zip(whole.model.parameters(), split.model.parameters(), strict=True)
    ]
    assert all((a is None) == (b is None) for a, b in pairs)
    whole_grad, split_grad = (torch.cat([p[i].flatten() for p in pairs if p[i] is not None]) for i in (0, 1))
    assert (split_grad - whole_grad).norm() < 1e-3 * whole_grad.norm()  # float32 sums in another order
    assert whole.step == split.step == 1  # one optimiser step, one scheduler step


def test_a_batch_splits_into_micro_batches_under_the_per_device_cap():
    paper = resolve_config("paper", from_scratch=True)
    assert paper.train.micro_batches(1) == (4, 8)  # one GPU runs the paper's 32 as 8 x 4
    assert paper.train.micro_batches(8) == (4, 1)  # 8 GPUs of 4, as the paper
    assert TrainConfig(batch_size=12, max_batch_per_device=5).micro_batches(1) == (4, 3)
    assert TrainConfig(batch_size=8, accumulate=2).micro_batches(2) == (2, 2)
    with pytest.raises(ValueError, match="--accumulate 3: the batch of 8 frames per process"):
        TrainConfig(batch_size=8, accumulate=3).micro_batches(1)
    with pytest.raises(ValueError, match="--batch-size 6 is not divisible by 4 processes"):
        TrainConfig(batch_size=6).micro_batches(4)
