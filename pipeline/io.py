"""Parquet I/O of the prepared dataset: one shard per log and table, written atomically, and the rows of a
log's tables."""

from __future__ import annotations

import json
import os
import zlib
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.errors import DataError
from pipeline.geometry import matrix_quaternion

if TYPE_CHECKING:
    from pipeline.records import AnnotatedLanes, Frame
    from pipeline.targets import FrameTargets, TargetOptions

SCHEMA_VERSION = 3  # 2: frames.ground_z; 3: frames.sample_token and frames.ground_slope
TABLES = ("frames", "graphs", "paths", "pieces", "piece_links", "rasters")
# OpenLane-V2's lanes as annotated (with heights) and links, unchanged beside its graph: its shards alone
ANNOTATED_LANES = "annotated_lanes"
ALL_TABLES = (*TABLES, ANNOTATED_LANES)

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
SCHEMAS[ANNOTATED_LANES] = pa.schema(
    [
        ("frame_id", pa.string()),
        ("openlanev2_split", pa.string()),  # the submission key: the split folder the frame file lies in,
        ("segment_id", pa.string()),  # its segment
        ("timestamp", pa.string()),  # and its timestamp as the file names it
        ("lane_ids", pa.list_(pa.string())),
        ("lane_sizes", i32_list),  # points per lane
        ("points", f64_list),  # every lane's (n, 3) points in OpenLane-V2's ego frame, flat, lane after lane
        ("links", f64_list),  # topology_lclc, (L, L) row-major
        ("images_missing", pa.int32()),  # its cameras whose image file is absent; 1 where it names none
    ]
)


def dataset_tables(dataset: str) -> tuple[str, ...]:
    """The tables of a dataset's shards: OpenLane-V2's add its annotated lanes."""
    return ALL_TABLES if dataset == "openlanev2" else TABLES


def list_array(values: list[np.ndarray], value_type: pa.DataType) -> pa.ListArray:
    """A list column from per-row numpy arrays without a Python loop per element."""
    lengths = np.array([len(v) for v in values], np.int32)
    offsets = np.concatenate([[0], np.cumsum(lengths, dtype=np.int64)]).astype(np.int32)
    flat = np.concatenate(values) if values else np.zeros(0)
    return pa.ListArray.from_arrays(pa.array(offsets, pa.int32()), pa.array(flat, value_type))


def shard_path(out: Path, table: str, shard: str) -> Path:
    return out / table / f"{shard}.parquet"


def shard_done(out: Path, shard: str, tables: tuple[str, ...] = TABLES) -> bool:
    return all(shard_path(out, table, shard).is_file() for table in tables)


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


def frame_row(frame: Frame, targets: FrameTargets) -> dict:
    return {
        "frame_id": frame.frame_id,
        "dataset": frame.dataset,
        "split": frame.split,
        "sample_token": frame.sample_token,
        "log_id": frame.log_id,
        "timestamp_ns": frame.timestamp_ns,
        "city": frame.city,
        "pose_translation": frame.ego_to_world[:3, 3].tolist(),
        "pose_rotation": matrix_quaternion(frame.ego_to_world).tolist(),
        "cameras": [
            {
                "name": c.name,
                "image_path": c.image_path,
                "intrinsics": np.asarray(c.intrinsics, np.float64).ravel().tolist(),
                "sensor_to_ego": np.asarray(c.sensor_to_ego, np.float64).ravel().tolist(),
                "width": c.width,
                "height": c.height,
            }
            for c in frame.cameras
        ],
        "lidar_path": frame.lidar_path,
        "lidar_to_ego": np.asarray(frame.lidar_to_ego, np.float64).ravel().tolist(),
        "ground_z": frame.ground_z,
        "ground_slope": [float(v) for v in frame.ground_slope],
        "n_vertices": len(targets.graph.x),
        "n_edges": len(targets.graph.src),
        "n_paths": len(targets.paths.vertex_ids),
        "n_pieces": len(targets.pieces.chains),
        "n_junctions": len(targets.pieces.junctions),
        "path_cap_hit": targets.paths.cap_hit,
    }


def chain_table(
    frame_ids: list[str], chains: list[list[np.ndarray]], graphs, points, lengths, index: str
) -> pa.Table:
    """Rows of paths or pieces: one per chain, with its vertex ids, full polyline and resampled points."""
    flat = [c for frame_chains in chains for c in frame_chains]
    xs = [g.x[c] for g, frame_chains in zip(graphs, chains) for c in frame_chains]
    ys = [g.y[c] for g, frame_chains in zip(graphs, chains) for c in frame_chains]
    resampled = np.concatenate(points).astype(np.float32) if flat else np.zeros((0, 1, 2), np.float32)
    counts = [len(c) for c in chains]
    return pa.table(
        {
            "frame_id": pa.array(np.repeat(frame_ids, counts).tolist(), pa.string()),
            index: pa.array(np.concatenate([np.arange(n) for n in counts] or [[]]).astype(np.int32)),
            "vertex_ids": list_array([c.astype(np.int32) for c in flat], pa.int32()),
            "x": list_array(xs, pa.float32()),
            "y": list_array(ys, pa.float32()),
            "rx": list_array(list(resampled[:, :, 0]), pa.float32()),
            "ry": list_array(list(resampled[:, :, 1]), pa.float32()),
            "length": pa.array(np.concatenate(lengths or [[]]).astype(np.float32)),
        }
    )


def log_tables(
    frames: list[Frame], targets: list[FrameTargets], options: TargetOptions
) -> dict[str, pa.Table]:
    ids = [f.frame_id for f in frames]
    graphs = [t.graph for t in targets]
    height, width = options.grid.shape
    links = [(t.pieces.link_src, t.pieces.link_dst) for t in targets]
    return {
        "frames": pa.Table.from_pylist(list(map(frame_row, frames, targets)), SCHEMAS["frames"]),
        "graphs": pa.table(
            {
                "frame_id": pa.array(ids, pa.string()),
                "x": list_array([g.x for g in graphs], pa.float32()),
                "y": list_array([g.y for g in graphs], pa.float32()),
                "src": list_array([g.src for g in graphs], pa.int32()),
                "dst": list_array([g.dst for g in graphs], pa.int32()),
            }
        ),
        "paths": chain_table(
            ids, [t.paths.vertex_ids for t in targets], graphs,
            [t.path_points for t in targets], [t.path_lengths for t in targets], "path_index",
        ),
        "pieces": chain_table(
            ids, [t.pieces.chains for t in targets], graphs,
            [t.piece_points for t in targets], [t.piece_lengths for t in targets], "piece_index",
        ),
        "piece_links": pa.table(
            {
                "frame_id": pa.array(np.repeat(ids, [len(s) for s, _ in links]).tolist(), pa.string()),
                "src_piece": pa.array(np.concatenate([s for s, _ in links] or [[]]).astype(np.int32)),
                "dst_piece": pa.array(np.concatenate([d for _, d in links] or [[]]).astype(np.int32)),
            }
        ),
        "rasters": pa.table(
            {
                "frame_id": pa.array(ids, pa.string()),
                "height": pa.array([height] * len(ids), pa.int32()),
                "width": pa.array([width] * len(ids), pa.int32()),
                "resolution": pa.array([options.resolution] * len(ids), pa.float32()),
                "line_width": pa.array([options.line_width] * len(ids), pa.int32()),
                "mask": pa.array([encode_mask(t.mask) for t in targets], pa.binary()),
                "direction": pa.array([encode_raster(t.direction) for t in targets], pa.binary()),
            }
        ),
    }  # fmt: skip


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


def read_annotated_lanes(data: Path, frame_ids=None) -> dict[str, AnnotatedLanes]:
    """The annotated lanes of an OpenLane-V2 prepared dataset, unchanged and uncropped (points in
    OpenLane-V2's ego frame, links 0/1), by frame id: every frame's, or those of `frame_ids` that it holds."""
    from pipeline.records import AnnotatedLanes

    columns = ["frame_id", "lane_ids", "lane_sizes", "points", "links"]
    table = read_table(openlanev2_data(data), ANNOTATED_LANES, columns)
    wanted = None if frame_ids is None else set(frame_ids)
    # numbers of whole columns at once, then cut per frame: a row at a time would make every point a float
    rows = [table.column(name).combine_chunks() for name in ("lane_sizes", "points", "links")]
    sizes, points, links = (numbers(column.flatten()) for column in rows)
    ends = [np.cumsum(numbers(column.value_lengths())) for column in rows]
    lanes, start = {}, [0, 0, 0]
    for i, (frame_id, ids) in enumerate(zip(table.column("frame_id").to_pylist(),
                                            table.column("lane_ids").to_pylist())):  # fmt: skip
        size, point, link = (values[start[k] : ends[k][i]] for k, values in enumerate((sizes, points, links)))
        start = [int(end[i]) for end in ends]
        if wanted is not None and frame_id not in wanted:  # (pyarrow.compute's filter costs 0.5 s to import)
            continue
        frame_points = point.astype(np.float64).reshape(-1, 3)
        lanes[frame_id] = AnnotatedLanes(
            np.split(frame_points, np.cumsum(size)[:-1]) if len(ids) else [],
            link.astype(np.float64).reshape(len(ids), len(ids)),
            list(ids),
        )
    return lanes


def read_openlanev2_keys(data: Path) -> dict[str, tuple[str, str, str]]:
    """Frame id -> its OpenLane-V2 submission key: (split folder, segment_id, timestamp as the file names
    it)."""
    table = read_table(openlanev2_data(data), ANNOTATED_LANES, ["frame_id", "openlanev2_split", "segment_id",
                                                                 "timestamp"])  # fmt: skip
    columns = [table.column(name).to_pylist() for name in table.column_names]
    return {frame: (split, segment, timestamp) for frame, split, segment, timestamp in zip(*columns)}


def openlanev2_data(data: Path) -> Path:
    """`data` if it holds OpenLane-V2's annotated lanes, else one ValueError saying what it is."""
    if not (Path(data) / ANNOTATED_LANES).is_dir():
        raise ValueError(f"{data}: holds no {ANNOTATED_LANES} (not a dataset prepared with `cli prepare "
                         "--dataset openlanev2`)")  # fmt: skip
    return Path(data)
