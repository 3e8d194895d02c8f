"""`cli eval`: predict every frame of a split, turn the paths into a lane graph, score it.

Writes RUN_DIR/predictions.parquet (the `graphs` table schema of docs/guide/prepare.md, the format `cli score`
reads; its metadata records the target parameters the run was trained on) and RUN_DIR/metrics.json: the
TOPO scores plus the parameter count, the frame rates (network only, and with the model's
post-processing to a lane graph), the device, the training's effective batch size, the config and,
unless `floor=False`, the sensor-blind floor and the model's margin over it (baselines/floor.py). Both
are written at the end, atomically: a failed evaluation leaves the earlier ones as they were.

RUN_DIR/frame_counts.parquet, written just before metrics.json, holds each frame's metric sums: the 95 %
intervals beside each F1 come from them (benchmark/metric/bootstrap.py), and so do `cli report`'s paired ones.

On OpenLane-V2 data it also writes RUN_DIR/submission.pkl, the predictions in OpenLane-V2's submission
format (openlanev2_submission), which OpenLane-V2's own tools and `cli score` read.

A dataset prepared with other target parameters than the run's training data is refused (stale data),
and so is a damaged checkpoint or one that would need unpickling (baselines/train.py load_checkpoint).
"""

from __future__ import annotations

import json
import os
import time
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow.compute as pc
import torch
from torch.utils.data import DataLoader
from torch.utils.flop_counter import FlopCounterMode

from baselines.checkpoint import CHOICES, load_checkpoint
from baselines.config import Config
from baselines.data import PreparedDataset, collate
from baselines.device import amp_settings, cuda_settings
from baselines.floor import blind_floor, floor_margins
from baselines.models import Built, build, load_config, without_pretrained_weights
from baselines.run_folder import SUBMISSION
from benchmark.formats.openlanev2_submission import write_submission
from benchmark.graph_table import graphs_from_table, read_graph_table
from benchmark.metric.bootstrap import DRAWS, add_intervals, check_draws
from benchmark.metric.frame import Frame
from benchmark.metric.openlanev2 import annotated_of_graph
from benchmark.metric.params import MetricParams
from benchmark.metric.table import ALWAYS, Metric
from benchmark.score import score_frame_records, write_run
from pipeline import io
from pipeline.lane_graph import LaneGraph
from pipeline.manifest import PreparedData
from pipeline.progress import tracked


def load_model(run_dir: Path, device: torch.device, checkpoint: str = "last") -> tuple[Built, Config, dict]:
    """The run's model (in eval mode on `device`) with its post-processing, the run's config, and where
    the weights come from (the file, its epoch and step); `checkpoint`: last (checkpoint.pt) or best
    (best.pt, the best validation during training)."""
    config = load_config(run_dir / "config.json")
    built = build(without_pretrained_weights(config))  # the checkpoint holds every weight
    path = run_dir / CHOICES[checkpoint]
    if checkpoint == "best" and not path.is_file():
        raise ValueError(f"--checkpoint best: {run_dir} has no {path.name} (it is written by validation "
                         "during training: cli train --eval-every)")  # fmt: skip
    checkpoint_ = load_checkpoint(path)  # weights_only, checksum: a file from elsewhere cannot run code
    try:
        built.model.load_state_dict(checkpoint_["model"])
    except RuntimeError as error:  # other weight names or shapes: another model or an older version
        first = str(error).splitlines()[1].strip() if "\n" in str(error) else str(error)
        raise ValueError(
            f"{path}: its weights do not fit the {config.model} model of config.json ({first})"
        ) from error

    built.to(device).model.eval()
    source = {"checkpoint": checkpoint, "file": path.name, "epoch": checkpoint_["epoch"],
              "step": checkpoint_["step"]}  # fmt: skip
    return built, config, source


def count_gflops(model: torch.nn.Module, sensors) -> float:
    """Forward-pass GFLOPs of one batch by torch's FLOP counter (matmuls and convolutions): a cost that
    does not depend on the machine. Counted with autograd on: the counter's module hooks need every
    input that requires grad to have a grad_fn, which a parameter view under no_grad has not."""
    with FlopCounterMode(display=False) as counter:
        model(sensors)
    return counter.get_total_flops() / 1e9


@dataclass
class Inference:
    """Every frame's predicted lane graph (in the loader's order), the forward pass's GFLOPs, and the
    seconds of the frames after the warm-up: the network's alone, and with the post-processing."""

    graphs: dict[str, LaneGraph]
    gflops: float
    timed_frames: int
    net_seconds: float
    total_seconds: float
    # by frame id, each graph edge's score from the model's instance scores (predict's `edge_scores`)
    edge_scores: dict[str, np.ndarray] | None = None

    def rates(self) -> dict:
        timed = self.timed_frames
        return {
            "fps_net": timed / self.net_seconds if self.net_seconds else 0.0,
            "fps": timed / self.total_seconds if self.total_seconds else 0.0,
            "postprocess_ms": 1000 * (self.total_seconds - self.net_seconds) / timed if timed else 0.0,
        }


def predict(built: Built, loader: DataLoader, device: torch.device, autocast_dtype: torch.dtype | None,
            warmup_frames: int, description: str, count_flops: bool = True,
            edge_scores: bool = False) -> Inference:  # fmt: skip
    """Run the model and its post-processing on every frame of `loader` (batches of one), timing the
    frames after the first `warmup_frames`; the GFLOPs are counted on the first frame (`count_flops`).
    `edge_scores` (for a submission) keeps each edge's score where the model's post-processing gives them
    (Built.scored_graphs), outside the timing, so that the graphs and the frame rates stay the plain ones."""

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    graphs = {}
    scored_graphs = built.scored_graphs if edge_scores else None
    scores = {} if scored_graphs is not None else None
    net_seconds = total_seconds = 0.0
    gflops = 0.0
    frames = len(loader.dataset)
    for index, batch in enumerate(tracked(loader, description, frames)):
        sensors = batch.sensors.to(device)
        if index == 0 and count_flops:
            gflops = count_gflops(built.model, sensors)
        sync()
        start = time.perf_counter()
        autocast = torch.autocast(device.type, dtype=autocast_dtype) if autocast_dtype else nullcontext()
        with torch.no_grad(), autocast:
            outputs = built.model(sensors)
        sync()
        network_done = time.perf_counter()
        graph = built.to_graphs(outputs)[0]
        done = time.perf_counter()
        if index >= warmup_frames:
            net_seconds += network_done - start
            total_seconds += done - start
        graphs[batch.frame_ids[0]] = graph
        if scored_graphs is not None:
            scored_graph, scores[batch.frame_ids[0]] = scored_graphs(outputs)[0]
            same = np.array_equal(scored_graph.src, graph.src) and np.array_equal(scored_graph.dst, graph.dst)
            if not same:  # the scores must be those of this very graph's edges
                raise RuntimeError(f"frame {batch.frame_ids[0]}: the scored post-processing gave other edges")
    return Inference(graphs, gflops, frames - warmup_frames, net_seconds, total_seconds, scores)


Ground = tuple[float, float, float]  # a frame's ground plane: ground_z, a, b (z = ground_z + a x + b y)


def ground_planes(frames: list[dict]) -> dict[str, Ground]:
    """Each prepared frame's ground plane (frames.ground_z, ground_slope), by frame id."""
    return {frame["frame_id"]: (float(frame["ground_z"]), *map(float, frame["ground_slope"]))
            for frame in frames}  # fmt: skip


def scored_frames(graphs: dict[str, LaneGraph], ground_truth: dict[str, LaneGraph], data: PreparedData,
                  grounds: dict[str, Ground], edge_scores: dict[str, np.ndarray] | None = None,
                  ) -> list[Frame]:  # fmt: skip
    """Each predicted frame beside its ground truth, in frame-id order, as the metrics take it; on OpenLane-V2
    data with its annotated lanes, its ground plane and the edges' scores (where the model has them), which
    the openlanev2 metric scores the predicted graph's lanes (with heights from that plane, confidences from
    those scores) against, as `cli score` scores the run's submission.pkl."""
    frame_ids = sorted(graphs)
    if not data.has_annotated_lanes:
        return [Frame(graphs[frame_id], ground_truth[frame_id]) for frame_id in frame_ids]
    lanes = io.read_annotated_lanes(data.path, frame_ids)
    scores = edge_scores or {}
    return [Frame(graphs[f], ground_truth[f], pred_scores=scores.get(f), gt_lanes=lanes[f], ground=grounds[f])
            for f in frame_ids]  # fmt: skip


def score_predictions(
    frames: list[Frame], params: MetricParams, bootstrap: int, metrics: tuple[Metric, ...] = ALWAYS
) -> tuple[dict, np.ndarray]:  # fmt: skip
    """The scores of the predicted frames (scored_frames) with a 95 % interval beside each F1 from
    `bootstrap` draws over them, and each frame's counts (FRAME_COUNTS, for `cli report`'s paired
    intervals); `metrics` adds the other published ones (benchmark/metric/table.py)."""
    scores, frame_counts = score_frame_records(frames, params, metrics=metrics)
    add_intervals(scores, frame_counts, bootstrap)
    return scores, frame_counts


def floor_scores(
    metrics: dict,
    graphs: dict[str, LaneGraph],
    ground_truth: dict[str, LaneGraph],
    dataset: PreparedDataset,
    config: Config,
    params: MetricParams,
    data: PreparedData,
) -> dict:
    """metrics["floor"]: the sensor-blind floor (baselines/floor.py) and the model's margin over it."""
    in_train = pc.field("split") == config.train.train_split
    train_ids = io.read_table(data.path, "frames", ["frame_id"], in_train)["frame_id"].to_pylist()
    floor = blind_floor(
        graphs, ground_truth, dataset.frames, train_ids, config.train.train_split, params,
        data.path / "floor_cache",
    )  # fmt: skip
    floor["margin"] = floor_margins({**metrics, "floor": floor}) if floor["f1"] else None
    return floor


# What a submission's confidences are: from the model's instance scores where its post-processing keeps
# them (Built.scored_graphs: LaneGAP's paths, MapTR's and STSU's pieces), else 1.0 (HDMapNet's rasters).
SCORED = ("each lane's confidence is the mean of its edges' scores, each edge's the highest score of the "
          "model's {instances} that give it")  # fmt: skip
UNSCORED = ("every lane's confidence is 1.0 (the model's post-processing keeps no scores), which makes "
            "OpenLane-V2's DET_l one point of its precision-recall curve")  # fmt: skip


def openlanev2_submission(run_dir: Path, graphs: dict[str, LaneGraph], grounds: dict[str, Ground],
                          data: PreparedData, method: str, edge_scores: dict[str, np.ndarray] | None = None,
                          instances: str = "") -> dict | None:  # fmt: skip
    """On OpenLane-V2 data RUN_DIR/submission.pkl (written atomically): each predicted frame's graph as
    OpenLane-V2's lanes under its submission key (pipeline.io.read_openlanev2_keys), their heights from the
    frame's ground plane, links from the graph, confidences from `edge_scores` (by frame id, one per edge:
    SCORED, naming the model's `instances`) or else 1.0 (UNSCORED), no traffic elements; returns what
    metrics.json says of it. On other data None, and an earlier evaluation's submission is removed: the
    folder holds one evaluation, which that file would not match."""
    path = run_dir / SUBMISSION
    if not data.has_annotated_lanes:
        path.unlink(missing_ok=True)
        return None
    keys = io.read_openlanev2_keys(data.path)
    unknown = sorted(set(graphs) - set(keys))
    if unknown:
        raise ValueError(f"{data.path}: frame {unknown[0]} has no OpenLane-V2 key (split, segment, timestamp)"
                         f"{f' (and {len(unknown) - 1} more)' if len(unknown) > 1 else ''}")  # fmt: skip
    lanes = {keys[frame_id]: annotated_of_graph(graph, grounds[frame_id],
                                                None if edge_scores is None else edge_scores[frame_id])
             for frame_id, graph in graphs.items()}  # fmt: skip
    write_submission(path, method, lanes)
    confidence = UNSCORED if edge_scores is None else SCORED.format(instances=instances)
    return {"path": str(path), "method": method, "frames": len(lanes),
            "lanes": sum(len(frame.points) for frame in lanes.values()),
            "confidence": confidence}  # fmt: skip


def check_options(run_dir: Path, device: str | None) -> None:
    """`cli eval`'s refusals before any work, each in one line: --device cuda where torch has no CUDA, a --run
    that is no folder or holds no config.json."""
    if device == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device cuda: CUDA is not available to torch {torch.__version__} here")
    if not run_dir.is_dir():
        raise ValueError(f"--run {run_dir}: no such folder")
    if not (run_dir / "config.json").is_file():
        raise ValueError(f"--run {run_dir}: no config.json (expected a run folder written by cli train)")


def evaluate(
    run_dir: Path,
    data_dir: Path | None = None,
    split: str | None = None,
    device: str | None = None,
    warmup_frames: int = 5,
    floor: bool = True,
    bootstrap: int = DRAWS,
    checkpoint: str = "last",
    metrics: tuple[Metric, ...] = ALWAYS,
) -> dict:
    """Predict, post-process to lane graphs, score, and score the blind floor (`floor`,
    baselines/floor.py); returns (and writes) the metrics, with a 95 % interval beside each F1 from
    `bootstrap` draws over the frames (0: none), with the weights of `checkpoint` (last or best). The floor's
    prior search is cached in DATA/floor_cache. `metrics`: LaneGAP's and the other published ones chosen
    (benchmark/metric/table.py; LaneGAP's among them), each other one under its name in metrics.json."""
    run_dir = Path(run_dir)
    check_options(run_dir, device)
    check_draws(bootstrap)
    device_ = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    built, config, source = load_model(run_dir, device_, checkpoint)
    cuda_settings(device_)  # the frame rates under the training's settings
    if config.train.threads and device_.type == "cpu":
        torch.set_num_threads(config.train.threads)
    run = json.loads((run_dir / "run.json").read_text())
    data = PreparedData.open(data_dir or run["data"])
    data.check_targets(run.get("targets", {}), f"the run {run_dir}")
    split = split or config.train.val_split
    dataset = PreparedDataset(data, split, config, built.needs)
    workers = min(config.data.num_workers, os.cpu_count() or 1)
    loader = DataLoader(dataset, batch_size=1, num_workers=workers, collate_fn=collate)
    autocast_dtype, _ = amp_settings(device_, config.train.amp)
    warmup_frames = min(warmup_frames, len(dataset) - 1)  # time at least one frame
    inference = predict(built, loader, device_, autocast_dtype, warmup_frames, f"predict {split}",
                        edge_scores=data.has_annotated_lanes)  # fmt: skip

    # `cli score` scores every frame of the ground truth; here only the frames of this split.
    ground_truth = graphs_from_table(read_graph_table(data.path), data.path)
    metric_params = MetricParams(bev_range=data.bev_range)
    grounds = ground_planes(dataset.frames)
    frames = scored_frames(inference.graphs, ground_truth, data, grounds, inference.edge_scores)
    scores, frame_counts = score_predictions(frames, metric_params, bootstrap, metrics)
    metrics = {
        **scores, "pred": str(run_dir / "predictions.parquet"), "gt": str(data.path),
        "frames_predicted": len(inference.graphs), "split": split, "data": str(data.path),
        "params": sum(p.numel() for p in built.model.parameters()),  # the thresholds: metric_params
        "model": config.model,
        "weights": source,  # which checkpoint: its file, epoch and step
        "modeling": built.modeling,
        # torch's FLOP counter (forward pass, batch 1): matmuls and convolutions; the deformable
        # attention's bilinear sampling and the LiDAR scatter are not counted
        "gflops": inference.gflops,
        **inference.rates(),
        "device": torch.cuda.get_device_name(device_) if device_.type == "cuda" else "cpu",
        "precision": f"{str(autocast_dtype).removeprefix('torch.')} autocast" if autocast_dtype else "fp32",
        "world_size": run.get("world_size", 1),  # the training's processes and batch over all of them
        "effective_batch_size": run.get("effective_batch_size", config.train.batch_size),
    }
    if floor:
        metrics["floor"] = floor_scores(
            metrics, inference.graphs, ground_truth, dataset, config, metric_params, data
        )
    submission = openlanev2_submission(run_dir, inference.graphs, grounds, data, f"lanegraph {config.model}",
                                       inference.edge_scores, f"{built.modeling}s")  # fmt: skip
    if submission is not None:
        metrics["submission"] = submission
    metrics["config"] = config.to_dict()
    write_run(run_dir, inference.graphs, frame_counts, metrics, run.get("targets", {}))
    return metrics
