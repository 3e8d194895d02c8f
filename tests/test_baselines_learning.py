"""The learning checks: each model (tiny preset, CPU) trained on the synthetic training logs must reach
its directed TOPO F1 bar (and LaneGAP its directed Junction TOPO F1 bar) on the validation logs, which it
never trains on, AND beat its sensor-blind floor (baselines/floor.py: the same model fed another log's
sensors, and the best constant training graph) by +0.15 directed TOPO F1 and +0.10 directed Junction
TOPO F1: a model that does so reads its sensors.

The data is `cli synth`'s default (10 logs x 20 frames 1 s apart, seed 0, 4 worlds): the validation logs
drive a world that no training log visits. Each check stays within 6 minutes of wall time on the 2-core
machine, run alone (not beside other tests): `make test-learning` (LANEGRAPH_LEARNING_CHECK=1). They are
not part of `make test`: only HDMapNet's reaches its bars yet (see MEASURED)."""

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
# MEASURED 2026-12-03, stop 26 (no model change): `make test-learning` alone at 31b2421: 5 failed in 1,504 s
# with the same scores as stop 25 (HDMapNet 0.484 / 0.431, +0.161 / +0.163, 408 s; LaneGAP 0.396 / 0.343,
# 376 s; LiDAR 0.281 / 0.256, 180 s; MapTR 0.351 / 0.311, 366 s; STSU 0.376 / 0.274, 284 s). This machine's
# speed swings ~1.45 x within minutes: the same script took 0.414 then 0.287 s per LaneGAP step, 0.459
# then 0.314 s per HDMapNet step (2.37 steps/s in the check); the checks' times follow it.
# Recall limits every model (0.27-0.36), and to the side more than ahead: the share of ground-truth points
# within 0.45 m of a prediction at |x| <= 5 m / > 5 m is 0.68 / 0.27 (HDMapNet), 0.65 / 0.15 (LaneGAP),
# 0.62 / 0.11 (STSU). HDMapNet's lane mask recall by 2.5 m lateral band, validation 0.83 0.80 0.74 0.54
# 0.23 0.11, training frames 0.83 0.84 0.83 0.66 0.60 0.34, while 68-78 % of the 1.5 m lane cells of every
# band hold >= 3 LiDAR ground points and every band is seen by a camera: the junction arms and side roads
# are observable and underfit (6-12 % of the lane cells per outer band).
# LaneGAP levers (fusion, 880 steps; the preset 0.396 / 0.344), reverted: snapping each predicted point
# across its path onto the best lane probability within 1-1.5 m: of its own fine level 0.427 / 0.353, of
# HDMapNet's 0.3 m mask (another run) 0.479 / 0.405 (still < 0.5; a head of that size adds ~0.26 s a step);
# 3 more conv-BN-ReLU in the fine level (no time cost) 0.415 / 0.323 (P 0.67, R 0.30; snapped 0.432).
# HDMapNet under bf16 autocast (this CPU has AVX512-BF16): 0.68 x the step time, but 0.435 / 0.327.
# More road per frame (`cli synth` at 2 s / 3 s between frames, the same 10 x 20 frames; their own floors
# 0.306 / 0.283 and 0.310 / 0.281): LaneGAP 0.412 / 0.401 (+0.106 / +0.118) and 0.378 / 0.325 (+0.068 /
# +0.044): within the data draw's noise of the 1 s split's 0.396 / 0.344 (+0.074 / +0.064).
# MEASURED 2026-12-03, stop 25: MapTR and STSU at score threshold 0.7 (chosen on the training frames,
# stop 24's sweep): MapTR 0.352 / 0.311, +0.029 / +0.043 (407 s); STSU 0.377 / 0.274, +0.054 / +0.006
# (345 s). `make test-learning` alone at 33c8377: 5 failed in 1,644 s, the same scores as above and stop
# 24's; HDMapNet 444 s (its scores pass, its time does not), LaneGAP 413 s, LiDAR 201 s, MapTR 381 s,
# STSU 344 s.
# LaneGAP levers tried on this split (880 steps, fusion; the preset: 0.396 / 0.344, P 0.51, R 0.32):
# Bezier head (5 control points) 0.417 / 0.327; 0.75 m LiDAR pillars 0.271 / 0.185 (0.394 / 0.355 at
# threshold 0.4); a LiDAR ground raster (max / mean intensity, count) at 0.6 m into the fine level
# 0.397 / 0.378; quality-aware class targets (exp(-d / 1 m) for the matched paths) 0.256 / 0.099 (0.355
# at 0.2). Its training frames would choose threshold 0.6 (0.382; validation 0.380 against 0.396 at 0.5).
# Recall limits it: with the match radius widened to 0.75 / 1 / 1.5 m the preset scores 0.451 / 0.488 /
# 0.533, recall only 0.435 at 1.5 m; a quarter of the GT lane length lies > 2 m from any predicted path
# (junction connectors, roundabouts). Drawn, its paths are jagged and mostly straight, and the fine
# level's lane probability shows junctions and S-bends as blurred regions beyond ~15 m of the ego.
# Three times the steps (2,640) do not help the piece-wise models: STSU 0.351 / 0.299 at 0.7 (0.372 at
# 0.8; 0.329 on its own training frames: it underfits), MapTR 0.305 / 0.297 (0.328 at 0.8). Gating STSU's
# links by the gap from piece end to piece start (1-4 m) before Piece2Graph: +0.01 to +0.03 (not landed).
# MEASURED 2026-12-03, stop 24, with the fine BEV level (baselines/fine_bev.py: the query decoders also
# read the BEV features lifted to 0.6 m cells, trained by a dense lane + direction loss) and LaneGAP's
# point weight 20 (`make test-learning` alone at 87befd4: 5 failed in 1,715 s), directed TOPO / Junction
# TOPO F1, margins over the floor, time with the data:
# - HDMapNet fusion 0.484 / 0.431, +0.161 / +0.151 (457 s: past the 360 s only because this machine ran
#   ~1.4 x slower than on 2026-12-02; the old and the new code take the same 0.51 s per step here);
# - LaneGAP fusion 0.396 / 0.344, +0.074 / +0.064 (401 s); LaneGAP LiDAR 0.281 / 0.256 (219 s);
# - MapTR fusion 0.312 / 0.309, -0.011 / +0.041 (426 s; without the fine level 0.092 / 0.035);
# - STSU fusion 0.324 / 0.286, +0.002 / +0.018 (348 s; without it 0.120 / 0.086).
# The fine level's runs (880 steps, fusion, point weight 20 for LaneGAP), directed TOPO / Junction TOPO:
# LaneGAP at 0.3 m cells (x5) 0.415 / 0.407 and 0.399 / 0.327 (training seed 0), 0.399 / 0.367 (seed 1);
# at 0.6 m (x2.5) 0.384 / 0.365 and 0.396 / 0.344; a 1x1 conv + PixelShuffle x5 instead of bilinear +
# 3x3 conv 0.407 / 0.311. Time per training step (2 cores): LaneGAP 0.32 s, x2.5 0.42 s, x5 0.52 s.
# Drawn, LaneGAP still misses most junction connectors and roundabouts (no path above 0.6 there).
# MEASURED 2026-12-02, stop 20 (seed 0, tiny preset: batch 2, 11 epochs = 880 steps, full-size synthetic
# images with the sky cropped; `make test-learning` alone: 1 passed, 4 failed in 1,028 s), directed TOPO /
# Junction TOPO F1 on the 40 validation frames, floor 0.323 / 0.268 (the constant prior), time with the
# data's preparation (~30 s):
# - HDMapNet fusion 0.488 / 0.392, margins +0.165 / +0.124 (298 s): passes, the first model to;
# - LaneGAP fusion 0.325 / 0.353 (240 s); LaneGAP LiDAR 0.269 / 0.294 (116 s);
# - MapTR fusion 0.092 / 0.035 (240 s; score threshold 0.3: 0.171, precision 0.12); STSU 0.120 / 0.086
#   (226 s).
# With 8 epochs (640 steps): HDMapNet 0.471 / 0.365 (+0.149 / +0.097, 240 s; 0.480 / 0.387 run alone: CPU
# convolutions' float order moves a run by ~0.01-0.04), LaneGAP 0.278 / 0.280 and LiDAR 0.297 / 0.258,
# MapTR 0.000 / 0.000 (no piece above its threshold), STSU 0.300 / 0.247.
# Before (stop 19: batch 4, 480 steps, images at 0.5): HDMapNet 0.363 / 0.305, LaneGAP 0.257 / 0.266 and
# LiDAR 0.253 / 0.294, MapTR 0.057 / 0.072, STSU 0.158 / 0.177.
# HDMapNet variants on this split (directed TOPO / Junction TOPO F1, train seconds): full-size images
# without the crop, 960 steps 0.490 / 0.416 (414 s), 640 steps 0.467 / 0.404 (285 s); with the crop
# 800 steps 0.440 / 0.352, lr 4e-3 0.447 / 0.348, 0.75 m LiDAR pillars and 60,000 points 0.424 / 0.361,
# lane class weight 2.13 0.363 / 0.285 (blobs); 0.75 m BEV cells 0.481 / 0.407 (532 s); image features
# at stride 4 0.482 / 0.409 (322 s). It underfits: 0.461 on its own training frames. Its misses are
# lanes it never draws (mIoU 0.36 against the raster round trip's 0.79), not directions (undirected
# F1 0.473) nor its post-processing (thresholds 0.3-0.7: at best +0.006; smoothing the traced branches
# over 2-6 m: +0.002 to +0.007, not landed).
# Stop 19's figures with batch 4, 480 steps and images at 0.5 (kept for the levers they rule out):
# HDMapNet underfits rather than overfits: on the training frames 0.399 / 0.274 (validation 0.365 /
# 0.355, on an earlier version of this split); a third of the ground-truth lane length has no prediction
# within 2 m. Neither its post-processing (thresholds 0.3-0.5, hysteresis, smoothing, bridging gaps up to
# 8 m along the direction: at best 0.401 / 0.396) nor 0.75 m BEV cells (LiDAR: 0.319 / 0.260 against
# 0.328 / 0.260) gets it there; with twice the data (40 frames per log) and images twice as large, 960
# steps (1,611 s) reached 0.451 / 0.514 on the split before inner-lane routes, 4.5x the budget. More,
# smaller steps help it: train.batch_size=2 (960 steps) 0.403 / 0.334 in 506 s, batch 1 (1,920 steps)
# 0.359 / 0.287 in 611 s. With batch 2, LaneGAP fusion 0.301 / 0.283 (383 s; floor 0.323 / 0.281) and
# MapTR 0.000 / 0.000 (no piece above its threshold); the preset then kept 4.
# LaneGAP's decoder on the ground-truth raster (python -m baselines.decoder_oracle) is the limit of the
# path-wise models: at the tiny preset's 1.5 m cells it scores 0.367 / 0.403 (64 queries: 0.341) and
# at 0.6 m about 0.43 in 480 steps; perfect paths that turn less than 17 degrees alone would score 0.787
# / 0.668, but 32 of 40 validation frames hold junctions, where its paths are jagged lines that follow no
# lane (precision 0.21 there). Tried on that oracle in 2026-12-01 without reaching the bar: learning rate,
# 6 layers, 8 deformable points, 128 channels, Bezier head, decoupled self-attention (kept), a dilated
# BEV neck with sine reference embeddings (+0.03), content-dependent deformable weights (+0.04),
# denoising queries, one-to-many matching, two-stage proposals, k-means initial paths, 3x the steps
# (+0.04), a trunk merge in Path2Graph; perfect score calibration of its paths would give 0.462.
# Stop 21 (2026-12-02), the decoders with perfect perception (python -m baselines.decoder_oracle: the GT
# raster at 1.5 m cells as the BEV input, the checks' 880 steps at batch 2), directed TOPO / Junction TOPO
# F1 on the validation frames at score threshold 0.5 (0.6): LaneGAP 0.305-0.332 / 0.348-0.439 (0.357-
# 0.378), MapTR 0.291 / 0.312 (0.248), STSU 0.316 / 0.324 (0.368); on their own training frames hardly
# more (LaneGAP 0.344-0.370): they underfit, all three query models alike. Drawn, LaneGAP's paths in
# junction frames stay near their initial straight lanes, jagged, through no lane. Ten times the steps
# (8,800, 990 s without the encoder): LaneGAP 0.341 / 0.530 (0.503 / 0.637 on its training frames);
# at 0.6 m cells 0.323 / 0.549 (0.413 on training). Its recall grows, its precision stays at 0.23-0.26:
# paths 0.5-1 m off their lane miss the metric's 0.45 m radius. Tried on the oracle without a gain
# beyond the run-to-run noise (+-0.03 TOPO, +-0.09 Junction TOPO between thread counts): global cross-
# attention over the whole BEV map beside the deformable one, Hungarian matching on the queries' fixed
# anchors instead of their predictions, k-means of the training paths as the queries' initial paths,
# and both together (the paths then bend with the lanes but stay jagged), 3- to 5-point smoothing of
# the predicted paths (+0.01 to +0.02; +0.08 after 8,800 steps at 0.6 m).
# HDMapNet on other seeds of `cli synth` (same recipe, its own validation world): seed 1 0.298 / 0.245,
# floor 0.181 / 0.147 (0.636 / 0.418 on its training frames: the validation world is where it fails;
# LiDAR only 0.243 / 0.151, camera only 0.260 / 0.250; 40 frames a log and 960 steps 0.333 / 0.187);
# seed 2 0.455 / 0.272, floor 0.268 / 0.184 (margins +0.187 / +0.088, 323 s of training). Its pass holds
# on seed 0 only.
# Stop 22-23 (2026-12-02/03), LaneGAP's decoder on the GT raster (the oracle, 880 steps, seed 0): it reads
# its input (0.346 / 0.448 with its own raster, 0.147 / 0.247 with another frame's, 0 with none); its
# points lie a median 0.31 m from the nearest GT path (90th percentile 1.5-2 m). Memorisation
# (--train-frames): 4 frames 0.93 / 0.95 on them; 16 frames 0.20-0.30 / 0.39-0.45 (2,640 steps: 0.66 /
# 0.81). Point weight (matching cost and loss; the preset's 5) on the full split, validation at 0.5 (0.6):
# 10 0.389 (0.454), 20 0.455 (0.488) / 0.432, 30 0.453 (0.373), 50 0.384, 100 0.043; 20 with cls 4
# 0.422 (0.477). With the sensors (fusion, 880 steps) the point weight does not carry over: 20 gives
# 0.306 / 0.264 (0.273 on its training frames; 0.315 at threshold 0.4), + seg weight 5 0.285 / 0.245,
# + a residual 3-block dilated conv BEV neck 0.000 (0.285 at 0.4): with sensors it underfits its own
# training frames, where the oracle does not. A sine reference-position query embedding (DAB-DETR) on
# the 16-frame oracle: 0.273 / 0.471, no gain. The oracle's lane direction matters: mask only (point
# weight 20) 0.341 / 0.326 against 0.455 / 0.432, and the sensors show paint, not direction. So an
# auxiliary BEV direction head (cos, sin, L2 on lane cells, as HDMapNet's; training only; scratch, not
# landed) with point weight 20: 0.361 / 0.329 (direction weight 1), 0.340 / 0.349 (5), training frames
# ~0.30. Point weight 20 with 3 x the steps (2,640, 849 s): 0.336 / 0.345 (0.361 at 0.6; 0.380 on its
# training frames). A fine auxiliary head (BEV upsampled x5 to 0.3 m, conv, lane mask cross-entropy +
# direction L2, training only; scratch) with point weight 20: 0.382 / 0.345 (0.372 on its training
# frames), weight 3 0.350 / 0.325, with point weight 5 0.311 / 0.381; with point weight 20 and 3 x the
# steps (911 s) 0.378 / 0.377, at threshold 0.6 0.418 / 0.366 (0.454 on its training frames). Within
# the checks' budget LaneGAP stays under 0.4 whatever the lever above. Training seed 1 (point weight
# 20): 0.263 / 0.214 alone, 0.322 / 0.312 with the fine head: the head's +0.06-0.08 repeats, but the
# seed moves a run by ~0.06, as much as the preset's point weight 5 differs from either.
# MapTR's and STSU's oracles at point weight 20 fall (MapTR 0.290 -> 0.242, STSU 0.268 -> 0.054 at 0.5):
# the lever is LaneGAP's alone.
# HDMapNet on seed 1 with 8 worlds (7 for training): 0.236 / 0.218 against 0.298 / 0.245 with 4 (floor
# 0.181 / 0.147): more training geography did not help it. LiDAR only on seed 0: HDMapNet 0.329 / 0.269
# (+0.007 / +0.001), STSU 0.176 / 0.115, MapTR 0.000 / 0.000.
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
