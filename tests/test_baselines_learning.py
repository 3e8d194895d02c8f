"""The learning check: LaneGAP (tiny preset, CPU) trained on the synthetic training logs must reach
directed TOPO F1 >= 0.5 on the synthetic validation logs, which it never sees, while the untrained
model scores below 0.1. The whole test (data, training, both evaluations) stays within 5 minutes on
the 2-core CI machine, run alone (not beside other tests)."""

from __future__ import annotations

import json
import os
import time

import pytest
import torch

from baselines.bench_train import prepare_synthetic
from baselines.config import resolve_config
from baselines.evaluate import evaluate
from baselines.lanegap import LaneGAP
from baselines.train import train

TRAINED_F1 = 0.5
UNTRAINED_F1 = 0.1


# It must run alone (`make test` runs it after the rest, via `make test-learning`): beside other
# tests its 5 minutes of wall time would not hold. Measured alone on a quiet 2-core machine
# (2026-11-30): ~190 s in all, F1 0.609.
@pytest.mark.skipif(
    os.environ.get("LANEGRAPH_LEARNING_CHECK") != "1",
    reason="the learning check runs alone: make test-learning (LANEGRAPH_LEARNING_CHECK=1)",
)
def test_lanegap_tiny_learns_the_synthetic_world(tmp_path):
    start = time.perf_counter()
    # 10 logs (8 train, 2 val) of 20 frames 1 s apart: ten times as much of the world as 20 frames at
    # 10 Hz, with which the same run reaches only ~0.2 (0.52 with frames 0.5 s apart).
    data = prepare_synthetic(tmp_path / "data", logs=10, frames_per_log=20, frame_period=1.0)
    # Fusion reads the paint both in the images and in the LiDAR intensities (the synthetic sweeps are
    # sparse: LiDAR alone scores ~0).
    config = resolve_config("tiny", modality="fusion", epochs=12)

    untrained = tmp_path / "untrained"
    untrained.mkdir()
    torch.manual_seed(config.train.seed)
    torch.save({"model": LaneGAP(config).state_dict()}, untrained / "checkpoint.pt")
    config.save(untrained / "config.json")
    (untrained / "run.json").write_text(json.dumps({"data": str(data)}))
    before = evaluate(untrained, data, "val", device="cpu")["directed"]["topo"]["f1"]

    summary = train(config, data, tmp_path / "run")
    after = evaluate(tmp_path / "run", data, "val", device="cpu")["directed"]["topo"]["f1"]
    seconds = time.perf_counter() - start
    print(f"directed TOPO F1 untrained {before:.3f}, trained {after:.3f}; {summary}; {seconds:.0f} s in all")
    assert before < UNTRAINED_F1
    assert after >= TRAINED_F1, f"trained F1 {after:.3f} < {TRAINED_F1}"
    assert seconds < 300
