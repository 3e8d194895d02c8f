"""`cli score`: read predicted and ground-truth graph tables, check them, score them, write JSON.

A graph table has one row per frame: `frame_id: string, x: list<float32>, y: list<float32>,
src: list<int32>, dst: list<int32>` (docs/DATA.md). The ground truth is the `graphs` table of a
prepared dataset (a folder) or one such file; predictions are one file (or a folder of shards).
The ground-truth frames scored are those of the predicted frames' split(s) (a prepared dataset's `frames`
table; `--split` names one): a frame of the ground truth without a prediction row is scored as an empty
prediction; a predicted frame id that is not in the ground truth is refused (a typo or another dataset,
never silently dropped).

Stale data is refused: predictions written by `cli eval` record the target parameters of the dataset
their model was trained on (TARGETS_KEY in the Parquet metadata), and a prepared ground truth made with
other ones is an error naming the parameter.
"""

from __future__ import annotations

import json
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq

from benchmark import external
from benchmark.bootstrap import FRAME_COUNTS, add_intervals, check_draws, write_frame_counts
from benchmark.metrics import METRIC_VERSION, MetricParams, Totals
from pipeline import io
from pipeline.geometry import Range
from pipeline.lane_graph import LaneGraph
from pipeline.manifest import check_targets
from pipeline.progress import track

COLUMNS = ("frame_id", "x", "y", "src", "dst")
# what metrics.json's "external" says of a result file besides its format and options
EXTERNAL_COUNTS = ("frames_in_file", "frames_not_in_file", "vectors_read", "vectors_kept", "points_clipped")
TARGETS_KEY = b"lanegraph_targets"  # Parquet metadata of predictions: the targets their model trained on


class GraphTableError(ValueError):
    """A graph table that cannot be scored; the message names the file and, where known, the frame."""


def read_graph_table(path: Path) -> pa.Table:
    """A graph-table file or folder of shards, or the `graphs` table of a prepared dataset."""
    path = Path(path)
    if not path.exists():
        raise GraphTableError(f"{path}: no such file or folder")
    if path.is_dir() and (path / "graphs").is_dir():
        path = path / "graphs"
    try:
        table = ds.dataset(path, format="parquet").to_table()
    except (pa.ArrowInvalid, OSError) as error:
        raise GraphTableError(f"{path}: not a readable Parquet graph table ({error})") from error
    missing = [c for c in COLUMNS if c not in table.column_names]
    if missing:
        raise GraphTableError(
            f"{path}: missing column(s) {', '.join(missing)}; a graph table has {', '.join(COLUMNS)}"
        )
    return table


def _flat(
    table: pa.Table, name: str, path: Path, frame_ids: list[str], dtype
) -> tuple[np.ndarray, np.ndarray]:
    """(values, offsets) of a list column, as numpy."""
    column = table.column(name).combine_chunks()
    kind = (
        (lambda t: pa.types.is_floating(t) or pa.types.is_integer(t))
        if dtype == np.float64
        else pa.types.is_integer
    )
    if not (pa.types.is_list(column.type) or pa.types.is_large_list(column.type)) or not kind(
        column.type.value_type
    ):
        expected = "a list of numbers" if dtype == np.float64 else "a list of integers"
        raise GraphTableError(f"{path}: column {name} is {column.type}, not {expected}")
    if column.null_count:
        row = int(np.flatnonzero(column.is_null().to_numpy(zero_copy_only=False))[0])
        raise GraphTableError(f"{path}: frame {frame_ids[row]}: {name} is null")
    offsets = column.offsets.to_numpy().astype(np.int64)
    if column.values.null_count:
        at = np.flatnonzero(column.values.is_null().to_numpy(zero_copy_only=False))[0]
        raise GraphTableError(
            f"{path}: frame {frame_ids[np.searchsorted(offsets, at, 'right') - 1]}: null in {name}"
        )
    values = column.values.to_numpy(zero_copy_only=False).astype(dtype)
    return values[offsets[0] : offsets[-1]], offsets - offsets[0]


def graphs_from_table(table: pa.Table, path: Path) -> dict[str, LaneGraph]:
    """{frame_id: graph}, after checking every row; the first bad row raises GraphTableError."""
    ids = table.column("frame_id")
    if ids.null_count:
        raise GraphTableError(f"{path}: a row has no frame_id")
    frame_ids = [str(f) for f in ids.to_pylist()]
    x, x_off = _flat(table, "x", path, frame_ids, np.float64)  # float32 in the schema; float64 loses nothing
    y, y_off = _flat(table, "y", path, frame_ids, np.float64)
    src, src_off = _flat(table, "src", path, frame_ids, np.int64)
    dst, dst_off = _flat(table, "dst", path, frame_ids, np.int64)

    def fail(bad: np.ndarray, problem: str) -> None:
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise GraphTableError(f"{path}: frame {frame_ids[row]}: {problem}")

    n_vertices, n_edges = np.diff(x_off), np.diff(src_off)
    fail(np.diff(y_off) != n_vertices, "x and y have different lengths")
    fail(np.diff(dst_off) != n_edges, "src and dst have different lengths")
    row_of_vertex, row_of_edge = (
        np.repeat(np.arange(len(frame_ids)), n_vertices),
        np.repeat(np.arange(len(frame_ids)), n_edges),
    )
    bad_value = ~(np.isfinite(x) & np.isfinite(y))
    fail(np.bincount(row_of_vertex[bad_value], minlength=len(frame_ids)) > 0, "x or y is NaN or infinite")
    limit = n_vertices[row_of_edge]
    bad_index = (src < 0) | (src >= limit) | (dst < 0) | (dst >= limit)
    fail(np.bincount(row_of_edge[bad_index], minlength=len(frame_ids)) > 0, "an edge index is out of range")
    unique, counts = np.unique(frame_ids, return_counts=True)
    if (counts > 1).any():
        raise GraphTableError(f"{path}: frame {unique[counts > 1][0]}: more than one row")
    return {
        f: LaneGraph(
            x[x_off[i] : x_off[i + 1]],
            y[y_off[i] : y_off[i + 1]],
            src[src_off[i] : src_off[i + 1]].astype(np.int32),
            dst[dst_off[i] : dst_off[i + 1]].astype(np.int32),
        )  # fmt: skip
        for i, f in enumerate(frame_ids)
    }


def graph_row(frame_id: str, graph: LaneGraph) -> dict:
    """The graph-table row of one frame's graph (graphs_from_table's inverse)."""
    return {
        "frame_id": frame_id,
        "x": np.asarray(graph.x, np.float32).tolist(),
        "y": np.asarray(graph.y, np.float32).tolist(),
        "src": np.asarray(graph.src, np.int32).tolist(),
        "dst": np.asarray(graph.dst, np.int32).tolist(),
    }


def _score_chunk(chunk: list[tuple[LaneGraph, LaneGraph]], params: MetricParams) -> Totals:
    totals = Totals(params)
    for pred, gt in chunk:
        totals.add_frame(pred, gt)
    return totals


def score_pairs(
    pairs: list[tuple[LaneGraph, LaneGraph]], params: MetricParams, workers: int = 1, bootstrap: int = 0
) -> dict:
    """The result dict for (pred, gt) graphs, one pair per frame, in `workers` processes (0: one per
    core); with `bootstrap` draws, a 95 % interval beside each F1 (benchmark/bootstrap.py)."""
    result, counts = score_frames(pairs, params, workers)
    return add_intervals(result, counts, bootstrap)


def score_frames(
    pairs: list[tuple[LaneGraph, LaneGraph]], params: MetricParams, workers: int = 1
) -> tuple[dict, np.ndarray]:
    """(score_pairs' result without intervals, each pair's counts: (frames, FRAME_COLUMNS) in pair
    order)."""
    workers = workers if workers > 0 else os.cpu_count() or 1
    totals = Totals(params)
    with track("score frames", len(pairs)) as advance:
        if workers <= 1 or len(pairs) < 2 * workers:
            for pred, gt in pairs:
                totals.add_frame(pred, gt)
                advance()
        else:
            size = max(1, min(64, len(pairs) // (4 * workers)))
            chunks = [pairs[i : i + size] for i in range(0, len(pairs), size)]
            with ProcessPoolExecutor(workers) as pool:
                for part in pool.map(_score_chunk, chunks, [params] * len(chunks)):
                    totals.add(part)  # exact sums: the chunking does not change a digit
                    advance(part.frames)
    return {**totals.result(), "metric_version": METRIC_VERSION}, totals.frame_table()


def default_range(gt_path: Path) -> str:
    """The perception range a prepared dataset was cut to (its manifest), else 30x60."""
    manifest = Path(gt_path) / "manifest.json"
    if manifest.is_file():
        return json.loads(manifest.read_text()).get("parameters", {}).get("bev_range", "30x60")
    return "30x60"


def write_result(result: dict, out: Path | None) -> None:
    if out is not None:  # atomic: a failed run leaves an earlier file as it was
        io.write_json(Path(out), result)


def frame_splits(gt_path: Path) -> dict[str, str] | None:
    """{frame_id: split} of a prepared dataset's `frames` table; None for a graph-table file."""
    if not (Path(gt_path) / "frames").is_dir():
        return None
    table = io.read_table(Path(gt_path), "frames", columns=["frame_id", "split"])
    return dict(zip(table.column("frame_id").to_pylist(), table.column("split").to_pylist()))


def scored_frames(
    pred: dict, gt: dict, gt_path: Path, pred_path: Path, split: str | None
) -> tuple[list[str], list[str] | None]:
    """(frame ids to score, their splits): the ground truth's frames of `split`, by default of the splits
    the predicted frames belong to; every frame (splits None) of a graph-table file, which has no splits."""
    split_of = frame_splits(gt_path)
    if split_of is None:
        if split:
            raise GraphTableError(
                f"--split {split}: the ground truth {gt_path} is a graph-table file without splits; pass a "
                "prepared dataset (cli prepare --out)"
            )
        return sorted(gt), None
    if split:
        if split not in set(split_of.values()):
            known = ", ".join(sorted(set(split_of.values())))
            raise GraphTableError(f"--split {split}: no such split in {gt_path} (its splits: {known})")
        outside = sorted(f for f in pred if split_of.get(f) != split)
        if outside:
            raise GraphTableError(
                f"{pred_path}: frame {outside[0]} is in split {split_of.get(outside[0])!r}, not in "
                f"--split {split}"
            )
    elif not pred:
        raise GraphTableError(
            f"{pred_path}: no predicted frame; pass --split to score a split's frames as empty"
        )
    splits = [split] if split else sorted({split_of[f] for f in pred})
    return sorted(f for f in gt if split_of.get(f) in splits), splits


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


def read_predictions(pred_path: Path, gt_path: Path) -> dict[str, LaneGraph]:
    """A graph table's frames, after the stale-data check of the targets its model trained on."""
    pred_table = read_graph_table(pred_path)
    trained = json.loads((pred_table.schema.metadata or {}).get(TARGETS_KEY, b"{}"))
    check_targets(trained, Path(gt_path), f"the model of {pred_path}")
    return graphs_from_table(pred_table, Path(pred_path))


def graph_predictions(pred: dict, pred_path: Path, gt_path: Path, gt: dict, split: str | None
                      ) -> tuple[dict[str, LaneGraph], list[str], dict]:  # fmt: skip
    """A graph table's frames scored: the ground truth's of the predicted frames' split(s), a frame
    without a prediction row an empty prediction."""
    unknown = sorted(set(pred) - set(gt))
    if unknown:
        raise GraphTableError(f"{pred_path}: frame {unknown[0]} is not in the ground truth {gt_path}")
    frame_ids, splits = scored_frames(pred, gt, Path(gt_path), Path(pred_path), split)
    missing = sum(f not in pred for f in frame_ids)
    graphs = {f: pred.get(f, LaneGraph.empty()) for f in frame_ids}
    info = {"splits": splits, "frames_predicted": len(pred), "frames_missing": missing}
    return graphs, frame_ids, {**info, "frames_in_file": len(pred), "frames_not_in_file": 0}


@dataclass
class ExternalFile:
    """A result file of another codebase, read and matched to the ground truth's frames."""

    vectors: external.Vectors
    frame_ids: list[str]  # each sample's frame
    dataset: str
    fmt: str
    rng: Range
    workers: int

    def graphs(self, min_score: float) -> external.Converted:
        return external.to_graphs(
            self.vectors, self.frame_ids, self.fmt, self.dataset, self.rng, min_score, self.workers
        )


def external_predictions(
    pred_path: Path, gt_path: Path, fmt: str, class_name: str, min_score: float, split: str | None,
    workers: int, parsed: dict | None = None,
) -> tuple[dict[str, LaneGraph], list[str], dict, ExternalFile]:  # fmt: skip
    """The frames of the file alone (a split's frames it lacks are counted, not scored as empty); `parsed`:
    the file's JSON when `--format auto` read it already."""
    vectors = external.read_vectors(pred_path, fmt, class_name, parsed)
    frame_ids, dataset = external.frame_ids_of(vectors.tokens, gt_path, pred_path)
    split_of = frame_splits(gt_path)
    if split:
        if split not in set(split_of.values()):
            known = ", ".join(sorted(set(split_of.values())))
            raise GraphTableError(f"--split {split}: no such split in {gt_path} (its splits: {known})")
        outside = [(t, f) for t, f in zip(vectors.tokens, frame_ids) if split_of[f] != split]
        if outside:
            raise GraphTableError(
                f"{pred_path}: {len(outside)} samples are not of --split {split}, e.g. {outside[0][0]} "
                f"({outside[0][1]}, split {split_of[outside[0][1]]})"
            )
    if not frame_ids:
        raise GraphTableError(f"{pred_path}: no sample in its results list")
    splits = sorted({split_of[f] for f in frame_ids})
    workers = workers if workers > 0 else os.cpu_count() or 1
    source = ExternalFile(vectors, frame_ids, dataset, fmt, Range.parse(default_range(gt_path)), workers)
    converted = source.graphs(min_score)
    in_splits = sum(s in splits for s in split_of.values())
    info = {
        "splits": splits,
        "frames_predicted": len(frame_ids),
        "frames_missing": 0,
        "frames_in_file": len(frame_ids),
        "frames_not_in_file": in_splits - len(frame_ids),
        "vectors_read": vectors.read,
        "vectors_kept": converted.kept,
        "points_clipped": converted.clipped,
    }
    return converted.graphs, sorted(frame_ids), info, source


def sweep_scores(source: ExternalFile, gt: dict, params: MetricParams, min_scores) -> list[dict]:
    """F1 of each kept score (no intervals): how much the choice of --min-score matters."""
    rows = []
    for min_score in min_scores:
        converted = source.graphs(min_score)
        pairs = [(converted.graphs[f], gt[f]) for f in sorted(converted.graphs)]
        result, _ = score_frames(pairs, params, source.workers)
        rows.append({"min_score": min_score, "vectors_kept": converted.kept,
                     **{mode: {m: result[mode][m]["f1"] for m in ("topo", "junction_topo")}
                        for mode in ("directed", "undirected")}})  # fmt: skip
    return rows


def resolve_format(pred_path: Path, fmt: str, class_name: str | None, min_score: float | None, sweep: bool
                   ) -> tuple[str, str | None, float | None, dict | None]:  # fmt: skip
    """(format, class name, kept score, the JSON if `auto` parsed it) after `auto` and the defaults;
    options of another format refused."""
    parsed = None
    if fmt == "auto":
        fmt, parsed = external.detect_format(pred_path)
    if fmt not in external.FORMATS:
        raise GraphTableError(f"--format {fmt}: expected one of graph, maptrv2, cgnet, auto")
    if fmt == "graph":
        given = [
            name
            for name, value in (("--class-name", class_name), ("--min-score", min_score))
            if value is not None
        ]
        if given or sweep:
            raise GraphTableError(
                f"{', '.join(given + ['--sweep'] * sweep)}: only for a result file of another codebase "
                f"(--format maptrv2, cgnet or auto); {pred_path} is read as a graph table"
            )
        external.refuse_pickle(Path(pred_path))
        if Path(pred_path).is_file() and Path(pred_path).suffix.lower() == ".json":
            raise GraphTableError(
                f"{pred_path}: a JSON file, not a graph table; pass --format maptrv2 or cgnet (or auto)"
            )
        return fmt, None, None, None
    class_name = class_name or "centerline"
    if class_name not in external.CLASSES[fmt]:
        raise GraphTableError(
            f"--class-name {class_name}: not a {fmt} class ({', '.join(external.CLASSES[fmt])})"
        )
    return fmt, class_name, external.MIN_SCORE[fmt] if min_score is None else min_score, parsed


def score(
    pred_path: Path, gt_path: Path, out: Path | None = None, workers: int = 1, bootstrap: int = 0,
    split: str | None = None, fmt: str = "graph", class_name: str | None = None,
    min_score: float | None = None, sweep: bool = False, **params,
) -> dict:  # fmt: skip
    """Score predictions against the ground truth; params are MetricParams fields; `bootstrap` draws over
    the frames give each F1 its 95 % interval (0: none; `cli score`: DRAWS).

    fmt "graph": a graph table. The frames of `split` are scored (by default the split or splits of the
    predicted frames, from a prepared dataset's `frames` table; every frame of a graph-table file). One
    with no prediction row counts as an empty prediction (`frames_missing`); a predicted frame that is
    not in the ground truth, or not in `split`, is refused.
    fmt "maptrv2" / "cgnet" (or "auto"): another codebase's JSON (benchmark/external.py); the frames in
    the file are scored, and the split's frames it lacks are counted (`frames_not_in_file`); `sweep`
    adds the F1 at each of external.SWEEP's kept scores.
    `out`: a .json file of the result, or a run folder (`write_run`) that `cli report` reads.
    """
    check_draws(bootstrap)
    fmt, class_name, min_score, parsed = resolve_format(Path(pred_path), fmt, class_name, min_score, sweep)
    check_out(out)
    params.setdefault("bev_range", default_range(gt_path))
    metric_params = MetricParams(**params)
    source, pred = None, read_predictions(pred_path, gt_path) if fmt == "graph" else None
    gt = graphs_from_table(read_graph_table(gt_path), Path(gt_path))
    if fmt == "graph":
        graphs, frame_ids, info = graph_predictions(pred, Path(pred_path), Path(gt_path), gt, split)
    else:
        graphs, frame_ids, info, source = external_predictions(
            Path(pred_path), Path(gt_path), fmt, class_name, min_score, split, workers, parsed
        )
    pairs = [(graphs[f], gt[f]) for f in frame_ids]
    result, frame_counts = score_frames(pairs, metric_params, workers)
    add_intervals(result, frame_counts, bootstrap)
    counts = {key: info.pop(key, None) for key in EXTERNAL_COUNTS}
    result.update(pred=str(pred_path), gt=str(gt_path), **info)
    run_folder = out is not None and Path(out).suffix.lower() != ".json"
    if fmt != "graph" or run_folder:  # what `cli report` says of a model that is not ours
        digest = external.sha256(Path(pred_path)) if Path(pred_path).is_file() else None
        result["external"] = {"format": fmt, "source": str(pred_path), "sha256": digest,
                              "class_name": class_name, "min_score": min_score, **counts}  # fmt: skip
    if sweep:
        result["sweep"] = sweep_scores(source, gt, metric_params, sorted({*external.SWEEP, min_score}))
    if run_folder:
        split_text = "+".join(result["splits"] or []) or None
        metrics = {**result, "data": str(Path(gt_path).resolve()), "split": split_text,
                   "model": "external", "modeling": external.MODELING[fmt], "params": None, "gflops": None,
                   "fps_net": None, "fps": None, "device": None, "precision": None}  # fmt: skip
        write_run(Path(out), graphs, frame_counts, metrics)
    else:
        write_result(result, out)
    return result
