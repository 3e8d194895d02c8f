"""Bootstrap confidence intervals of the pooled F1 scores, over frames.

A set's TOPO and Junction TOPO pool sums over its frames (docs/METRICS.md): precision is the sum of the
pairs' fractions over the number of predicted vertices, and so on. Each frame's sums are kept
(`Totals.frame_table`, one row per frame, FRAME_COLUMNS), so a bootstrap draw (the frames resampled with
replacement, then pooled again) is a weighted sum of rows: no second metric pass. Every draw is one
column of a frames x draws index matrix; counted, it is a (draws, frames) weight matrix, and all draws
pool at once as weights @ counts.

The interval is the percentile one: the 2.5th and 97.5th percentiles of the draws' F1. Two runs scored
on the same frames share the draws (a paired bootstrap): the interval of their difference says whether a
lead survives a different choice of frames. The draws depend only on the number of frames, the number
of draws and SEED, so every run of one split gets the same ones.

A run's counts are written by `cli eval` beside its metrics.json (FRAME_COUNTS), for `cli report`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from benchmark.metric.totals import FRAME_COLUMNS, FRAME_FIELDS
from pipeline import io

DRAWS = 1000  # the default of `--bootstrap`
SEED = 0
LEVEL = 0.95
MODES = ("directed", "undirected")
METRICS = ("topo", "junction_topo")
FRAME_COUNTS = "frame_counts.parquet"  # in a run folder, written by `cli eval`


def check_draws(draws: int) -> None:
    if draws < 0:
        raise ValueError(f"--bootstrap must be 0 (no intervals) or a number of draws, not {draws}")


def weights(frames: int, draws: int, seed: int = SEED) -> np.ndarray:
    """(draws, frames) float64: how many times each frame is in each draw."""
    index = np.random.default_rng(seed).integers(0, frames, size=(frames, draws))  # column d: draw d
    cells = index + np.arange(draws) * frames
    return np.bincount(cells.ravel(), minlength=draws * frames).reshape(draws, frames).astype(np.float64)


def _ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """num / den, 0 where den is 0 (as the metric's own ratio)."""
    return np.divide(num, den, out=np.zeros_like(num), where=den != 0)


def pooled_f1(counts: np.ndarray, w: np.ndarray) -> dict[tuple[str, str], np.ndarray]:
    """{(mode, metric): F1 of each weighting (row of w)} of the per-frame counts (frames, FRAME_COLUMNS)."""
    sums = w @ counts
    out = {}
    for m, mode in enumerate(MODES):
        for k, metric in enumerate(METRICS):
            at = m * len(FRAME_FIELDS) + 4 * k
            pre, n_pred, rec, n_gt = sums[:, at], sums[:, at + 1], sums[:, at + 2], sums[:, at + 3]
            p, r = _ratio(pre, n_pred), _ratio(rec, n_gt)
            out[mode, metric] = _ratio(2 * p * r, p + r)
    return out


def _percentiles(values: np.ndarray, level: float) -> list[float]:
    tail = (1 - level) / 2
    return [float(v) for v in np.quantile(values, [tail, 1 - tail])]


def intervals(counts: np.ndarray, draws: int = DRAWS, seed: int = SEED, level: float = LEVEL) -> dict:
    """{mode: {metric: [low, high]}}: the F1 interval of one set of frames."""
    f1 = pooled_f1(counts, weights(len(counts), draws, seed))
    return {mode: {metric: _percentiles(f1[mode, metric], level) for metric in METRICS} for mode in MODES}


def paired(a: np.ndarray, b: np.ndarray, draws: int = DRAWS, seed: int = SEED, level: float = LEVEL) -> dict:
    """{mode: {metric: [low, high]}}: the interval of F1(a) - F1(b), two runs' counts on the same frames
    in the same order, both pooled with the same draws."""
    if a.shape != b.shape:
        raise ValueError(f"paired bootstrap: counts of {len(a)} and {len(b)} frames; they must be the same")
    w = weights(len(a), draws, seed)
    f1_a, f1_b = pooled_f1(a, w), pooled_f1(b, w)
    return {
        mode: {metric: _percentiles(f1_a[mode, metric] - f1_b[mode, metric], level) for metric in METRICS}
        for mode in MODES
    }


def add_intervals(result: dict, counts: np.ndarray, draws: int = DRAWS, seed: int = SEED) -> dict:
    """A score result with "f1_ci" beside each F1 and the bootstrap's settings; as it was when draws is 0
    or there are no frames."""
    check_draws(draws)
    if draws == 0 or len(counts) == 0:
        return result
    for mode, by_metric in intervals(counts, draws, seed).items():
        for metric, interval in by_metric.items():
            result[mode][metric]["f1_ci"] = interval
    result["bootstrap"] = {"draws": draws, "seed": seed, "level": LEVEL, "over": "frames",
                           "interval": "percentile"}  # fmt: skip
    return result


def write_frame_counts(path: Path, frame_ids: list[str], counts: np.ndarray) -> None:
    """The per-frame counts as Parquet: frame_id, then one float64 column per FRAME_COLUMNS (atomic)."""
    columns = {"frame_id": pa.array(frame_ids, pa.string())}
    columns.update({name: pa.array(counts[:, i], pa.float64()) for i, name in enumerate(FRAME_COLUMNS)})
    table = pa.table(columns)
    io.write_atomic(Path(path), lambda tmp: pq.write_table(table, tmp))


def read_frame_counts(path: Path) -> tuple[list[str], np.ndarray]:
    """(frame ids, counts) of a FRAME_COUNTS file; ValueError naming the file when it is not one."""
    try:
        table = pq.read_table(path)
    except (pa.ArrowInvalid, OSError) as error:
        raise ValueError(f"{path}: not a readable Parquet file ({error})") from error
    missing = [name for name in ("frame_id", *FRAME_COLUMNS) if name not in table.column_names]
    if missing:
        raise ValueError(f"{path}: not a per-frame count table (no column {missing[0]})")
    counts = np.stack([table.column(name).to_numpy().astype(np.float64) for name in FRAME_COLUMNS], axis=1)
    if table.column("frame_id").null_count or not np.isfinite(counts).all() or (counts < 0).any():
        raise ValueError(f"{path}: a frame_id is null, or a count negative, NaN or infinite")
    return [str(f) for f in table.column("frame_id").to_pylist()], counts.reshape(-1, len(FRAME_COLUMNS))
