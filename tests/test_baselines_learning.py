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


# Opt-in (`make test-learning`, or LANEGRAPH_LEARNING_CHECK=1) while its margin is thin: on a quiet
# 2-core machine it takes ~200 s and reaches F1 0.518 (seed 0) / 0.535 (seed 1) (2026-11-30), and a
# red CI blocks everything else from landing.
@pytest.mark.skipif(
    os.environ.get("LANEGRAPH_LEARNING_CHECK") != "1",
    reason="learning check is opt-in while its margin is thin: LANEGRAPH_LEARNING_CHECK=1",
)
def test_lanegap_tiny_learns_the_synthetic_world(tmp_path):
    start = time.perf_counter()
    # 10 logs (8 train, 2 val) of 100 frames, every 5th kept: 20 frames per log that show 5 times as
    # much of the world as 20 consecutive ones; with consecutive frames the same run reaches only ~0.2.
    data = prepare_synthetic(tmp_path / "data", logs=10, frames_per_log=100, frame_stride=5)
    # Fusion reads the paint both in the images and in the LiDAR intensities (the synthetic sweeps are
    # sparse: LiDAR alone stays near 0.1).
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
