"""Graph tables: the Parquet lane graphs of predictions and of the ground truth, read, checked, written.
Also what a prepared dataset says of them: the perception range its graphs were cut to.

A graph table has one row per frame: `frame_id: string, x: list<float32>, y: list<float32>,
src: list<int32>, dst: list<int32>` (docs/guide/prepare.md). The ground truth is the `graphs` table of a
prepared dataset (a folder) or one such file; predictions are one file (or a folder of shards).
Predictions written by `cli eval` record the target parameters of the dataset their model was trained on
(TARGETS_KEY in the Parquet metadata).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline import io
from pipeline.lane_graph import LaneGraph
from pipeline.manifest import PreparedData

COLUMNS = ("frame_id", "x", "y", "src", "dst")
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
        files = io.shard_files(path) if path.is_dir() else [path]
        tables = [pq.ParquetFile(file).read() for file in files]
        # as a dataset scan reads them: every shard in the first one's schema (a cast only where it differs:
        # it imports pyarrow.compute, 0.07 s of a one-frame `cli score`)
        schema = tables[0].schema if tables else None
        same = [t if t.schema.equals(schema) else t.cast(schema) for t in tables]
        table = pa.concat_tables(same) if tables else pa.table({})
    except (pa.ArrowInvalid, pa.ArrowTypeError, OSError, ValueError) as error:
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
    offsets = io.numbers(column.offsets).astype(np.int64)
    if column.values.null_count:
        at = np.flatnonzero(column.values.is_null().to_numpy(zero_copy_only=False))[0]
        raise GraphTableError(
            f"{path}: frame {frame_ids[np.searchsorted(offsets, at, 'right') - 1]}: null in {name}"
        )
    values = io.numbers(column.values).astype(dtype)
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


def default_range(gt_path: Path) -> str:
    """The perception range a prepared dataset was cut to (its manifest), else 30x60."""
    return PreparedData.open(gt_path).bev_range
