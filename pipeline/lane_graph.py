"""Crop a map's lane centerlines to the ego frame and build the ground-truth lane graph."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.geometry import AV2_EGO_FROM_BEV, Range, clip_polylines
from pipeline.kernels import kernel
from pipeline.records import AnnotatedLanes, Lane


@dataclass
class LaneGraph:
    """A directed lane graph: vertices (x, y) in metres and straight edges src -> dst."""

    x: np.ndarray  # (V,) float32
    y: np.ndarray  # (V,) float32
    src: np.ndarray  # (E,) int32
    dst: np.ndarray  # (E,) int32

    @property
    def xy(self) -> np.ndarray:
        return np.stack([self.x, self.y], axis=1)

    @classmethod
    def empty(cls) -> LaneGraph:
        return cls(
            np.zeros(0, np.float32), np.zeros(0, np.float32), np.zeros(0, np.int32), np.zeros(0, np.int32)
        )


def graph_of_edges(
    x: np.ndarray, y: np.ndarray, src: np.ndarray, dst: np.ndarray, score: np.ndarray | None = None
) -> tuple[LaneGraph, np.ndarray | None]:
    """The LaneGraph of vertices (x, y) and edges src -> dst, self-loops and repeated edges dropped, the
    edges in (src, dst) order; with `score` (one per given edge), each kept edge's highest (else None)."""
    n, real = len(x), src != dst
    keys = (src.astype(np.int64) * n + dst)[real]
    if score is None:
        key, best = np.unique(keys), None
    else:
        key, edge_of = np.unique(keys, return_inverse=True)
        best = np.full(len(key), -np.inf)
        np.maximum.at(best, edge_of.ravel(), np.asarray(score, np.float64)[real])
    return LaneGraph(x, y, (key // n).astype(np.int32), (key % n).astype(np.int32)), best


@dataclass
class LaneMap:
    """The lanes of one map stacked into arrays, so that each frame crops them in a few vector ops."""

    ids: list[str]
    points: np.ndarray  # (N, 3) world coordinates of every centerline point
    offsets: np.ndarray  # (L + 1,) lane i is points[offsets[i]:offsets[i + 1]]
    centers: np.ndarray  # (L, 2) bounding-circle centre of each lane
    radii: np.ndarray  # (L,) bounding-circle radius of each lane
    link_src: np.ndarray  # (C,) lane index of each connection lane -> successor
    link_dst: np.ndarray  # (C,)

    @classmethod
    def from_lanes(cls, lanes: list[Lane]) -> LaneMap:
        lanes = sorted(lanes, key=lambda lane: lane.id)
        index = {lane.id: i for i, lane in enumerate(lanes)}
        lengths = np.array([len(lane.xyz) for lane in lanes], np.int64)
        offsets = np.concatenate([[0], np.cumsum(lengths)])
        points = np.concatenate([lane.xyz for lane in lanes]) if lanes else np.zeros((0, 3))
        lo = np.array([lane.xyz[:, :2].min(0) for lane in lanes]).reshape(-1, 2)
        hi = np.array([lane.xyz[:, :2].max(0) for lane in lanes]).reshape(-1, 2)
        # successors that name lanes outside this map are ignored (real AV2 maps have them)
        links = [(i, index[s]) for i, lane in enumerate(lanes) for s in lane.successors if s in index]
        links = np.array(sorted(set(links)), np.int64).reshape(-1, 2)
        return cls(
            ids=[lane.id for lane in lanes],
            points=points.astype(np.float64),
            offsets=offsets,
            centers=(lo + hi) / 2,
            radii=np.linalg.norm(hi - lo, axis=1) / 2,
            link_src=links[:, 0],
            link_dst=links[:, 1],
        )


@kernel
def merge_labels(n, a, b):
    """Union-find over n points joined in pairs (a[k], b[k]): a label per point, numbered in order of
    first appearance. A numba kernel: scipy's connected_components costs more in set-up than the
    handful of merges of a frame."""
    parent = np.arange(n)
    for k in range(a.shape[0]):
        ra, rb = a[k], b[k]
        while parent[ra] != ra:
            ra = parent[ra]
        while parent[rb] != rb:
            rb = parent[rb]
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    label = np.empty(n, np.int64)
    count = 0
    for i in range(n):
        root = i
        while parent[root] != root:
            root = parent[root]
        if root == i:
            label[i] = count
            count += 1
        else:
            label[i] = label[root]  # root < i is labelled already
    return label


def crop_lane_graph(lane_map: LaneMap, world_to_ego: np.ndarray, rng: Range) -> LaneGraph:
    """The lane graph of one frame: every centerline moved into the ego frame and clipped to rng.

    Lanes that leave and re-enter the range give separate chains. A connection lane -> successor
    survives only when the end of the lane and the start of the successor both lie inside the range;
    its two endpoints then become one vertex (at their mean, which is the shared point in real maps).
    """
    return crop_scored_lane_graph(lane_map, world_to_ego, rng)[0]


def crop_scored_lane_graph(
    lane_map: LaneMap, world_to_ego: np.ndarray, rng: Range, lane_scores: np.ndarray | None = None
) -> tuple[LaneGraph, np.ndarray | None]:
    """(crop_lane_graph's graph, each edge's score): the highest score of the lanes it lies on (`lane_scores`:
    one per lane of `lane_map`, in its order; None: no scores)."""
    no_edge = (LaneGraph.empty(), None if lane_scores is None else np.zeros(0))
    ego_xy = -world_to_ego[:3, :3].T @ world_to_ego[:3, 3]
    near = np.flatnonzero(
        np.linalg.norm(lane_map.centers - ego_xy[:2], axis=1) <= lane_map.radii + rng.radius
    )
    if len(near) == 0:
        return no_edge
    starts, ends = lane_map.offsets[near], lane_map.offsets[near + 1]
    counts = ends - starts
    take = np.repeat(starts - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts) + np.arange(counts.sum())
    world = lane_map.points[take]
    ego = world @ world_to_ego[:3, :3].T + world_to_ego[:3, 3]
    offsets = np.concatenate([[0], np.cumsum(counts)])
    points, piece_offsets, piece_lane, has_start, has_end = clip_polylines(
        np.ascontiguousarray(ego[:, :2]), offsets, rng.x_min, rng.x_max, rng.y_min, rng.y_max
    )
    if len(points) == 0:
        return no_edge

    # edges between consecutive points of each clipped piece
    n = len(points)
    is_last = np.zeros(n, bool)
    is_last[piece_offsets[1:] - 1] = True
    src = np.flatnonzero(~is_last)
    dst = src + 1

    # merge the end of a lane with the start of its successor when both are inside
    local = np.full(len(lane_map.ids), -1, np.int64)
    local[near] = np.arange(len(near))
    end_vertex = np.full(len(near), -1, np.int64)
    start_vertex = np.full(len(near), -1, np.int64)
    end_vertex[piece_lane[has_end]] = piece_offsets[1:][has_end] - 1
    start_vertex[piece_lane[has_start]] = piece_offsets[:-1][has_start]
    a, b = local[lane_map.link_src], local[lane_map.link_dst]
    ok = (a >= 0) & (b >= 0)
    a, b = end_vertex[a[ok]], start_vertex[b[ok]]
    ok = (a >= 0) & (b >= 0)
    label = merge_labels(n, a[ok], b[ok])
    x, y = vertex_positions(label, points)
    label = merge_coincident(label, x, y)
    x, y = vertex_positions(label, points)

    score = None
    if lane_scores is not None:  # each edge's lane: the lane of the piece its first point belongs to
        point_piece = np.repeat(np.arange(len(piece_lane)), np.diff(piece_offsets))
        score = np.asarray(lane_scores, np.float64)[near][piece_lane][point_piece[src]]
    return graph_of_edges(x, y, label[src], label[dst], score)


# OpenLane-V2's ego frame (x forward, y left) onto the BEV axes (x right, y forward), as for AV2's
BEV_FROM_OPENLANEV2_EGO = np.linalg.inv(AV2_EGO_FROM_BEV)
LINK_THRESHOLD = 0.5  # a predicted link counts above this probability, as OpenLane-V2 reads topology_lclc


# OpenLane-V2 annotates 201 points per lane, a vertex every few centimetres; TOPO's densification splits each
# edge, so a graph's point count follows its vertices and the denser side loses (docs/METRICS.md). Lanes are
# simplified (Douglas-Peucker, end points kept) to within a centimetre, far below the metrics' 0.15 m, before
# they become a graph, ground truth and submissions alike: vertices where the lanes bend, as a map's are.
SIMPLIFY_M = 0.01


def simplified(lanes: list[np.ndarray]) -> list[np.ndarray]:
    """Each (n, 3) polyline with the points that shapely's Douglas-Peucker (in x, y) keeps at SIMPLIFY_M."""
    import shapely

    index = np.repeat(np.arange(len(lanes)), [len(lane) for lane in lanes])
    lines = shapely.linestrings(np.concatenate(lanes), indices=index)
    lines = shapely.simplify(lines, SIMPLIFY_M, preserve_topology=False)
    return [np.asarray(shapely.get_coordinates(line, include_z=True)) for line in lines]


def graph_of_annotated(lanes: AnnotatedLanes, rng: Range | None = None, simplify: bool = True) -> LaneGraph:
    """The BEV lane graph of OpenLane-V2 lanes: each lane a chain of its points, a link i -> j (an entry of
    `links` above LINK_THRESHOLD) joining i's last point to j's first, points at one place one vertex (so
    merges and forks are junctions); clipped to `rng` as crop_lane_graph clips a map (None: unclipped).
    `simplify`: each lane simplified first (SIMPLIFY_M); False: every annotated point a vertex."""
    return scored_graph_of_annotated(lanes, rng, simplify)[0]


def scored_graph_of_annotated(
    lanes: AnnotatedLanes, rng: Range | None = None, simplify: bool = True
) -> tuple[LaneGraph, np.ndarray | None]:
    """(graph_of_annotated's graph, each edge's score: the highest confidence of the lanes it lies on; None
    for annotated lanes, which have no confidence)."""
    if not len(lanes):
        return LaneGraph.empty(), None if lanes.confidence is None else np.zeros(0)
    bev = [p @ BEV_FROM_OPENLANEV2_EGO[:3, :3].T for p in lanes.points]
    bev = simplified(bev) if simplify else bev
    src, dst = np.nonzero(np.asarray(lanes.links) > LINK_THRESHOLD)
    names = [f"{i:09d}" for i in range(len(bev))]  # LaneMap sorts lanes by id: keep their order
    successors = [[] for _ in bev]
    for i, j in zip(src.tolist(), dst.tolist()):
        successors[i].append(names[j])
    lane_map = LaneMap.from_lanes([Lane(n, p, s) for n, p, s in zip(names, bev, successors)])
    if rng is None:
        reach = float(np.abs(lane_map.points[:, :2]).max()) + 1.0
        rng = Range(-reach, reach, -reach, reach)
    return crop_scored_lane_graph(lane_map, np.eye(4), rng, lanes.confidence)


def vertex_positions(label: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float32 (x, y) of each vertex: the mean of the points merged into it."""
    n_vertices = label.max() + 1
    size = np.bincount(label, minlength=n_vertices)
    x = np.bincount(label, points[:, 0], n_vertices) / size
    y = np.bincount(label, points[:, 1], n_vertices) / size
    return x.astype(np.float32), y.astype(np.float32)


def merge_coincident(label: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Point labels with vertices at identical stored coordinates made one, in first-appearance order.

    A graph draws lanes, so two vertices at one point are one place: lanes that overlap exactly (a
    fork whose branches leave along the same arc) share their common part instead of doubling it.
    """
    order = np.lexsort((y, x))
    same = (x[order][1:] == x[order][:-1]) & (y[order][1:] == y[order][:-1])
    if not same.any():
        return label
    group = np.concatenate([[0], np.cumsum(~same)])
    first = np.minimum.reduceat(order, np.flatnonzero(np.concatenate([[True], ~same])))
    representative = np.empty(len(x), np.int64)
    representative[order] = first[group]
    return np.unique(representative, return_inverse=True)[1][label]
