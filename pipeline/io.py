"""Parquet I/O of the prepared dataset: one shard per log and table, written atomically."""

from __future__ import annotations

import json
import os
import zlib
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.errors import DataError

SCHEMA_VERSION = 3  # 2: frames.ground_z; 3: frames.sample_token and frames.ground_slope
TABLES = ("frames", "graphs", "paths", "pieces", "piece_links", "rasters")

f32_list = pa.list_(pa.float32())
f64_list = pa.list_(pa.float64())
i32_list = pa.list_(pa.int32())
CAMERA = pa.struct(
    [
        ("name", pa.string()),
        ("image_path", pa.string()),
        ("intrinsics", f64_list),
        ("sensor_to_ego", f64_list),
        ("width", pa.int32()),
        ("height", pa.int32()),
    ]
)
SCHEMAS = {
    "frames": pa.schema(
        [
            ("frame_id", pa.string()),
            ("dataset", pa.string()),
            ("split", pa.string()),
            ("sample_token", pa.string()),  # nuScenes: the sample's token; AV2: null (no such token)
            ("log_id", pa.string()),
            ("timestamp_ns", pa.int64()),
            ("city", pa.string()),
            ("pose_translation", f64_list),
            ("pose_rotation", f64_list),
            ("cameras", pa.list_(CAMERA)),
            ("lidar_path", pa.string()),
            ("lidar_to_ego", f64_list),
            ("ground_z", pa.float32()),
            ("ground_slope", f64_list),  # (2) dz/dx, dz/dy: the ground is z = ground_z + a x + b y
            ("n_vertices", pa.int32()),
            ("n_edges", pa.int32()),
            ("n_paths", pa.int32()),
            ("n_pieces", pa.int32()),
            ("n_junctions", pa.int32()),
            ("path_cap_hit", pa.bool_()),
        ]
    ),
    "graphs": pa.schema(
        [("frame_id", pa.string()), ("x", f32_list), ("y", f32_list), ("src", i32_list), ("dst", i32_list)]
    ),
    "paths": pa.schema(
        [
            ("frame_id", pa.string()),
            ("path_index", pa.int32()),
            ("vertex_ids", i32_list),
            ("x", f32_list),
            ("y", f32_list),
            ("rx", f32_list),
            ("ry", f32_list),
            ("length", pa.float32()),
        ]
    ),
    "piece_links": pa.schema(
        [("frame_id", pa.string()), ("src_piece", pa.int32()), ("dst_piece", pa.int32())]
    ),
    "rasters": pa.schema(
        [
            ("frame_id", pa.string()),
            ("height", pa.int32()),
            ("width", pa.int32()),
            ("resolution", pa.float32()),
            ("line_width", pa.int32()),
            ("mask", pa.binary()),
            ("direction", pa.binary()),
        ]
    ),
}
SCHEMAS["pieces"] = pa.schema(
    [("piece_index", pa.int32()) if f.name == "path_index" else f for f in SCHEMAS["paths"]]
)


def list_array(values: list[np.ndarray], value_type: pa.DataType) -> pa.ListArray:
    """A list column from per-row numpy arrays without a Python loop per element."""
    lengths = np.array([len(v) for v in values], np.int32)
    offsets = np.concatenate([[0], np.cumsum(lengths, dtype=np.int64)]).astype(np.int32)
    flat = np.concatenate(values) if values else np.zeros(0)
    return pa.ListArray.from_arrays(pa.array(offsets, pa.int32()), pa.array(flat, value_type))


def shard_path(out: Path, table: str, shard: str) -> Path:
    return out / table / f"{shard}.parquet"


def shard_done(out: Path, shard: str) -> bool:
    return all(shard_path(out, table, shard).is_file() for table in TABLES)


def write_atomic(path: Path, write) -> None:
    """write(tmp_path) then rename: readers never see a half-written file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_shard(out: Path, shard: str, tables: dict[str, pa.Table]) -> None:
    """Every table of one log; frames last, so that a shard with frames is complete."""
    for name in sorted(tables, key=lambda n: n == "frames"):
        table = tables[name].cast(SCHEMAS[name])
        write_atomic(
            shard_path(out, name, shard), lambda tmp, t=table: pq.write_table(t, tmp, compression="zstd")
        )


def write_json(path: Path, obj) -> None:
    write_atomic(path, lambda tmp: tmp.write_text(json.dumps(obj, indent=2) + "\n"))


def same_type(a: pa.DataType, b: pa.DataType) -> bool:
    """Equal Arrow types, whatever the names of list items (Parquet writers name them item or element)."""
    if pa.types.is_list(a) and pa.types.is_list(b):
        return same_type(a.value_type, b.value_type)
    if pa.types.is_struct(a) and pa.types.is_struct(b):
        return [f.name for f in a] == [f.name for f in b] and all(
            map(same_type, (f.type for f in a), (f.type for f in b))
        )
    return a == b


def read_table(out: Path, table: str, columns: list[str] | None = None, filter=None) -> pa.Table:
    """One table of a prepared dataset, all shards together (in the order of their names), cast to its
    schema; `filter`: a pyarrow.dataset expression on its rows."""
    folder = Path(out) / table
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such table (is {out} a prepared dataset?)")
    names = columns or SCHEMAS[table].names
    paths, shards = shard_files(folder), []
    for path in paths:
        try:
            shards.append(pq.ParquetFile(path))
            physical = shards[-1].schema_arrow
        except pa.ArrowInvalid as error:
            raise DataError(path, "Parquet footer", "unreadable: truncated or not Parquet") from error
        # a column a shard lacks must not be read as nulls, nor one of another type cast: refuse the shard
        for name in names:
            if name not in physical.names:
                problem = "missing: prepared by an older version; re-run `cli prepare` with --overwrite"
                raise DataError(path, f"column {name}", problem)
            found, expected = physical.field(name).type, SCHEMAS[table].field(name).type
            if not same_type(found, expected):
                raise DataError(path, f"column {name}", f"is {found}, not {expected}")
    if filter is not None:  # a dataset scan filters each shard as it reads it
        import pyarrow.dataset as ds  # it imports pandas (0.2 s): loaded only where a filter asks for it

        scan = ds.dataset([str(path) for path in paths], format="parquet", schema=SCHEMAS[table])
        return scan.to_table(columns=columns, filter=filter)
    schema = pa.schema([SCHEMAS[table].field(name) for name in names])
    tables = [shard.read(columns=names).cast(schema) for shard in shards]
    return pa.concat_tables(tables) if tables else schema.empty_table()


def shard_files(folder: Path) -> list[Path]:
    """The Parquet files of a folder of shards, as pyarrow's datasets find them: by name, hidden
    (`.`, `_`) ones left out (an atomic write's temporary file)."""
    return sorted(p for p in Path(folder).glob("*.parquet") if not p.name.startswith((".", "_")))


def numbers(array: pa.Array) -> np.ndarray:
    """A numeric array without nulls as numpy, viewed from its data buffer: pyarrow's own to_numpy imports
    pandas on its first call (0.2 s, most of a one-frame `cli score`)."""
    kind = "f" if pa.types.is_floating(array.type) else "i" if pa.types.is_signed_integer(array.type) else "u"
    dtype = np.dtype(f"{kind}{array.type.bit_width // 8}")
    return np.frombuffer(array.buffers()[1], dtype, len(array), array.offset * dtype.itemsize)


def count_rows(out: Path, table: str) -> int:
    return sum(pq.read_metadata(p).num_rows for p in sorted((out / table).glob("*.parquet")))


def encode_mask(mask: np.ndarray) -> bytes:
    """A 0/1 mask packed to bits, then zlib: 8x less to compress on the hot path."""
    return zlib.compress(np.packbits(mask.astype(bool)).tobytes(), 1)


def encode_raster(array: np.ndarray) -> bytes:
    return zlib.compress(np.ascontiguousarray(array, np.uint8).tobytes(), 1)


def decode_raster(row: dict) -> tuple[np.ndarray, np.ndarray]:
    """(mask, direction) uint8 arrays of one `rasters` row (a dict, e.g. from Table.to_pylist())."""
    shape = (row["height"], row["width"])
    bits = np.frombuffer(zlib.decompress(row["mask"]), np.uint8)
    mask = np.unpackbits(bits, count=shape[0] * shape[1]).reshape(shape)
    direction = np.frombuffer(zlib.decompress(row["direction"]), np.uint8).reshape(shape)
    return mask, direction
