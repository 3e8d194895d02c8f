"""Our graph table as predictions (`--format graph`): a Parquet file or folder of shards of lane graphs
(benchmark/graph_table.py reads and checks it), such as `cli eval` writes. The frames of `--split` are
scored (by default the split or splits of the predicted frames, from a prepared dataset's `frames` table;
every frame of a graph-table ground truth); one without a prediction row counts as an empty prediction
(`frames_missing`); a predicted frame that is not in the ground truth (a typo or another dataset), or not
in `--split`, is refused, never dropped unsaid. Stale data is refused: predictions written by `cli eval`
record the target parameters of the dataset their model was trained on, and a prepared ground truth made
with other ones is an error naming the parameter. A graph table has no scores.
"""

from __future__ import annotations

import json

from benchmark.formats.base import (
    FramePrediction,
    GroundTruth,
    Options,
    PredictionFormat,
    Predictions,
    Source,
)
from benchmark.graph_table import TARGETS_KEY, GraphTableError, graphs_from_table, read_graph_table
from pipeline.lane_graph import LaneGraph
from pipeline.manifest import check_targets

PARQUET_MAGIC = b"PAR1"


def detect(source: Source) -> bool:
    """A Parquet file, or a folder (of shards, or a prepared dataset whose `graphs` the reader takes)."""
    return source.path.is_dir() or source.head(len(PARQUET_MAGIC)) == PARQUET_MAGIC


def check(source: Source, options: Options) -> str | None:
    """None of a result file's options; neither a pickle nor JSON (`--format graph` names the format, and
    an earlier default did)."""
    if given := options.given():
        return (
            f"{', '.join(given)}: only for a result file of another codebase "
            f"(--format maptrv2 or cgnet); {source.path} is read as a graph table"
        )
    if (refusal := source.pickle_refusal()) is not None:
        return refusal
    if source.head(64).lstrip()[:1] in (b"{", b"["):  # by its content, whatever its name
        # never "or auto": auto cannot tell whose a result file without vectors is
        return f"{source.path}: a JSON file, not a graph table; pass --format maptrv2 or cgnet"
    return None


def read(source: Source, options: Options, gt: GroundTruth) -> Predictions:
    """The ground truth's frames of the predicted frames' split(s), after the stale-data check of the
    targets the predictions' model trained on; a frame without a prediction row an empty prediction."""
    path = source.path
    table = read_graph_table(path)
    trained = json.loads((table.schema.metadata or {}).get(TARGETS_KEY, b"{}"))
    check_targets(trained, gt.path, f"the model of {source.given}")
    pred = graphs_from_table(table, path)
    unknown = sorted(set(pred) - set(gt.graphs))
    if unknown:
        raise GraphTableError(f"{path}: frame {unknown[0]} is not in the ground truth {gt.path}")
    frame_ids, splits = scored_frames(pred, gt, path)
    return Predictions(
        frames=[FramePrediction(f, pred.get(f, LaneGraph.empty())) for f in frame_ids],
        splits=splits,
        frames_predicted=len(pred),
        frames_missing=sum(f not in pred for f in frame_ids),
        frames_in_file=len(pred),
        frames_not_in_file=0,
        format=FORMAT,
        source=source,
    )


def scored_frames(pred: dict, gt: GroundTruth, pred_path) -> tuple[list[str], list[str] | None]:
    """(frame ids to score, their splits): the ground truth's frames of --split, by default of the splits
    the predicted frames belong to; every frame (splits None) of a graph-table file, which has no splits."""
    split_of = gt.frame_splits()
    if split_of is None:
        if gt.split:
            raise GraphTableError(
                f"--split {gt.split}: the ground truth {gt.path} is a graph-table file without splits; "
                "pass a prepared dataset (cli prepare --out)"
            )
        return sorted(gt.graphs), None
    if gt.split:
        gt.check_split(split_of)
        outside = sorted(f for f in pred if split_of.get(f) != gt.split)
        if outside:
            raise GraphTableError(
                f"{pred_path}: frame {outside[0]} is in split {split_of.get(outside[0])!r}, not in "
                f"--split {gt.split}"
            )
    elif not pred:
        raise GraphTableError(
            f"{pred_path}: no predicted frame; pass --split to score a split's frames as empty"
        )
    splits = [gt.split] if gt.split else sorted({split_of[f] for f in pred})
    return sorted(f for f in gt.graphs if split_of.get(f) in splits), splits


FORMAT = PredictionFormat(
    name="graph", title="graph table", modeling="graph", external=False, detect=detect, check=check, read=read
)
