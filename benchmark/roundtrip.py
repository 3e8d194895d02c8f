"""`cli roundtrip`: the ground truth through a representation and back, scored against itself
(LaneGAP Tab. 10, post-processing accuracy).

path:  the `paths` table (full polylines x, y) -> Path2Graph
piece: the `pieces` table (full polylines x, y) and `piece_links` -> Piece2Graph
pixel: the `rasters` table (mask and direction map) -> Pixel2Graph
The ground truth is the `graphs` table of the same prepared dataset. Path runs Path2Graph with
merge_radius 0 by default: ground-truth paths share their common vertices exactly, so identical points
are all there is to merge, and the near merge (for predictions) would merge distinct lanes that the
map itself puts closer than 0.15 m (docs/METRICS.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pyarrow.dataset import field as ds_field

from benchmark.graph_table import default_range, graphs_from_table
from benchmark.graphs.path2graph import path2graph
from benchmark.graphs.piece2graph import piece2graph
from benchmark.graphs.pixel2graph import pixel2graph
from benchmark.metric.params import MetricParams
from benchmark.score import score_pairs, write_result
from pipeline.geometry import Range
from pipeline.io import decode_raster, read_table
from pipeline.lane_graph import LaneGraph
from pipeline.progress import track
from pipeline.raster import Grid

VIAS = ("path", "piece", "pixel")


def polylines_by_frame(data: Path, table: str, index: str) -> dict[str, list[np.ndarray]]:
    """{frame_id: [(n, 2) polyline, ...] in index order} of the paths or pieces table."""
    rows = read_table(data, table, columns=["frame_id", index, "x", "y"]).sort_by(
        [("frame_id", "ascending"), (index, "ascending")]
    )
    out: dict[str, list[np.ndarray]] = {}
    for frame_id, x, y in zip(*(rows.column(c).to_pylist() for c in ("frame_id", "x", "y"))):
        out.setdefault(frame_id, []).append(
            np.stack([np.asarray(x, np.float32), np.asarray(y, np.float32)], axis=1)
        )
    return out


def rebuild(data: Path, via: str, frame_ids: list[str], merge_radius: float) -> dict[str, LaneGraph]:
    """{frame_id: the graph rebuilt from the representation}."""
    if via not in VIAS:
        raise ValueError(f"via must be one of {', '.join(VIAS)}, not {via!r}")
    out: dict[str, LaneGraph] = {}
    with track(f"rebuild via {via}", len(frame_ids)) as advance:
        if via == "path":
            paths = polylines_by_frame(data, "paths", "path_index")
            for f in frame_ids:
                out[f] = path2graph(paths.get(f, []), merge_radius=merge_radius)
                advance()
        elif via == "piece":
            pieces = polylines_by_frame(data, "pieces", "piece_index")
            links: dict[str, list[tuple[int, int]]] = {}
            table = read_table(data, "piece_links")
            for f, i, j in zip(
                *(table.column(c).to_pylist() for c in ("frame_id", "src_piece", "dst_piece"))
            ):
                links.setdefault(f, []).append((i, j))
            for f in frame_ids:
                out[f] = piece2graph(pieces.get(f, []), np.array(links.get(f, [])))
                advance()
        else:
            crop = Range.parse(default_range(data))
            wanted = ds_field("frame_id").isin(frame_ids)
            for row in read_table(data, "rasters", filter=wanted).to_pylist():
                mask, direction = decode_raster(row)
                # the table stores float32 (0.15000000596): the grid's own value places the pixels
                grid = Grid(crop, round(float(row["resolution"]), 6))
                out[row["frame_id"]] = pixel2graph(mask, direction, grid)
                advance()
    return {f: out.get(f, LaneGraph.empty()) for f in frame_ids}


def roundtrip(
    data: Path,
    via: str,
    out: Path | None = None,
    merge_radius: float = 0.0,
    workers: int = 1,
    frame_stride: int = 1,
) -> dict:
    """The scores of the ground truth rebuilt through `via` against the ground truth itself
    (every frame_stride-th frame, in frame_id order)."""
    if via not in VIAS:
        raise ValueError(f"via must be one of {', '.join(VIAS)}, not {via!r}")
    if frame_stride < 1 or merge_radius < 0:
        raise ValueError(
            f"--frame-stride must be at least 1 ({frame_stride}), --merge-radius at least 0 ({merge_radius})"
        )
    data = Path(data)
    gt = graphs_from_table(read_table(data, "graphs"), data / "graphs")
    frame_ids = sorted(gt)[::frame_stride]
    rebuilt = rebuild(data, via, frame_ids, merge_radius)
    params = MetricParams(bev_range=default_range(data))
    result = score_pairs([(rebuilt[f], gt[f]) for f in frame_ids], params, workers)
    result.update(data=str(data), via=via)
    if via == "path":
        result["merge_radius"] = merge_radius
    write_result(result, out)
    return result
