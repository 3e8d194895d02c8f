"""Result files of other codebases, MapTRv2 / LaneGAP and CGNet JSON: their formats and classes, their vectors
read, their sample ids matched to our frames and converted to our lane graphs (for benchmark/predictions.py).

Both codebases write `<work dir>/pts_bbox/nuscmap_results.json` (MapTRv2 on AV2: `av2map_results.json`)
with mmcv.dump: {"meta": ..., "results": [{"sample_token": ..., "vectors": [{"pts": [[x, y(, z)], ...],
"pts_num": 20, "cls_name": "centerline", "type": 3, "confidence_level": 0.83}, ...]}, ...]}.
docs/EXTERNAL.md is the user's page; what each step does and why:

- A MapTRv2 centerline is a whole lane path (its ground truth is every start-to-end path), so its graph
  is Path2Graph's (benchmark/graphs/path2graph.py, the parameters our LaneGAP's post-processing uses).
- A CGNet centerline is a piece whose linked endpoints its decoder already snapped to one coordinate, and
  CGNet builds its graph by merging exactly equal points: `merge_equal_points` does the same.
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
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmark.metric.densify import identical_points
from pipeline import io
from pipeline.geometry import Range, clip_polylines
from pipeline.lane_graph import LaneGraph, graph_of_edges

FORMATS = ("graph", "maptrv2", "cgnet")
CLASSES = {  # each codebase's map classes (MapTRv2's `_w_centerline` configs; CGNet's config)
    "maptrv2": ("divider", "ped_crossing", "boundary", "centerline"),
    "cgnet": ("centerline",),
}
# The default kept score of each format, from that codebase's own post-processing, never tuned here:
# MapTRv2's prediction drawing (tools/maptrv2/nusc_vis_pred.py and av2_vis_pred.py, --score-thresh) and
# CGNet's decoder (configs/cgnet/cgnet_ep110.py, score_threshold, before it snaps and builds its graph).
MIN_SCORE = {"maptrv2": 0.4, "cgnet": 0.3}
MODELING = {"graph": "graph", "maptrv2": "path", "cgnet": "piece"}
FORMAT_NAMES = {"graph": "graph table", "maptrv2": "MapTRv2 / LaneGAP JSON", "cgnet": "CGNet JSON"}
SWEEP = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)  # `--sweep`'s kept scores
PICKLE_SUFFIXES = (".pkl", ".pickle")


class ResultFileError(ValueError):
    """A result file that cannot be scored; the message names the file and, where known, the sample."""


@dataclass
class Vectors:
    """One class's vectors of a result file, every sample together, in the file's own frame."""

    tokens: list[str]  # each sample's token, in file order
    sample: np.ndarray  # (V,) the sample of each vector
    scores: np.ndarray  # (V,) confidence_level
    points: np.ndarray  # (P, 2) float64, x and y of every vector's points
    offsets: np.ndarray  # (V + 1,) vector v is points[offsets[v]:offsets[v + 1]]
    read: int  # vectors in the file, every class


def refuse_pickle(path: Path) -> None:
    """A pickle can run code when read: refused by name and by its first byte (protocol 2+ opcode)."""
    if path.is_file():
        with open(path, "rb") as file:
            first = file.read(1)
        if path.suffix.lower() in PICKLE_SUFFIXES or first == b"\x80":
            raise ResultFileError(
                f"{path}: a pickle, refused: reading one can run code. Write the results as JSON in the "
                "schema of MapTRv2's nuscmap_results.json and pass --format maptrv2 or cgnet "
                "(docs/EXTERNAL.md)"
            )


def detect_format(path: Path) -> tuple[str, dict | None]:
    """`--format auto`: (format, the parsed JSON or None). graph for Parquet (a file or folder); for JSON,
    maptrv2 when its centerline is MapTRv2's class 3 or other MapTRv2 classes appear, cgnet when every
    vector is a class-0 centerline."""
    path = Path(path)
    refuse_pickle(path)
    if path.is_dir() or not path.is_file():
        return "graph", None  # a folder of shards or a prepared dataset; a missing path fails in the reader
    with open(path, "rb") as file:
        head = file.read(4)
    if head == b"PAR1":
        return "graph", None
    data = load_json(path)
    records = [r for r in data["results"] if isinstance(r, dict) and isinstance(r.get("vectors"), list)]
    kinds = {(v.get("cls_name"), v.get("type")) for r in records for v in r["vectors"] if isinstance(v, dict)}
    if any(name in CLASSES["maptrv2"][:3] for name, _ in kinds) or ("centerline", 3) in kinds:
        return "maptrv2", data
    if kinds and kinds <= {("centerline", 0)}:
        return "cgnet", data
    raise ResultFileError(
        f"{path}: --format auto cannot tell MapTRv2 from CGNet (classes {sorted(map(str, kinds))[:4]}); "
        "pass --format maptrv2 or --format cgnet"
    )


def load_json(path: Path) -> dict:
    try:
        with open(path, "rb") as file:
            data = json.load(file)
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ResultFileError(f"{path}: not a JSON result file ({error})") from error
    if not isinstance(data, dict) or not isinstance(data.get("results"), list):
        raise ResultFileError(
            f'{path}: no "results" list: not a MapTRv2 / CGNet result file ({{"meta": ..., "results": '
            '[{"sample_token": ..., "vectors": [...]}, ...]})'
        )
    return data


def read_vectors(path: Path, fmt: str, class_name: str, data: dict | None = None) -> Vectors:
    """The vectors of `class_name` (from `data`, the file parsed already, if given), after checking every
    record; the first bad one raises one line naming the file, the sample and the field. Other classes'
    vectors are counted, their points unread."""
    path = Path(path)
    refuse_pickle(path)
    if not path.is_file():
        raise ResultFileError(f"{path}: no such file")
    classes = CLASSES[fmt]
    data = load_json(path) if data is None else data
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


def merge_equal_points(pieces: list[np.ndarray]) -> LaneGraph:
    """CGNet's graph of its snapped pieces: points at exactly equal coordinates are one vertex, each piece's
    consecutive points an edge; self-loops and repeated edges dropped."""
    return merge_equal_points_scored(pieces, None)[0]


def merge_equal_points_scored(pieces: list[np.ndarray], scores=None) -> tuple[LaneGraph, np.ndarray]:
    """(merge_equal_points' graph, each of its edges' score): the score of the piece it came from, the
    highest where pieces repeat it (`scores`: one per piece; None: every score 0.0)."""
    piece_score = np.zeros(len(pieces)) if scores is None else np.asarray(scores, np.float64)
    if piece_score.shape != (len(pieces),):
        raise ValueError(f"scores: one per piece ({len(pieces)}) is needed, not shape {piece_score.shape}")
    long = [i for i, p in enumerate(pieces) if len(p) >= 2]
    pieces, piece_score = [pieces[i] for i in long], piece_score[long]
    if not pieces:
        return LaneGraph.empty(), np.zeros(0)
    xy = np.concatenate(pieces) + 0.0  # no -0.0
    vertex, n = identical_points(xy)
    first = np.full(n, len(xy))
    np.minimum.at(first, vertex, np.arange(len(xy)))
    sizes = np.array([len(p) for p in pieces])
    is_last = np.zeros(len(xy), bool)
    is_last[np.cumsum(sizes) - 1] = True
    inner = ~is_last[:-1]
    src, dst = vertex[:-1][inner], vertex[1:][inner]
    edge_score = np.repeat(piece_score, sizes)[:-1][inner]
    return graph_of_edges(xy[first, 0], xy[first, 1], src, dst, edge_score)


@dataclass
class Converted:
    graphs: dict[str, LaneGraph]  # by frame id, every sample of the file (empty where nothing was kept)
    kept: int  # vectors above the score
    clipped: int  # their points outside the range
    edge_scores: dict[str, np.ndarray]  # by frame id, each graph edge's score (its src / dst order)


def to_graphs(vectors: Vectors, frame_ids: list[str], fmt: str, dataset: str, rng: Range, min_score: float,
              workers: int = 1) -> Converted:  # fmt: skip
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
            parts = pool.map(build_graphs, chunks, [fmt] * len(chunks), score_chunks)
            built = [g for part in parts for g in part]
    else:
        built = build_graphs(frames, fmt, scores)
    return Converted(
        {f: graph for f, (graph, _) in zip(frame_ids, built)}, len(keep), int(outside.sum()),
        {f: edge_scores for f, (_, edge_scores) in zip(frame_ids, built)},
    )  # fmt: skip


def build_graphs(frames: list[list[np.ndarray]], fmt: str,
                 scores: list[np.ndarray]) -> list[tuple[LaneGraph, np.ndarray]]:  # fmt: skip
    """Each frame's (graph, its edges' scores) from its clipped vectors and their scores: Path2Graph for
    MapTRv2's paths, equal points merged for CGNet's pieces; an edge takes the highest score of the vectors
    that produce it."""
    from benchmark.graphs.path2graph import path2graph_scored  # loaded only where a MapTRv2 file is converted

    build = path2graph_scored if fmt == "maptrv2" else merge_equal_points_scored
    return [
        build(pieces, score) if pieces else (LaneGraph.empty(), np.zeros(0))
        for pieces, score in zip(frames, scores)
    ]
