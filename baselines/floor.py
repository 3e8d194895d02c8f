"""The sensor-blind floor of an evaluation: what a model scores without looking at its frame.

On the synthetic validation frames a constant graph scored as well as a trained LaneGAP, so every
`cli eval` also scores two blind baselines and reports the model's margin over the better of them:

- `other_log_sensors`: the same model fed, for each frame, the sensors of a frame of another log of
  the split (the frame at the same position in the next log, cycling), scored against the frame's
  own ground truth: what the model knows of the world without this frame's sensors.
- `constant_prior`: one training frame's ground-truth graph, the one that scores best (directed TOPO
  F1) on the training frames, predicted for every frame.

And, beside the floor, `best_constant`: of the same candidate training graphs, the one that scores best
on the evaluated frames themselves, an upper bound for any constant prediction (chosen in hindsight, so
not a blind model's score). Which constant the training frames choose depends on the candidate pool;
the learning checks therefore hold a model against this bound.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from benchmark.metric.params import MetricParams
from benchmark.score import score_pairs
from pipeline.lane_graph import LaneGraph
from pipeline.progress import track

# The prior search scores each candidate frame's graph on other training frames: candidates x scored
# metric calls (~8 ms each). Both are bounded here, the only place: 32 x 64 = 2048 calls, ~16 s once
# per data and split; the choice is then cached beside the prepared data.
PRIOR_CANDIDATES = 32  # candidate frames, spread evenly over the training split
PRIOR_SCORED_FRAMES = 64  # training frames each candidate is scored on, spread evenly
MODES = ("directed", "undirected")
METRICS = ("topo", "junction_topo")


def spread(items: list, count: int) -> list:
    """At most `count` of the items, evenly spaced, the first and the last included."""
    if len(items) <= count:
        return list(items)
    return [items[round(i)] for i in np.linspace(0, len(items) - 1, count)]


def other_log_partners(frames: list[dict]) -> dict[str, str]:
    """{frame_id: frame_id of the frame at the same position (modulo its length) in the next log};
    empty when the frames come from a single log."""
    logs: dict[str, list[str]] = {}
    for frame in sorted(frames, key=lambda f: (f["log_id"], f["timestamp_ns"], f["frame_id"])):
        logs.setdefault(frame["log_id"], []).append(frame["frame_id"])
    if len(logs) < 2:
        return {}
    names = sorted(logs)
    partners = {}
    for index, name in enumerate(names):
        other = logs[names[(index + 1) % len(names)]]
        for position, frame_id in enumerate(logs[name]):
            partners[frame_id] = other[position % len(other)]
    return partners


def prior_cache_key(ground_truth: dict[str, LaneGraph], frame_ids: list[str], params: MetricParams) -> str:
    """A hash of everything the search depends on: the graphs it reads, the bounds, the thresholds."""
    # "f1": the cache files' format (older ones held "train_f1" and are not read)
    bounds = ["f1", PRIOR_CANDIDATES, PRIOR_SCORED_FRAMES, params.as_dict()]
    digest = hashlib.sha256(json.dumps(bounds).encode())
    for frame_id in frame_ids:
        graph = ground_truth[frame_id]
        digest.update(frame_id.encode())
        for array in (graph.x, graph.y, graph.src, graph.dst):
            digest.update(np.asarray(array, np.float64).tobytes())
    return digest.hexdigest()[:16]


def best_constant(
    ground_truth: dict[str, LaneGraph],
    candidates: list[str],
    scored: list[str],
    name: str,
    params: MetricParams,
    cache_dir: Path,
) -> dict:
    """Of the candidate frames' graphs, the one that, predicted for every scored frame (but itself),
    has the best directed TOPO F1 (the first on ties): {"frame_id", "f1", ...}; read from / written to
    cache_dir under `name`."""
    key = prior_cache_key(ground_truth, sorted(set(candidates + scored)), params)
    cache = Path(cache_dir) / f"{name}__{key}.json"
    if cache.is_file():
        return {**json.loads(cache.read_text()), "cached": True}
    best_f1, best_id = -1.0, None
    with track(f"floor: {name.partition('__')[0].replace('_', ' ')} search", len(candidates)) as advance:
        for candidate in candidates:
            # a frame scored against itself is a perfect match that only the candidates in `scored` get
            pairs = [(ground_truth[candidate], ground_truth[f]) for f in scored if f != candidate]
            f1 = score_pairs(pairs, params)["directed"]["topo"]["f1"]
            if f1 > best_f1:
                best_f1, best_id = f1, candidate
            advance()
    found = {"frame_id": best_id, "f1": best_f1, "candidates": len(candidates), "scored_frames": len(scored)}
    try:  # atomic: a concurrent eval reads the old file or the new one, never half of one
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_name(f"{cache.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(found, indent=2) + "\n")
        tmp.replace(cache)
    except OSError:  # a read-only dataset: the search is redone next time, the result is the same
        pass
    return {**found, "cached": False}


def search_constant_prior(
    ground_truth: dict[str, LaneGraph],
    train_ids: list[str],
    split: str,
    params: MetricParams,
    cache_dir: Path,
) -> dict:
    """The training frame whose graph, predicted for the other scored training frames, has the best
    directed TOPO F1 (the first on ties); cached in cache_dir."""
    train_ids = sorted(train_ids)
    candidates, scored = spread(train_ids, PRIOR_CANDIDATES), spread(train_ids, PRIOR_SCORED_FRAMES)
    found = best_constant(ground_truth, candidates, scored, f"constant_prior__{split}", params, cache_dir)
    return {"frame_id": found["frame_id"], "split": split, "train_f1": found["f1"],
            "candidates": found["candidates"], "scored_frames": found["scored_frames"],
            "cached": found["cached"]}  # fmt: skip


def search_best_constant(
    ground_truth: dict[str, LaneGraph],
    train_ids: list[str],
    split: str,
    evaluated: list[str],
    params: MetricParams,
    cache_dir: Path,
) -> dict:
    """The constant prior's candidates scored on the evaluated frames themselves: the best of them, the
    best constant in hindsight (its F1 there is `hindsight_f1`)."""
    candidates = spread(sorted(train_ids), PRIOR_CANDIDATES)
    found = best_constant(ground_truth, candidates, sorted(evaluated), f"best_constant__{split}", params,
                          cache_dir)  # fmt: skip
    return {"frame_id": found["frame_id"], "split": split, "hindsight_f1": found["f1"],
            "candidates": found["candidates"], "scored_frames": found["scored_frames"],
            "cached": found["cached"]}  # fmt: skip


def blind_floor(
    predictions: dict[str, LaneGraph],
    ground_truth: dict[str, LaneGraph],
    frames: list[dict],
    train_ids: list[str],
    train_split: str,
    params: MetricParams,
    cache_dir: Path,
) -> dict:
    """metrics["floor"] without the margin: both blind baselines' scores and, per mode and metric, the
    higher of their F1s; and the best constant in hindsight (not part of that floor). `predictions`
    are the model's own, per frame_id, of the evaluated `frames`."""
    floor: dict = {"absent": {}}
    partners = other_log_partners(frames)
    if partners:
        # The model is deterministic in eval mode and sees nothing but the sensors, so its prediction
        # from another frame's sensors is its prediction for that frame: no second forward pass.
        pairs = [(predictions[partners[f]], ground_truth[f]) for f in sorted(predictions)]
        floor["other_log_sensors"] = without_params(score_pairs(pairs, params))
    else:
        floor["other_log_sensors"] = None
        log = frames[0]["log_id"] if frames else "none"
        floor["absent"]["other_log_sensors"] = f"the split has a single log ({log}): no other log's sensors"
    if train_ids:
        prior = search_constant_prior(ground_truth, train_ids, train_split, params, cache_dir)
        pairs = [(ground_truth[prior["frame_id"]], ground_truth[f]) for f in sorted(predictions)]
        floor["constant_prior"] = {**prior, **without_params(score_pairs(pairs, params))}
        best = search_best_constant(ground_truth, train_ids, train_split, sorted(predictions), params,
                                    cache_dir)  # fmt: skip
        pairs = [(ground_truth[best["frame_id"]], ground_truth[f]) for f in sorted(predictions)]
        floor["best_constant"] = {**best, **without_params(score_pairs(pairs, params))}
    else:
        floor["constant_prior"] = floor["best_constant"] = None
        floor["absent"]["constant_prior"] = f"no frames in the training split {train_split!r}"
        floor["absent"]["best_constant"] = floor["absent"]["constant_prior"]
    present = [floor[name] for name in ("other_log_sensors", "constant_prior") if floor[name]]
    floor["f1"] = None
    if present:
        floor["f1"] = {mode: {m: max(b[mode][m]["f1"] for b in present) for m in METRICS} for mode in MODES}
    return floor


def without_params(scores: dict) -> dict:
    """A score_pairs result without its thresholds, which are the model's own (metric_params)."""
    return {name: value for name, value in scores.items() if name != "metric_params"}


def floor_margins(metrics: dict) -> dict:
    """Model F1 minus the floor F1 of an evaluation's metrics: {mode: {metric: margin}}, modes directed
    and undirected, metrics topo and junction_topo. For checks such as `margin >= 0.1`."""
    floor = metrics.get("floor")
    if floor is None:
        raise ValueError("the metrics have no floor: evaluated with --no-floor / floor=False")
    if floor["f1"] is None:
        raise ValueError(f"no blind baseline could be scored: {floor['absent']}")
    return {mode: {m: metrics[mode][m]["f1"] - floor["f1"][mode][m] for m in METRICS} for mode in MODES}


def contract_margins(metrics: dict) -> dict:
    """The learning contract's margins, directed: {"sensors": F1 minus the F1 with another log's sensors
    (TOPO), "best_constant": {metric: F1 minus the best constant's in hindsight}}; None where absent."""
    floor = metrics.get("floor") or {}
    other, best = floor.get("other_log_sensors"), floor.get("best_constant")
    directed = metrics["directed"]

    def margins(baseline: dict | None) -> dict | None:
        return {m: directed[m]["f1"] - baseline["directed"][m]["f1"] for m in METRICS} if baseline else None

    return {"sensors": margins(other), "best_constant": margins(best)}
