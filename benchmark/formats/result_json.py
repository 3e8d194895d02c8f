"""What the result JSON of MapTRv2 / LaneGAP and of CGNet share, for their readers (maptrv2_json.py,
cgnet_json.py): the schema's vectors read, their sample ids matched to our frames, converted to our lane
graphs by the codebase's own way of building one (a `Codebase`), and scored frame by frame with their scores.

Both codebases write `<work dir>/pts_bbox/nuscmap_results.json` (MapTRv2 on AV2: `av2map_results.json`)
with mmcv.dump: {"meta": ..., "results": [{"sample_token": ..., "vectors": [{"pts": [[x, y(, z)], ...],
"pts_num": 20, "cls_name": "centerline", "type": 3, "confidence_level": 0.83}, ...]}, ...]}.
docs/guide/score.md is the user's page; what each step does and why:

- A MapTRv2 centerline is a whole lane path, whose graph is Path2Graph's; a CGNet centerline a piece
  with snapped ends, whose graph merges exactly equal points (each codebase's module).
- Frames: a nuScenes sample token is looked up in the prepared `frames` table (column sample_token); an
  AV2 `<log_id>_<lidar timestamp ns>` is our `av2/<log_id>/<timestamp ns>`.
- Points: nuScenes results are in the LIDAR_TOP frame, which is our BEV frame (x right, y forward); AV2
  results are in the egovehicle frame (x forward, y left), turned here by -90 deg about z into ours; a z is
  dropped. They are then clipped to the dataset's range with the kernel that clipped the ground truth.
- A vector is kept when its confidence_level is above `min_score` (strictly, as both codebases compare).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmark.formats.base import (
    FormatError,
    FramePrediction,
    GroundTruth,
    Options,
    PredictionFormat,
    Predictions,
    Source,
    Swept,
)
from benchmark.graph_table import default_range
from pipeline import io
from pipeline.geometry import Range, clip_polylines
from pipeline.lane_graph import LaneGraph

# one frame's (graph, each edge's score) from its clipped vectors and their scores; module-level (picklable)
Build = Callable[[list[np.ndarray], np.ndarray], tuple[LaneGraph, np.ndarray]]


class ResultFileError(FormatError):
    """A result file that cannot be scored; the message names the file and, where known, the sample."""


@dataclass(frozen=True)
class Codebase:
    """What one codebase's result JSON means: its map classes, its own default kept score and how it builds
    a frame's lane graph from the kept vectors."""

    name: str  # the --format word
    classes: tuple[str, ...]
    min_score: float  # the codebase's own post-processing's, never tuned here
    build: Build


@dataclass
class Vectors:
    """One class's vectors of a result file, every sample together, in the file's own frame."""

    tokens: list[str]  # each sample's token, in file order
    sample: np.ndarray  # (V,) the sample of each vector
    scores: np.ndarray  # (V,) confidence_level
    points: np.ndarray  # (P, 2) float64, x and y of every vector's points
    offsets: np.ndarray  # (V + 1,) vector v is points[offsets[v]:offsets[v + 1]]
    read: int  # vectors in the file, every class


def results_list(source: Source) -> list | None:
    """The file's results list, for detection; None when it is not a JSON file with one."""
    try:
        data = source.json()
    except (ValueError, OSError):
        return None
    if not isinstance(data, dict) or not isinstance(data.get("results"), list):
        return None
    return data["results"]


def vector_kinds(source: Source) -> set[tuple[object, object]] | None:
    """Detection's look at a file: the (cls_name, type) of its vectors, or None when it is not a JSON file
    with a results list."""
    results = results_list(source)
    if results is None:
        return None
    records = [r for r in results if isinstance(r, dict) and isinstance(r.get("vectors"), list)]
    return {(v.get("cls_name"), v.get("type")) for r in records for v in r["vectors"] if isinstance(v, dict)}


def undecided(source: Source) -> str | None:
    """The line refusing, under auto, a result JSON that no detection recognises because it holds no vector:
    with no sample, what either reader says; with only empty samples, a file either codebase may have
    written, which both score alike but whose result records one's format and kept score (None: neither)."""
    results = results_list(source)
    if results is None:
        return None
    if not results:
        return f"{source.path}: no sample in its results list"
    if all(isinstance(record, dict) and record.get("vectors") == [] for record in results):
        return f"{source.path}: no vectors to tell MapTRv2 from CGNet: pass --format maptrv2 or cgnet"
    return None


def load_json(source: Source) -> dict:
    """The file's JSON for its reader, the last to ask for it."""
    try:
        data = source.json(keep=False)
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ResultFileError(f"{source.path}: not a JSON result file ({error})") from error
    if not isinstance(data, dict) or not isinstance(data.get("results"), list):
        raise ResultFileError(
            f'{source.path}: no "results" list: not a MapTRv2 / CGNet result file ({{"meta": ..., "results": '
            '[{"sample_token": ..., "vectors": [...]}, ...]})'
        )
    return data


def read_vectors(source: Source, codebase: Codebase, class_name: str) -> Vectors:
    """The vectors of `class_name`, after checking every record; the first bad one raises one line naming
    the file, the sample and the field. Other classes' vectors are counted, their points unread."""
    path, fmt, classes = source.path, codebase.name, codebase.classes
    source.refuse_pickle()
    if not path.is_file():
        raise ResultFileError(f"{path}: no such file")
    data = load_json(source)
    tokens, sample, scores, chains = [], [], [], []
    read = 0
    for index, record in enumerate(data["results"]):
        token = record.get("sample_token") if isinstance(record, dict) else None
        if not isinstance(token, str) or not token:
            raise ResultFileError(f"{path}: results[{index}]: no sample_token")
        vectors = record.get("vectors")
        if not isinstance(vectors, list):
            raise ResultFileError(f"{path}: sample {token}: vectors is missing or not a list")
        tokens.append(token)
        read += len(vectors)
        for number, vector in enumerate(vectors):
            where = f"{path}: sample {token}: vectors[{number}]"
            name = vector.get("cls_name") if isinstance(vector, dict) else None
            if name not in classes:
                raise ResultFileError(
                    f"{where}.cls_name {name!r} is not one of {fmt}'s ({', '.join(classes)})"
                )
            if name != class_name:
                continue
            score = vector.get("confidence_level")
            if isinstance(score, bool) or not isinstance(score, int | float) or not math.isfinite(score):
                raise ResultFileError(f"{where}.confidence_level {score!r} is not a finite number")
            try:
                pts = np.asarray(vector.get("pts"), np.float64)
            except (TypeError, ValueError):
                raise ResultFileError(f"{where}.pts is not a list of [x, y] or [x, y, z] points") from None
            if pts.ndim != 2 or pts.shape[1] not in (2, 3):
                raise ResultFileError(f"{where}.pts is not a list of [x, y] or [x, y, z] points")
            if len(pts) < 2:
                raise ResultFileError(f"{where}.pts has {len(pts)} point(s); a line needs 2")
            if not np.isfinite(pts).all():
                raise ResultFileError(f"{where}.pts holds a NaN or infinite coordinate")
            sample.append(index)
            scores.append(float(score))
            chains.append(pts[:, :2])
    unique, counts = np.unique(tokens, return_counts=True)
    if (counts > 1).any():
        raise ResultFileError(f"{path}: sample {unique[counts > 1][0]}: more than one record")
    sizes = np.array([len(c) for c in chains], np.int64)
    return Vectors(
        tokens,
        np.array(sample, np.int64),
        np.array(scores, np.float64),
        np.concatenate(chains) if chains else np.zeros((0, 2)),
        np.concatenate([[0], np.cumsum(sizes)]),
        read,
    )


def dataset_kind(gt_path: Path) -> str:
    """'nuscenes' or 'av2': the prepared dataset's (its manifest.json)."""
    manifest = Path(gt_path) / "manifest.json"
    if not manifest.is_file() or not (Path(gt_path) / "frames").is_dir():
        raise ResultFileError(
            f"--gt {gt_path}: a result file of another codebase needs a prepared dataset (cli prepare "
            "--out), whose frames table maps its sample ids to frames"
        )
    dataset = json.loads(manifest.read_text()).get("dataset")
    if dataset not in ("nuscenes", "av2"):
        raise ResultFileError(f"{manifest}: dataset {dataset!r} is neither nuscenes nor av2")
    return dataset


def frame_ids_of(tokens: list[str], gt_path: Path, path: Path) -> tuple[list[str], str]:
    """(our frame id of each sample token, dataset kind); a token the ground truth lacks is refused
    with the first few and their count."""
    dataset = dataset_kind(gt_path)
    if dataset == "av2":
        ids = []
        for token in tokens:
            log_id, _, timestamp = token.rpartition("_")
            if not log_id or not timestamp.isdigit():
                raise ResultFileError(
                    f"{path}: sample {token}: not an AV2 id <log_id>_<lidar timestamp ns> (MapTRv2's token)"
                )
            ids.append(f"av2/{log_id}/{int(timestamp)}")
        known = set(io.read_table(Path(gt_path), "frames", ["frame_id"]).column("frame_id").to_pylist())
    else:
        table = io.read_table(Path(gt_path), "frames", ["frame_id", "sample_token"])
        frame_of = dict(zip(table.column("sample_token").to_pylist(), table.column("frame_id").to_pylist()))
        ids = [frame_of.get(token, token) for token in tokens]
        known = set(frame_of.values())
    unknown = [token for token, frame_id in zip(tokens, ids) if frame_id not in known]
    if unknown:
        first = ", ".join(unknown[:3])
        raise ResultFileError(
            f"{path}: {len(unknown)} of {len(tokens)} samples are not frames of the ground truth {gt_path} "
            f"(first: {first}); results of another dataset or split, or a dataset prepared with another "
            "--frame-stride?"
        )
    return ids, dataset


@dataclass
class Converted:
    graphs: dict[str, LaneGraph]  # by frame id, every sample of the file (empty where nothing was kept)
    kept: int  # vectors above the score
    clipped: int  # their points outside the range
    edge_scores: dict[str, np.ndarray]  # by frame id, each graph edge's score (its src / dst order)


def to_graphs(vectors: Vectors, frame_ids: list[str], build: Build, dataset: str, rng: Range,
              min_score: float, workers: int = 1) -> Converted:  # fmt: skip
    """Each sample's lane graph from its vectors above min_score, in our BEV frame, clipped to rng, with each
    edge's score (build_graphs); the graphs built in `workers` processes."""
    kept = vectors.scores > min_score
    keep = np.flatnonzero(kept)
    sizes = np.diff(vectors.offsets)[keep]
    xy = vectors.points[np.repeat(kept, np.diff(vectors.offsets))]
    if dataset == "av2":  # egovehicle (x forward, y left) -> BEV (x right, y forward)
        xy = np.stack([-xy[:, 1], xy[:, 0]], axis=1)
    xy = np.ascontiguousarray(xy) + 0.0
    outside = (
        (xy[:, 0] < rng.x_min) | (xy[:, 0] > rng.x_max) | (xy[:, 1] < rng.y_min) | (xy[:, 1] > rng.y_max)
    )
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    points, piece_offsets, piece_vector, _, _ = clip_polylines(
        xy, offsets, rng.x_min, rng.x_max, rng.y_min, rng.y_max
    )
    piece_sample = vectors.sample[keep][piece_vector]  # nondecreasing: vectors are in sample order
    piece_score = vectors.scores[keep][piece_vector]  # a clipped piece keeps its vector's score
    bounds = np.searchsorted(piece_sample, np.arange(len(vectors.tokens) + 1))
    frames = [
        [points[piece_offsets[k] : piece_offsets[k + 1]] for k in range(bounds[i], bounds[i + 1])]
        for i in range(len(frame_ids))
    ]
    scores = [piece_score[bounds[i] : bounds[i + 1]] for i in range(len(frame_ids))]
    if workers > 1 and len(frames) >= 64 * workers:  # Path2Graph is most of the conversion's time
        size = -(-len(frames) // (4 * workers))
        chunks = [frames[i : i + size] for i in range(0, len(frames), size)]
        score_chunks = [scores[i : i + size] for i in range(0, len(scores), size)]
        with ProcessPoolExecutor(workers) as pool:
            parts = pool.map(build_graphs, chunks, [build] * len(chunks), score_chunks)
            built = [g for part in parts for g in part]
    else:
        built = build_graphs(frames, build, scores)
    return Converted(
        {f: graph for f, (graph, _) in zip(frame_ids, built)}, len(keep), int(outside.sum()),
        {f: edge_scores for f, (_, edge_scores) in zip(frame_ids, built)},
    )  # fmt: skip


def build_graphs(frames: list[list[np.ndarray]], build: Build,
                 scores: list[np.ndarray]) -> list[tuple[LaneGraph, np.ndarray]]:  # fmt: skip
    """Each frame's (graph, its edges' scores) from its clipped vectors and their scores, built as the
    codebase builds one; an edge takes the highest score of the vectors that produce it."""
    return [
        build(pieces, score) if pieces else (LaneGraph.empty(), np.zeros(0))
        for pieces, score in zip(frames, scores)
    ]


def check(codebase: Codebase, options: Options) -> str | None:
    """--class-name names one of the codebase's classes (--min-score and --sweep apply to every one);
    --min-score is a confidence (cli.py's range check lets a NaN through; a caller of score() has none)."""
    class_name = options.class_name or "centerline"
    if class_name not in codebase.classes:
        return f"--class-name {class_name}: not a {codebase.name} class ({', '.join(codebase.classes)})"
    if options.min_score is not None and not 0.0 <= options.min_score <= 1.0:
        return f"--min-score {options.min_score:g}: not a confidence from 0 to 1"
    return None


def read(fmt: PredictionFormat, codebase: Codebase, source: Source, options: Options,
         gt: GroundTruth) -> Predictions:  # fmt: skip
    """The frames of the file alone, converted at the kept score (a split's frames it lacks are counted,
    not scored as empty), each graph with its edges' scores."""
    path = source.path
    class_name = options.class_name or "centerline"
    min_score = codebase.min_score if options.min_score is None else options.min_score
    vectors = read_vectors(source, codebase, class_name)
    frame_ids, dataset = frame_ids_of(vectors.tokens, gt.path, path)
    split_of = gt.frame_splits()
    if gt.split:
        gt.check_split(split_of)
        outside = [(t, f) for t, f in zip(vectors.tokens, frame_ids) if split_of[f] != gt.split]
        if outside:
            raise ResultFileError(
                f"{path}: {len(outside)} samples are not of --split {gt.split}, e.g. {outside[0][0]} "
                f"({outside[0][1]}, split {split_of[outside[0][1]]})"
            )
    if not frame_ids:
        raise ResultFileError(f"{path}: no sample in its results list")
    splits = sorted({split_of[f] for f in frame_ids})
    rng = Range.parse(default_range(gt.path))

    def convert(kept_score: float) -> Converted:
        return to_graphs(vectors, frame_ids, codebase.build, dataset, rng, kept_score, gt.workers)

    def swept(kept_score: float) -> Swept:
        converted = convert(kept_score)
        return Swept(kept_score, converted.kept, converted.graphs)

    converted = convert(min_score)
    in_splits = sum(s in splits for s in split_of.values())
    return Predictions(
        frames=[FramePrediction(f, converted.graphs[f], converted.edge_scores[f]) for f in sorted(frame_ids)],
        splits=splits,
        frames_predicted=len(frame_ids),
        frames_missing=0,
        frames_in_file=len(frame_ids),
        frames_not_in_file=in_splits - len(frame_ids),
        format=fmt,
        source=source,
        class_name=class_name,
        min_score=min_score,
        vectors_read=vectors.read,
        vectors_kept=converted.kept,
        points_clipped=converted.clipped,
        convert=swept,
    )
