"""The learning checks: each model (tiny preset, CPU) trained on the synthetic training logs must reach
its directed TOPO F1 bar (and LaneGAP its directed Junction TOPO F1 bar) on the validation logs, which it
never trains on, AND beat its sensor-blind floor (baselines/floor.py: the same model fed another log's
sensors, and the best constant training graph) by +0.15 directed TOPO F1 and +0.10 directed Junction
TOPO F1: a model that does so reads its sensors.

The data is `cli synth`'s default (10 logs x 20 frames 1 s apart, seed 0, 4 worlds): the validation logs
drive a world that no training log visits. Each check stays within 6 minutes of wall time on the 2-core
machine, run alone (not beside other tests): `make test-learning` (LANEGRAPH_LEARNING_CHECK=1). They are
not part of `make test` today: none passes yet (see MEASURED)."""

from __future__ import annotations

import os
import time

import pytest

from baselines.bench_train import prepare_synthetic
from baselines.config import resolve_config
from baselines.evaluate import evaluate
from baselines.floor import floor_margins
from baselines.train import train

TOPO_MARGIN, JUNCTION_MARGIN = 0.15, 0.10
WALL_SECONDS = 360
# (model, modality, directed TOPO F1 bar, directed Junction TOPO F1 bar), all on the unseen-roads split
CHECKS = [
    ("lanegap", "fusion", 0.5, 0.45),
    ("lanegap", "lidar", 0.4, 0.0),
    ("hdmapnet", "fusion", 0.4, 0.0),
    ("maptr", "fusion", 0.4, 0.0),
    ("stsu", "fusion", 0.4, 0.0),
]
# MEASURED 2026-12-01 (seed 0, tiny preset: 12 epochs = 480 steps, score threshold 0.5; all three fail),
# directed TOPO / Junction TOPO F1, floor = max(other log's sensors, constant prior):
# - decoder with one self-attention over all Q * N point queries, sigmoid over exactly the map: same roads
#   fusion 0.170 / 0.187 (floor 0.201 / 0.186, 304 s), unseen roads fusion 0.167 / 0.266 (floor 0.330 /
#   0.283, 315 s), unseen roads LiDAR 0.190 / 0.174 (164 s);
# - decoupled self-attention (MapTRv2) and points over the map widened by 10 % (baselines/query_decoder.py):
#   same roads fusion 0.173 / 0.257 (466 s with other work on the machine), unseen roads fusion 0.170 /
#   0.296, unseen roads LiDAR 0.222 / 0.170 (156 s); unseen roads LiDAR with 36 epochs: 0.162 / 0.267
#   (precision 0.12, recall 0.25: more steps fit the training worlds, not the unseen one).
# Perfect 20-point paths through Path2Graph scored 0.704 / 0.824 on the unseen-roads frames (before its
# direction check; with it and 0.01 m of noise, 0.948 / 0.932: tests/test_lanegap_oracle.py), and the
# decoder trained on the ground-truth raster (python -m baselines.decoder_oracle) reaches only
# ~0.3-0.37 / 0.30-0.33 on validation and ~0.35 / 0.5 on its own training frames: the decoder's
# convergence is the limit, not perception. Re-measured later on 2026-12-01 (unseen roads, GT raster,
# 480 steps): train / val directed TOPO F1 0.34-0.38 / 0.36-0.43, so it underfits (4 training frames alone
# overfit to point L1 0.006 in 300 steps); at step 1320 of a 1920-step run the training point L1 was still
# 0.13 (0.18 at 480). Its paths stay near the straight-lane prior of the initial queries; matching on the
# queries' initial paths with k-means initial paths (0.431), and perfect lateral snapping of the
# predicted points onto the GT centrelines (+0.05), do not change that. Stop 17 (same GT-raster setup, val
# directed TOPO F1 at threshold 0.6, baseline 0.425): learning rate 6e-4 / 4e-3 0.429 / 0.319; a dilated
# conv neck on the BEV plus the reference point's sine embedding in the query position (DAB-DETR) 0.458;
# content-dependent deformable attention weights plus the weighted mean sampling offset 0.467; denoising
# queries (DN-DETR, noised GT paths) 0.382, and the denoised paths are refined only from ~0.06 to ~0.045
# point L1; one-to-many matching (MapTRv2: 64 more queries, GT x 3) 0.266. The training point L1 after
# 480 steps is 0.17-0.21 in every variant. Stop 18: drawn beside the GT, the 1,920-step oracle's paths are
# right on straight roads and jagged lines that follow no lane in every junction and roundabout frame,
# train and val alike; a best-first trunk merge in Path2Graph shortens its graph from 1.8x to 1.5x the GT
# length but scores 0.338 (today's 0.348). The oracle's BEV cells matter: 0.307 at 1.5 m (pool 10, the
# tiny encoder's cells) against 0.425 at 0.6 m; two-stage queries seeded by per-cell proposals
# (Deformable DETR two-stage, top-k with or without 3 x 3 peak selection; pool 10) reach at best 0.156 /
# 0.131 (threshold 0.4, recall 0.13) against 0.236-0.307 without: not landed. At pool 10 neither 6 decoder
# layers (0.305), 8 deformable points (0.306), 128 channels (0.275) nor the 5-point Bezier head (0.250)
# moves it. The real
# model with 0.75 m BEV cells (encoder.bev_h=80, bev_w=40; unseen fusion, 480 steps) scores 0.205 / 0.223
# (floor 0.330 / 0.283) against 0.198 / 0.294 with the tiny preset's 1.5 m cells. The oracle at pool 10
# with 1,440 steps: 0.350 / 0.428. HDMapNet tiny fusion (the same recipe, 533 s) scores 0.366 / 0.269
# (P 0.76, R 0.24), with 60,000 LiDAR points 0.355 / 0.275: its lane mask holds the ego's lane and the
# one to its left in every frame and none further out. With images twice as large (data.image_scale_av2=1.0,
# 767 s) its lanes follow more of the road, but it fits the training worlds: train 0.452, val 0.171 / 0.203.
# With those images AND twice the data (synth frames_per_log=40: 320 training frames; 12 epochs = 960
# steps, 1,611 s) HDMapNet reads its sensors: val 0.451 / 0.514, floor 0.307 / 0.287, margins +0.144 /
# +0.227 (the first run above the floor by about the margins; the time is 4.5x the budget).
# The bars are the learning-check issue's; do not lower them.


@pytest.fixture(scope="module")
def unseen_roads(tmp_path_factory):
    """`cli synth`'s default data, prepared once for every check, and the seconds that took."""
    start = time.perf_counter()
    data = prepare_synthetic(tmp_path_factory.mktemp("data") / "unseen_roads")
    return data, time.perf_counter() - start


@pytest.mark.parametrize(
    ("model", "modality", "bar", "junction_bar"), CHECKS, ids=[f"{c[0]}-{c[1]}" for c in CHECKS]
)
def test_tiny_model_learns_to_read_its_sensors(request, tmp_path_factory, model, modality, bar, junction_bar):
    if os.environ.get("LANEGRAPH_LEARNING_CHECK") != "1":
        pytest.skip("learning checks run alone: make test-learning (LANEGRAPH_LEARNING_CHECK=1)")
    data, data_seconds = request.getfixturevalue("unseen_roads")  # not prepared when skipped
    start = time.perf_counter() - data_seconds  # each check's budget holds the data's preparation
    config = resolve_config("tiny", modality=modality, model=model)
    run = tmp_path_factory.mktemp(f"{model}_{modality}")
    summary = train(config, data, run)
    metrics = evaluate(run, data, "val", device="cpu")
    seconds = time.perf_counter() - start
    margins = floor_margins(metrics)["directed"]
    scores = {m: metrics["directed"][m]["f1"] for m in ("topo", "junction_topo")}
    print(f"{model} {modality}: directed F1 {scores}, floor {metrics['floor']['f1']['directed']}, "
          f"margins {margins}; {summary}; {seconds:.0f} s in all")  # fmt: skip
    assert scores["topo"] >= bar, f"directed TOPO F1 {scores['topo']:.3f} < {bar}"
    assert scores["junction_topo"] >= junction_bar, (
        f"directed Junction TOPO F1 {scores['junction_topo']:.3f} < {junction_bar}"
    )
    assert margins["topo"] >= TOPO_MARGIN, f"TOPO F1 only {margins['topo']:+.3f} over the blind floor"
    assert margins["junction_topo"] >= JUNCTION_MARGIN, (
        f"Junction TOPO F1 only {margins['junction_topo']:+.3f} over the blind floor"
    )
    assert seconds < WALL_SECONDS
