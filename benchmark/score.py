"""`cli score`: check the options, open the ground truth, read the predictions in one step, score them, write
the result (a JSON file or a run folder); also the scoring of (pred, gt) pairs that others call.

The predictions are read by the reader of their format (benchmark/formats/: a graph table, or a result
file of another codebase) into one `Predictions`: each frame to score, as the metrics take it (`Frame`), and
what the result says of the file. The ground truth is the `graphs` table of a prepared dataset (a folder)
or one graph-table file (benchmark/graph_table.py); an OpenLane-V2 prepared dataset also gives each frame its
annotated lanes and ground plane, for the openlanev2 metric's lane path.
"""

from __future__ import annotations

import json
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from benchmark import formats
from benchmark.formats.base import GroundTruth, Options, Predictions
from benchmark.graph_table import (
    TARGETS_KEY,
    GraphTableError,
    default_range,
    graph_row,
    graphs_from_table,
    read_graph_table,
)
from benchmark.metric.bootstrap import FRAME_COUNTS, add_intervals, check_draws, write_frame_counts
from benchmark.metric.frame import Frame
from benchmark.metric.params import MetricParams
from benchmark.metric.table import ALWAYS, Contributions, Metric
from pipeline import io
from pipeline.geometry import Range
from pipeline.lane_graph import LaneGraph
from pipeline.manifest import PreparedData
from pipeline.progress import track


def _score_chunk(chunk: list[Frame], params: MetricParams, metrics: tuple[Metric, ...]) -> Contributions:
    part = Contributions(metrics, params)
    for frame in chunk:
        part.add_frame(frame)
    return part


def score_pairs(
    pairs: list[tuple[LaneGraph, LaneGraph]], params: MetricParams, workers: int = 1, bootstrap: int = 0,
    metrics: tuple[Metric, ...] = ALWAYS,
) -> dict:  # fmt: skip
    """The result dict for (pred, gt) graphs, one pair per frame, in `workers` processes (0: one per
    core); with `bootstrap` draws, a 95 % interval beside each LaneGAP F1 (benchmark/metric/bootstrap.py)."""
    result, counts = score_frames(pairs, params, workers, metrics)
    return add_intervals(result, counts, bootstrap) if counts is not None else result


def score_frames(
    pairs: list[tuple[LaneGraph, LaneGraph]], params: MetricParams, workers: int = 1,
    metrics: tuple[Metric, ...] = ALWAYS, pred_scores: list[np.ndarray | None] | None = None,
) -> tuple[dict, np.ndarray | None]:  # fmt: skip
    """(score_pairs' result without intervals, each pair's LaneGAP counts: (frames, FRAME_COLUMNS) in pair
    order, None without LaneGAP's metric). `metrics` (benchmark/metric/table.py): LaneGAP's at the top level,
    each other one under its name, all scored per frame in the same workers. `pred_scores`, parallel to
    `pairs`: each prediction's edge scores (one per edge of its graph, or None: no score), OpenLane-V2's
    lane confidences."""
    if pred_scores is not None and len(pred_scores) != len(pairs):
        raise ValueError(f"pred_scores: one per pair ({len(pairs)}) is needed, not {len(pred_scores)}")
    scores = list(pred_scores) if pred_scores is not None else [None] * len(pairs)
    frames = [Frame(pred, gt, frame_scores) for (pred, gt), frame_scores in zip(pairs, scores)]
    return score_frame_records(frames, params, workers, metrics)


def score_frame_records(frames: list[Frame], params: MetricParams, workers: int = 1,
                        metrics: tuple[Metric, ...] = ALWAYS) -> tuple[dict, np.ndarray | None]:  # fmt: skip
    """score_frames of the frames as the metrics take them (a format's reader gives them so)."""
    workers = workers if workers > 0 else os.cpu_count() or 1
    scored = Contributions(metrics, params)
    with track("score frames", len(frames)) as advance:
        if workers <= 1 or len(frames) < 2 * workers:
            for frame in frames:
                scored.add_frame(frame)
                advance()
        else:
            size = max(1, min(64, len(frames) // (4 * workers)))
            chunks = [frames[i : i + size] for i in range(0, len(frames), size)]
            with ProcessPoolExecutor(workers) as pool:
                parts = pool.map(_score_chunk, chunks, [params] * len(chunks), [metrics] * len(chunks))
                for chunk, part in zip(chunks, parts):
                    scored.add(part)  # in chunk order, so in pair order; LaneGAP's exact sums: no digit moves
                    advance(len(chunk))
    return scored.result(), scored.frame_counts()


def sweep_scores(pred: Predictions, gt: dict[str, LaneGraph], params: MetricParams,
                 workers: int) -> list[dict]:  # fmt: skip
    """F1 of each kept score (no intervals): how much the choice of --min-score matters."""
    rows = []
    for swept in pred.sweep():
        pairs = [(swept.graphs[f], gt[f]) for f in sorted(swept.graphs)]
        result, _ = score_frames(pairs, params, workers)
        rows.append({"min_score": swept.min_score, "vectors_kept": swept.vectors_kept,
                     **{mode: {m: result[mode][m]["f1"] for m in ("topo", "junction_topo")}
                        for mode in ("directed", "undirected")}})  # fmt: skip
    return rows


def write_result(result: dict, out: Path | None) -> None:
    if out is not None:  # atomic: a failed run leaves an earlier file as it was
        io.write_json(Path(out), result)


def check_out(out: Path | None) -> None:
    """`--out`: a .json file, or a run folder that is not one of our trained runs (checked up front)."""
    if out is None or Path(out).suffix.lower() == ".json":
        return
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise GraphTableError(f"--out {out}: a file that is not .json; name a .json file or a run folder")
    for name in ("config.json", "checkpoint.pt"):
        if (out / name).exists():
            raise GraphTableError(
                f"--out {out}: holds a trained run ({name}); write the external run to another folder"
            )


def check_metrics(metrics: tuple[Metric, ...], out: Path | None, sweep: bool) -> None:
    """A run folder (`cli report` reads its LaneGAP scores) and `--sweep` (LaneGAP's F1 by kept score) need
    the always-computed metric, LaneGAP's, among the chosen."""
    if all(metric in metrics for metric in ALWAYS):
        return
    names = ",".join(metric.name for metric in ALWAYS)
    if sweep:
        raise GraphTableError(f"--sweep: it sweeps LaneGAP's F1; add {names} to --metric")
    if out is not None and Path(out).suffix.lower() != ".json":
        raise GraphTableError(f"--out {out}: a run folder holds LaneGAP's scores for cli report; add {names} "
                              "to --metric or write a .json file")  # fmt: skip


def write_run(run_dir: Path, graphs: dict[str, LaneGraph], frame_counts: np.ndarray, metrics: dict,
              targets: dict | None = None) -> None:  # fmt: skip
    """A run folder as `cli report` reads it: predictions.parquet (its metadata: the targets the model
    trained on, when known), frame_counts.parquet (rows in sorted frame order, as the counts) and
    metrics.json last, each written atomically."""
    schema = io.SCHEMAS["graphs"]
    if targets is not None:
        schema = schema.with_metadata({TARGETS_KEY: json.dumps(targets)})
    rows = [graph_row(frame_id, graphs[frame_id]) for frame_id in sorted(graphs)]
    table = pa.Table.from_pylist(rows, schema)
    io.write_atomic(Path(run_dir) / "predictions.parquet", lambda tmp: pq.write_table(table, tmp))
    write_frame_counts(Path(run_dir) / FRAME_COUNTS, sorted(graphs), frame_counts)
    io.write_json(Path(run_dir) / "metrics.json", metrics)


def frames_of(pred: Predictions, gt: dict[str, LaneGraph], gt_path: Path) -> list[Frame]:
    """Each predicted frame beside its ground truth as the metrics take it; with OpenLane-V2 ground truth
    also its annotated lanes and its ground plane (frames.ground_z, ground_slope)."""
    if not PreparedData.open(gt_path).has_annotated_lanes:
        return [prediction.frame(gt[prediction.frame_id]) for prediction in pred]
    frame_ids = [prediction.frame_id for prediction in pred]
    lanes = io.read_annotated_lanes(gt_path, frame_ids)
    table = io.read_table(gt_path, "frames", columns=["frame_id", "ground_z", "ground_slope"])
    ground = {frame_id: (float(z), float(slope[0]), float(slope[1])) for frame_id, z, slope in zip(
        *(table.column(name).to_pylist() for name in ("frame_id", "ground_z", "ground_slope")))}  # fmt: skip
    return [p.frame(gt[p.frame_id], lanes[p.frame_id], ground[p.frame_id]) for p in pred]


def check_range(bev_range: str, gt_path: Path) -> None:
    """--range within the ground truth's own crop: beyond it the ground truth has no lanes, and predictions
    there would count as false ones."""
    recorded = PreparedData.open(gt_path).manifest.get("parameters", {}).get("bev_range")
    if recorded is None:  # a graph table, or a folder whose manifest says nothing of its crop
        return
    wanted, prepared = Range.parse(bev_range), Range.parse(recorded)
    if wanted.x_max > prepared.x_max or wanted.y_max > prepared.y_max:
        raise ValueError(f"--range {bev_range}: wider than the ground truth {gt_path}, prepared at "
                         f"{prepared.text}: beyond it there is no ground truth; score at {prepared.text} "
                         "or less, or prepare at the wider range")  # fmt: skip


def score(
    pred_path: Path, gt_path: Path, out: Path | None = None, workers: int = 1, bootstrap: int = 0,
    split: str | None = None, fmt: str = formats.AUTO, class_name: str | None = None,
    min_score: float | None = None, sweep: bool = False, metrics: tuple[Metric, ...] = ALWAYS, **params,
) -> dict:  # fmt: skip
    """Score predictions against the ground truth; params are MetricParams fields; `bootstrap` draws over
    the frames give each F1 its 95 % interval (0: none; `cli score`: DRAWS). `metrics`: LaneGAP's (the
    result's top level) and the other published ones (benchmark/metric/table.py, each under its name).

    fmt: a format's name (benchmark/formats/: "graph", "maptrv2", "cgnet") or "auto", told by the file's
    content; which frames are scored for `split`: its reader's docstring. `sweep` (a format with scores)
    adds the F1 at each of formats.base.SWEEP's kept scores. `out`: a .json file of the result, or a run
    folder (`write_run`) that `cli report` reads.
    """
    check_draws(bootstrap)
    options = Options(class_name, min_score, sweep)
    reader, source = formats.checked(pred_path, fmt, options)
    check_out(out)
    check_metrics(metrics, out, sweep)
    # one spelling of a range (50.0X100 as 50x100): cli report compares runs' ranges as text
    params["bev_range"] = Range.parse(params.get("bev_range") or default_range(gt_path)).text
    check_range(params["bev_range"], Path(gt_path))
    metric_params = MetricParams(**params)
    gt = graphs_from_table(read_graph_table(gt_path), Path(gt_path))
    truth = GroundTruth(Path(gt_path), gt, split, workers if workers > 0 else os.cpu_count() or 1,
                        Range.parse(metric_params.bev_range))  # fmt: skip
    pred = reader.read(source, options, truth)
    frames = frames_of(pred, gt, Path(gt_path))
    result, frame_counts = score_frame_records(frames, metric_params, workers, metrics)
    if frame_counts is not None:
        add_intervals(result, frame_counts, bootstrap)
    result.setdefault("frames", len(frames))
    result.update(pred=str(pred_path), gt=str(gt_path), **pred.info())
    run_folder = out is not None and Path(out).suffix.lower() != ".json"
    if pred.format.external or run_folder:  # what `cli report` says of a model that is not ours
        result["external"] = pred.provenance()
    if sweep:
        result["sweep"] = sweep_scores(pred, gt, metric_params, workers)
    if run_folder:
        split_text = "+".join(result["splits"] or []) or None
        metrics = {**result, "data": str(Path(gt_path).resolve()), "split": split_text,
                   "model": "external", "modeling": pred.format.modeling, "params": None, "gflops": None,
                   "fps_net": None, "fps": None, "device": None, "precision": None}  # fmt: skip
        write_run(Path(out), pred.graphs, frame_counts, metrics)
    else:
        write_result(result, out)
    return result
