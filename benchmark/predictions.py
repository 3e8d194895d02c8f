"""The predictions `cli score` scores, read in one step: a graph table or another codebase's result file in,
one `Predictions` out (graphs by frame id, the frames to score, the counts and provenance the result records).

`request` checks `--pred` and the options of its format before any work; `read` reads the file and matches
it to the ground truth's frames:
- "graph", our graph table (benchmark/graph_table.py): the frames of `split` are scored (by default the
  split or splits of the predicted frames, from a prepared dataset's `frames` table; every frame of a
  graph-table file). One with no prediction row counts as an empty prediction (`frames_missing`); a
  predicted frame that is not in the ground truth (a typo or another dataset), or not in `split`, is
  refused, never dropped unsaid. Stale data is refused: predictions written by `cli eval` record the
  target parameters of the dataset their model was trained on, and a prepared ground truth made with
  other ones is an error naming the parameter.
- "maptrv2" / "cgnet": another codebase's JSON (benchmark/external.py), converted to graphs at the kept
  score; the frames in the file are scored, the split's frames it lacks counted (`frames_not_in_file`).
  `Predictions.sweep` converts it again at each of external.SWEEP's kept scores.
- "auto": one of those, told apart by the file's content (external.detect_format).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmark import external
from benchmark.graph_table import (
    TARGETS_KEY,
    GraphTableError,
    default_range,
    graphs_from_table,
    read_graph_table,
)
from pipeline import io
from pipeline.geometry import Range
from pipeline.lane_graph import LaneGraph
from pipeline.manifest import check_targets


@dataclass
class Request:
    """`--pred` and its options, checked: `auto` resolved to a format, the defaults filled in."""

    source: str  # --pred as given
    fmt: str  # graph, maptrv2 or cgnet
    class_name: str | None  # the class of vectors scored (None: graph)
    min_score: float | None  # the kept score (None: graph)
    parsed: dict | None  # the file's JSON when `--format auto` parsed it already


def request(pred_path: Path, fmt: str = "graph", class_name: str | None = None,
            min_score: float | None = None, sweep: bool = False) -> Request:  # fmt: skip
    """The options checked before any work (`--format auto` reads the file to tell its format); options of
    another format refused, each with one line."""
    source, pred_path, parsed = str(pred_path), Path(pred_path), None
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
        external.refuse_pickle(pred_path)
        if pred_path.is_file() and pred_path.suffix.lower() == ".json":
            raise GraphTableError(
                f"{pred_path}: a JSON file, not a graph table; pass --format maptrv2 or cgnet (or auto)"
            )
        return Request(source, fmt, None, None, None)
    class_name = class_name or "centerline"
    if class_name not in external.CLASSES[fmt]:
        raise GraphTableError(
            f"--class-name {class_name}: not a {fmt} class ({', '.join(external.CLASSES[fmt])})"
        )
    return Request(
        source, fmt, class_name, external.MIN_SCORE[fmt] if min_score is None else min_score, parsed
    )


@dataclass
class Conversion:
    """A result file's vectors matched to our frames, converted to graphs at any kept score."""

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


@dataclass
class Predictions:
    """A prediction file read and matched to the ground truth's frames: what `cli score` scores and what its
    result says of the file."""

    graphs: dict[str, LaneGraph]  # by frame id, each frame scored (empty where the file has no row)
    frame_ids: list[str]  # the frames scored, sorted
    splits: list[str] | None  # their split(s); None: a graph-table ground truth, which has none
    frames_predicted: int
    frames_missing: int  # frames of the split(s) without a row, scored as empty (graph tables)
    frames_in_file: int
    frames_not_in_file: int  # frames of the split(s) the file lacks, not scored (result files)
    vectors_read: int | None  # result files: vectors in the file, every class
    vectors_kept: int | None  # result files: those of the class above the kept score
    points_clipped: int | None  # result files: their points outside the range, clipped
    fmt: str
    source: str  # --pred as given
    sha256: str | None  # of the file (None: a folder)
    class_name: str | None
    min_score: float | None
    modeling: str  # what the format predicts: graph, path or piece (external.MODELING)
    conversion: Conversion | None = None  # result files: to convert again at other kept scores
    # result files: each graph edge's score, by frame id (external.Converted); None: graph tables, no score
    edge_scores: dict[str, np.ndarray] | None = None

    def info(self) -> dict:
        """What the result says of the frames scored."""
        return {"splits": self.splits, "frames_predicted": self.frames_predicted,
                "frames_missing": self.frames_missing}  # fmt: skip

    def provenance(self) -> dict:
        """The result's "external": the file, its format and options, what reading it kept."""
        return {
            "format": self.fmt,
            "source": self.source,
            "sha256": self.sha256,
            "class_name": self.class_name,
            "min_score": self.min_score,
            "frames_in_file": self.frames_in_file,
            "frames_not_in_file": self.frames_not_in_file,
            "vectors_read": self.vectors_read,
            "vectors_kept": self.vectors_kept,
            "points_clipped": self.points_clipped,
        }

    def sweep(self) -> Iterator[tuple[float, external.Converted]]:
        """(kept score, the file converted at it) for each of external.SWEEP's kept scores and the file's
        own, one at a time (`--sweep`; a result file's only)."""
        if self.conversion is None:
            raise GraphTableError(
                f"--sweep: only for a result file of another codebase; {self.source} is not"
            )
        for min_score in sorted({*external.SWEEP, self.min_score}):
            yield min_score, self.conversion.graphs(min_score)


def read(request: Request, gt_path: Path, gt: dict[str, LaneGraph], split: str | None = None,
         workers: int = 1) -> Predictions:  # fmt: skip
    """The file of `request` matched to the ground truth `gt` (of `gt_path`), its frames of `split`; a
    result file converted in `workers` processes (0: one per core)."""
    path = Path(request.source)
    if request.fmt == "graph":
        frames = _graph_table(request, Path(gt_path), gt, split)
    else:
        frames = _result_file(request, Path(gt_path), split, workers)
    digest = sha256(path) if path.is_file() else None
    return Predictions(
        **frames, fmt=request.fmt, source=request.source, sha256=digest, class_name=request.class_name,
        min_score=request.min_score, modeling=external.MODELING[request.fmt],
    )  # fmt: skip


def _graph_table(request: Request, gt_path: Path, gt: dict[str, LaneGraph], split: str | None) -> dict:
    """A graph table's frames, after the stale-data check of the targets its model trained on: the ground
    truth's of the predicted frames' split(s), a frame without a prediction row an empty prediction."""
    path = Path(request.source)
    table = read_graph_table(path)
    trained = json.loads((table.schema.metadata or {}).get(TARGETS_KEY, b"{}"))
    check_targets(trained, gt_path, f"the model of {request.source}")
    pred = graphs_from_table(table, path)
    unknown = sorted(set(pred) - set(gt))
    if unknown:
        raise GraphTableError(f"{path}: frame {unknown[0]} is not in the ground truth {gt_path}")
    frame_ids, splits = _scored_frames(pred, gt, gt_path, path, split)
    return {
        "graphs": {f: pred.get(f, LaneGraph.empty()) for f in frame_ids},
        "frame_ids": frame_ids,
        "splits": splits,
        "frames_predicted": len(pred),
        "frames_missing": sum(f not in pred for f in frame_ids),
        "frames_in_file": len(pred),
        "frames_not_in_file": 0,
        "vectors_read": None,
        "vectors_kept": None,
        "points_clipped": None,
    }


def _result_file(request: Request, gt_path: Path, split: str | None, workers: int) -> dict:
    """The frames of the file alone (a split's frames it lacks are counted, not scored as empty)."""
    path = Path(request.source)
    vectors = external.read_vectors(path, request.fmt, request.class_name, request.parsed)
    frame_ids, dataset = external.frame_ids_of(vectors.tokens, gt_path, path)
    split_of = frame_splits(gt_path)
    if split:
        _check_split(split, split_of, gt_path)
        outside = [(t, f) for t, f in zip(vectors.tokens, frame_ids) if split_of[f] != split]
        if outside:
            raise GraphTableError(
                f"{path}: {len(outside)} samples are not of --split {split}, e.g. {outside[0][0]} "
                f"({outside[0][1]}, split {split_of[outside[0][1]]})"
            )
    if not frame_ids:
        raise GraphTableError(f"{path}: no sample in its results list")
    splits = sorted({split_of[f] for f in frame_ids})
    workers = workers if workers > 0 else os.cpu_count() or 1
    conversion = Conversion(
        vectors, frame_ids, dataset, request.fmt, Range.parse(default_range(gt_path)), workers
    )
    converted = conversion.graphs(request.min_score)
    in_splits = sum(s in splits for s in split_of.values())
    return {
        "graphs": converted.graphs,
        "frame_ids": sorted(frame_ids),
        "splits": splits,
        "frames_predicted": len(frame_ids),
        "frames_missing": 0,
        "frames_in_file": len(frame_ids),
        "frames_not_in_file": in_splits - len(frame_ids),
        "vectors_read": vectors.read,
        "vectors_kept": converted.kept,
        "points_clipped": converted.clipped,
        "conversion": conversion,
        "edge_scores": converted.edge_scores,
    }


def frame_splits(gt_path: Path) -> dict[str, str] | None:
    """{frame_id: split} of a prepared dataset's `frames` table; None for a graph-table file."""
    if not (Path(gt_path) / "frames").is_dir():
        return None
    table = io.read_table(Path(gt_path), "frames", columns=["frame_id", "split"])
    return dict(zip(table.column("frame_id").to_pylist(), table.column("split").to_pylist()))


def _check_split(split: str, split_of: dict[str, str], gt_path: Path) -> None:
    if split not in set(split_of.values()):
        known = ", ".join(sorted(set(split_of.values())))
        raise GraphTableError(f"--split {split}: no such split in {gt_path} (its splits: {known})")


def _scored_frames(
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
        _check_split(split, split_of, gt_path)
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


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
