"""The frame browser of report.html, as data: every evaluated frame with, per run, its directed TOPO and
Junction TOPO F1 from the run's per-frame counts (RUN/frame_counts.parquet, as `cli eval` wrote them),
the junction count and lane length of its ground truth, and its drawings (the ground truth and each run's
prediction, coordinates quantised to QUANTUM, each edge's share of densified points that the metric's own
matching paired: benchmark/report/figures.py's matched_vertices, as `cli viz` colours them).

Above `frames` frames it keeps those that say most (the largest absolute differences between two runs,
each run's lowest F1, a seeded random sample), each with the reasons it is there. A frame's drawing is
packed into one base64 string of varints (assets/browser.js decodes it only when the frame is shown); a
run without predictions.parquet has its scores and no drawing."""

from __future__ import annotations

import base64
import math
import os
import re
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path

import numpy as np

from benchmark.metric.densify import identical_points, split_into_parts, unique_edges
from benchmark.metric.params import EPS, MetricParams
from benchmark.metric.totals import FRAME_FIELDS
from benchmark.report.figures import matched_vertices, piece_arrows
from benchmark.report.runs import Block
from benchmark.report.runs import shown as shown_path
from pipeline.geometry import Range
from pipeline.lane_graph import LaneGraph
from pipeline.pieces import graph_to_pieces
from pipeline.progress import track

QUANTUM = 0.05  # metres: finer than the metric's 0.15 m step, so the drawing shows what it scored
DEFAULT_FRAMES = 3000  # `cli report --browser-frames`
SEED = 0  # of the random sample
THUMBNAIL_WIDTH = 240  # pixels of the front camera image (`--thumbnails`)
DIRECTED = {name: i for i, name in enumerate(FRAME_FIELDS)}  # the directed columns of a count row


@dataclass
class BrowserRun:
    """One run as the browser shows it: its per-frame counts and, where it has them, its predictions."""

    name: str
    counts: dict[str, np.ndarray]  # frame id -> its row of FRAME_COLUMNS
    predictions: dict[str, LaneGraph] | None  # None: no predictions.parquet (scores, no drawing)


@dataclass
class BrowserBlock:
    """The frames of one prepared dataset and split with the runs scored on them."""

    dataset: str
    split: str
    label: str  # as the filter names it
    params: MetricParams
    gt: dict[str, LaneGraph]  # every frame of the block that a run scored
    runs: list[BrowserRun]
    data: Path | None = None  # the prepared folder, where `--thumbnails` finds the cameras


@dataclass(frozen=True)
class FrameScores:
    precision: float | None
    recall: float | None
    f1: float | None  # None: neither graph has a vertex
    junction_f1: float | None  # None: the ground truth has no junction


def frame_scores(row: np.ndarray) -> FrameScores:
    """Directed TOPO P, R, F1 and Junction TOPO F1 of one frame's count row, as the metric pools them."""
    c = {name: float(row[i]) for name, i in DIRECTED.items()}
    if c["n_pred"] == 0 and c["n_gt"] == 0:
        topo = (None, None, None)
    else:
        p = c["pre"] / c["n_pred"] if c["n_pred"] else 0.0
        r = c["rec"] / c["n_gt"] if c["n_gt"] else 0.0
        topo = (p, r, 2 * p * r / (p + r) if p + r else 0.0)
    junction = None
    if c["n_junctions"]:
        p = c["junction_pre"] / c["n_anchored"] if c["n_anchored"] else 0.0
        r = c["junction_rec"] / c["n_junctions"]
        junction = 2 * p * r / (p + r) if p + r else 0.0
    return FrameScores(*topo, junction)


def browser_blocks(blocks: list[Block]) -> tuple[list[BrowserBlock], list[str]]:
    """The report's blocks as the browser shows them, and a line for each run or block left out."""
    from benchmark.graph_table import graphs_from_table, read_graph_table

    shown, notes, sources = [], [], []
    for block in blocks:
        runs = []
        for run in block.scored:
            if run.counts is None:
                notes.append(f"{run.name}: not in the frame browser: {run.no_counts}.")
                continue
            file = run.path / "predictions.parquet"
            predictions = graphs_from_table(read_graph_table(file), file) if file.is_file() else None
            if predictions is None:
                notes.append(
                    f"{run.name}: no predictions.parquet: its scores are shown, its graphs not drawn."
                )
            runs.append(BrowserRun(run.name, dict(zip(run.frame_ids, run.counts)), predictions))
        for run in block.runs:
            if not run.scored:
                notes.append(f"{run.name}: not in the frame browser: {'; '.join(run.reasons)}.")
        if not runs:
            continue
        if block.data is None:
            notes.append(
                f"{block.title}: data folder not found, so no ground truth: not in the frame browser."
            )
            continue
        gt_all = graphs_from_table(read_graph_table(block.data), block.data)
        frames = sorted(set().union(*(run.counts for run in runs)))
        unknown = [f for f in frames if f not in gt_all]
        if unknown:
            notes.append(f"{block.title}: {len(unknown)} scored frames are not in the ground truth (first "
                         f"{unknown[0]}): left out of the frame browser.")  # fmt: skip
        gt = {f: gt_all[f] for f in frames if f in gt_all}
        label = f"{block.dataset} · {block.split or '?'} split"
        params = MetricParams(**block.metric_params)
        browser = BrowserBlock(block.dataset, block.split or "?", label, params, gt, runs, block.data)
        shown.append(browser)
        sources.append(block)
    labels = [b.label for b in shown]
    for browser, block in zip(shown, sources):
        if labels.count(browser.label) > 1:  # the same dataset and split prepared twice (another range)
            browser.label += f" (`{shown_path(block.data)}`)"
    return shown, notes


def front_thumbnails(data: Path, frames: list[str]) -> tuple[dict[str, str], str]:
    """{frame id: JPEG data URI} of each frame's front camera image, THUMBNAIL_WIDTH wide, and a note
    where the dataset has no cameras or an image is missing."""
    import cv2
    from pyarrow.dataset import field as column

    from benchmark.report.figures import forward_camera
    from pipeline.io import read_table
    from pipeline.manifest import PreparedData

    rows = read_table(data, "frames", columns=["frame_id", "cameras"], filter=column("frame_id").isin(frames))
    root = PreparedData.open(data).sensor_root
    thumbs, missing, without = {}, 0, 0
    for row in rows.to_pylist():
        if not row["cameras"]:
            without += 1
            continue
        image = cv2.imread(str(root / forward_camera(row["cameras"])["image_path"]), cv2.IMREAD_COLOR)
        if image is None:
            missing += 1
            continue
        height = max(1, round(image.shape[0] * THUMBNAIL_WIDTH / image.shape[1]))
        small = cv2.resize(image, (THUMBNAIL_WIDTH, height), interpolation=cv2.INTER_AREA)
        ok, jpeg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 70])
        thumbs[row["frame_id"]] = "data:image/jpeg;base64," + base64.b64encode(jpeg.tobytes()).decode()
    note = ""
    if without:
        note = f"{without} frames have no cameras (no thumbnail)"
    if missing:
        note += (
            "; " if note else ""
        ) + f"{missing} front camera images are missing under {root} (no thumbnail)"
    return thumbs, note


# ---------------------------------------------------------------------------------------------------
# Which frames are kept


@dataclass(frozen=True)
class Kept:
    frames: list[tuple[int, str]]  # (block index, frame id), in block then frame order
    why: dict[tuple[int, str], list[int]]  # reasons (indices into reasons) of each kept frame
    reasons: list[str]
    total: int  # frames evaluated


def f1_column(block: BrowserBlock, run: BrowserRun, frames: list[str]) -> np.ndarray:
    """Directed TOPO F1 of each frame (NaN: the run did not score it, or neither graph has a vertex)."""
    values = [frame_scores(run.counts[f]).f1 if f in run.counts else None for f in frames]
    return np.array([math.nan if v is None else v for v in values], np.float64)


def keep_frames(blocks: list[BrowserBlock], limit: int, seed: int = SEED) -> Kept:
    """Every frame when there are at most `limit`; else a third of the limit to the largest absolute
    differences of directed TOPO F1 between two runs of a block (never 0), a third to each run's lowest
    (never 100 %), taken in turn, and the rest a seeded random sample of the others."""
    everything = [(b, f) for b, block in enumerate(blocks) for f in block.gt]
    if len(everything) <= limit:
        why = {key: [0] for key in everything}
        return Kept(everything, why, ["every evaluated frame"], len(everything))
    reasons: list[str] = []
    why: dict[tuple[int, str], list[int]] = {}
    queues: list[tuple[int, list[tuple[int, str]]]] = []  # (reason, frames best first)
    worst: list[tuple[int, list[tuple[int, str]]]] = []
    for b, block in enumerate(blocks):
        frames = list(block.gt)
        f1 = {run.name: f1_column(block, run, frames) for run in block.runs}
        for a, c in combinations(block.runs, 2):
            gap = np.abs(f1[a.name] - f1[c.name])
            order = [i for i in np.argsort(-np.nan_to_num(gap, nan=-1.0), kind="stable") if gap[i] > 0]
            reasons.append(f"among the largest differences of dir TOPO F1 between {a.name} and {c.name}")
            queues.append((len(reasons) - 1, [(b, frames[i]) for i in order]))
        for run in block.runs:
            values = f1[run.name]
            order = [i for i in np.argsort(np.nan_to_num(values, nan=2.0), kind="stable") if values[i] < 1]
            reasons.append(f"among {run.name}'s lowest dir TOPO F1")
            worst.append((len(reasons) - 1, [(b, frames[i]) for i in order]))
    for pool, quota in ((queues, limit // 3), (worst, limit // 3)):
        take_in_turn(pool, quota, why)
    reasons.append(f"a random sample (seed {seed})")
    rest = [key for key in everything if key not in why]
    for i in np.random.default_rng(seed).permutation(len(rest))[: max(0, limit - len(why))]:
        why[rest[i]] = [len(reasons) - 1]
    kept = [key for key in everything if key in why]
    return Kept(kept, why, reasons, len(everything))


def take_in_turn(pool: list[tuple[int, list[tuple[int, str]]]], quota: int, why: dict) -> None:
    """Frames from each list of `pool` in turn, best first, until `quota` new frames are kept; a frame that
    is already kept gains the list's reason, so a frame kept for one reason is labelled with every list
    whose kept part holds it."""
    taken, at = 0, [0] * len(pool)
    while taken < quota and any(at[k] < len(frames) for k, (_, frames) in enumerate(pool)):
        for k, (reason, frames) in enumerate(pool):
            if at[k] >= len(frames) or taken >= quota:
                continue
            key = frames[at[k]]
            at[k] += 1
            if key not in why:
                why[key] = []
                taken += 1
            if reason not in why[key]:
                why[key].append(reason)


# ---------------------------------------------------------------------------------------------------
# Drawings


def edge_shares(graph: LaneGraph, paired: np.ndarray, step: float) -> np.ndarray:
    """Each directed edge's (unique_edges order) share of its densified points that the matching paired:
    `paired` is per vertex of the metric's densified graph (densify's numbering, the same kernels)."""
    edges = unique_edges(graph, True)
    if len(edges) == 0:
        return np.zeros(0)
    xy = np.stack([np.asarray(graph.x, np.float64), np.asarray(graph.y, np.float64)], axis=1) + 0.0
    points, sub_src, sub_dst, _ = split_into_parts(xy, edges[:, 0], edges[:, 1], step, EPS)
    vertex, _ = identical_points(points)
    edge_of = (
        np.cumsum(sub_src < len(xy)) - 1
    )  # an edge's sub-edges follow each other, the first from its src
    both = (paired[vertex[sub_src]].astype(np.float64) + paired[vertex[sub_dst]]) / 2
    return np.bincount(edge_of, weights=both, minlength=len(edges)) / np.bincount(
        edge_of, minlength=len(edges)
    )


def zigzag(values: np.ndarray) -> np.ndarray:
    values = np.asarray(values, np.int64)
    return ((values << 1) ^ (values >> 63)).astype(np.uint64)


def varints(values: np.ndarray) -> bytes:
    """Unsigned LEB128 of each value (7 bits a byte, the high bit: more follows), vectorised."""
    v = np.asarray(values, np.uint64)
    size = np.ones(len(v), np.int64)
    rest = v >> np.uint64(7)
    while rest.any():
        size += rest > 0
        rest >>= np.uint64(7)
    out = np.empty(int(size.sum()), np.uint8)
    start = np.cumsum(size) - size
    for k in range(int(size.max(initial=0))):
        has = size > k
        byte = (v[has] >> np.uint64(7 * k)) & np.uint64(127)
        more = (size[has] > k + 1).astype(np.uint64) << np.uint64(7)
        out[start[has] + k] = (byte | more).astype(np.uint8)
    return out.tobytes()


def graph_numbers(graph: LaneGraph) -> tuple[list[np.ndarray], np.ndarray]:
    """(the numbers of a graph's drawing, its unique directed edges): vertex and edge counts, vertices
    quantised and delta-coded, edges (src delta, dst - src), then its pieces' arrows as edge indices."""
    edges = unique_edges(graph, True)
    qx = np.rint(np.asarray(graph.x, np.float64) / QUANTUM).astype(np.int64)
    qy = np.rint(np.asarray(graph.y, np.float64) / QUANTUM).astype(np.int64)
    coords = np.stack([np.diff(qx, prepend=0), np.diff(qy, prepend=0)], axis=1).ravel()
    pairs = np.stack([np.diff(edges[:, 0], prepend=0), edges[:, 1] - edges[:, 0]], axis=1).ravel()
    index = {(int(s), int(d)): e for e, (s, d) in enumerate(edges)}
    xy = np.stack([np.asarray(graph.x, np.float64), np.asarray(graph.y, np.float64)], axis=1)
    arrows = (
        [index[a] for a in piece_arrows(xy, graph_to_pieces(graph).chains) if a in index]
        if len(edges)
        else []
    )
    numbers = [np.array([len(qx), len(edges)], np.uint64), zigzag(coords), zigzag(pairs),
               np.array([len(arrows)], np.uint64), np.asarray(arrows, np.uint64)]  # fmt: skip
    return numbers, edges


@dataclass(frozen=True)
class FrameTask:
    """What one frame's drawing needs, picklable for a worker: the ground truth, the prediction of each run
    that is drawn (one with predictions.parquet; None: it has none for this frame, drawn empty) and the
    metric's parameters."""

    gt: LaneGraph
    predictions: tuple[LaneGraph | None, ...]
    params: MetricParams


def frame_task(block: BrowserBlock, frame: str) -> FrameTask:
    predictions = tuple(run.predictions.get(frame) for run in block.runs if run.predictions is not None)
    return FrameTask(block.gt[frame], predictions, block.params)


def frame_drawing(task: FrameTask) -> str:
    """One frame packed for browser.js: the ground truth's drawing, then for each drawn run of the block
    its prediction's drawing (empty where it has none), its edges' shares paired (paired_percent), the
    ground truth's edges' shares that it paired, and whether it predicted the frame (1) or not (0)."""
    gt, step = task.gt, task.params.step
    numbers, _ = graph_numbers(gt)
    for prediction in task.predictions:
        pred = LaneGraph.empty() if prediction is None else prediction
        drawn, _ = graph_numbers(pred)
        _, p_ok, _, g_ok = matched_vertices(pred, gt, task.params)
        shares = [edge_shares(pred, p_ok, step), edge_shares(gt, g_ok, step)]
        numbers += drawn + [paired_percent(s) for s in shares]
        numbers.append(np.array([prediction is not None], np.uint64))
    return base64.b64encode(varints(np.concatenate(numbers))).decode()


def paired_percent(shares: np.ndarray) -> np.ndarray:
    """Shares paired in whole percent, rounded down: 50 or more exactly where half or more is paired (the
    page's green), so 49.5 % stays red. A share is a count over 2m (m: the edge's pieces, each end paired or
    not): 100 x share is an integer or at least 1/(2m) below one, so 1e-9 only undoes float error (0.57 x 100
    = 56.99...)."""
    return np.floor(100 * np.asarray(shares, np.float64) + 1e-9).astype(np.uint64)


def _drawing_chunk(tasks: list[FrameTask]) -> list[str]:
    return [frame_drawing(task) for task in tasks]


def frame_drawings(blocks: list[BrowserBlock], frames: list[tuple[int, str]], workers: int = 1) -> list[str]:
    """The drawings of the kept frames ((block index, frame id)), in order, in `workers` processes (0: one
    per core): the metric's matching of each run on each frame is the report's longest work here."""
    tasks = [frame_task(blocks[b], frame) for b, frame in frames]
    workers = workers if workers > 0 else os.cpu_count() or 1
    out: list[str] = []
    with track("report.html frames", len(tasks)) as advance:
        if workers <= 1 or len(tasks) < 2 * workers:
            for task in tasks:
                out.append(frame_drawing(task))
                advance()
            return out
        size = max(1, min(64, len(tasks) // (4 * workers)))
        chunks = [tasks[i : i + size] for i in range(0, len(tasks), size)]
        with ProcessPoolExecutor(workers) as pool:
            for chunk, part in zip(chunks, pool.map(_drawing_chunk, chunks)):
                out += part
                advance(len(chunk))
    return out


def rounded(value: float | None) -> float | None:
    """A score as the page gets it: finer than it shows (0.1 %), so that it rounds once."""
    return None if value is None else round(value, 6)


def plain(text: str) -> str:
    """Markdown's code spans as plain text (the page shows notes and labels as text, not markdown)."""
    return re.sub(r"`([^`]*)`", r"\1", text)


def kept_thumbnails(blocks: list[BrowserBlock], kept: Kept) -> tuple[dict[tuple[int, str], str], list[str]]:
    """The front camera images of the kept frames only ({(block index, frame id): data URI}), and a note
    per block where some have none."""
    thumbs, notes = {}, []
    for b, block in enumerate(blocks):
        frames = [f for k, f in kept.frames if k == b]
        if block.data is None or not frames:
            continue
        found, note = front_thumbnails(block.data, frames)
        thumbs |= {(b, f): uri for f, uri in found.items()}
        notes += [f"{block.label}: {note}"] if note else []
    return thumbs, notes


def browser_data(
    blocks: list[BrowserBlock], limit: int, notes: list[str], seed: int = SEED, workers: int = 1,
    thumbnails: bool = False,
) -> dict:  # fmt: skip
    """Everything browser.js reads, JSON-able: the blocks and runs, the kept frames' columns and drawings
    (`thumbnails`: and front camera images), the reasons, and what was left out."""
    from benchmark.report.style import STYLE

    kept = keep_frames(blocks, limit, seed)
    thumbs, thumb_notes = kept_thumbnails(blocks, kept) if thumbnails else ({}, [])
    drawings = frame_drawings(blocks, kept.frames, workers)
    every = [(b, run) for b, block in enumerate(blocks) for run in block.runs]  # the runs' columns, in order
    names = ("id", "block", "why", "junctions", "length", "drawing", "thumbnail")
    columns: dict[str, list] = {name: [] for name in names}
    # per run: P, R, F1 and J-TOPO F1 of each kept frame, and whether it scored the frame (0 or 1)
    scores = [{"p": [], "r": [], "f1": [], "jf1": [], "scored": []} for _ in every]
    for (b, frame), drawing in zip(kept.frames, drawings):
        block, gt = blocks[b], blocks[b].gt[frame]
        edges = unique_edges(gt, True)
        length = np.hypot(gt.x[edges[:, 1]] - gt.x[edges[:, 0]], gt.y[edges[:, 1]] - gt.y[edges[:, 0]]).sum()
        # the directed junctions of the metric's densified ground truth, as each of its count rows has them
        row = next(run.counts[frame] for run in block.runs if frame in run.counts)
        values = (frame, b, kept.why[(b, frame)], int(row[DIRECTED["n_junctions"]]), round(float(length), 1),
                  drawing, thumbs.get((b, frame), ""))  # fmt: skip
        for name, value in zip(names, values):
            columns[name].append(value)
        for column, (run_block, run) in zip(scores, every):
            row = run.counts.get(frame) if run_block == b else None
            s = frame_scores(row) if row is not None else FrameScores(None, None, None, None)
            for key, value in (("p", s.precision), ("r", s.recall), ("f1", s.f1), ("jf1", s.junction_f1)):
                column[key].append(rounded(value))
            column["scored"].append(int(row is not None))
    # drawn: the run has predictions.parquet (its drawings are in each frame's, in the runs' order)
    runs = [{"name": run.name, "block": b, "drawn": run.predictions is not None} for b, run in every]
    left_out = kept.total - len(kept.frames)
    return {
        "style": STYLE.as_json(),
        "quantum": QUANTUM,
        "blocks": [{"label": plain(block.label), "dataset": block.dataset, "split": block.split,
                    "range": crop_of(block)} for block in blocks],
        "runs": runs,
        "frames": columns,
        "scores": scores,
        "reasons": kept.reasons,
        "total": kept.total,
        "left_out": left_out,
        "limit": limit,
        "notes": [plain(note) for note in notes + thumb_notes],
    }  # fmt: skip


def crop_of(block: BrowserBlock) -> list[float]:
    """[x_min, x_max, y_min, y_max] of the block's range, the drawings' frame."""
    crop = Range.parse(block.params.bev_range)
    return [crop.x_min, crop.x_max, crop.y_min, crop.y_max]
