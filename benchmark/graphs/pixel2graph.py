"""Pixel2Graph (HDMapNet-style post-processing): a lane mask and a direction map to a directed graph.

1. Thinning: the mask's skeleton (scikit-image, Zhang's method), one pixel wide.
2. Pixel graph: skeleton pixels are joined to their 4-neighbours, and to a diagonal neighbour only
   when no skeleton pixel is a 4-neighbour of both (m-adjacency), so that an L-shaped corner is a
   chain and not a triangle.
3. Nodes: pixels with other than two neighbours (ends, junctions); touching junction pixels form one
   node at their mean. A closed loop without any gets its first pixel as a node.
4. Tracing: from every node, each way out is followed through two-neighbour pixels to the next node,
   giving one polyline per skeleton branch; spurs (a branch from a junction to a dead end) shorter
   than min_spur pixels are dropped, the thinning's usual artefacts at the ends of a wide line.
5. Orientation: along each polyline, the direction bins under its pixels (bin b: travel direction
   (b - 0.5) * 360 / bins degrees, 0 = +x, counter-clockwise; 0 = no direction) are compared with the
   polyline's own direction of tracing, over a moving window of heading_pixels; the polyline is cut
   where they turn from agreeing to disagreeing (two lanes whose lines touch at their ends make one
   branch that runs two ways), and each part is reversed when they disagree on the whole of it.
6. Junctions: nodes joined by a branch shorter than heading_pixels are one junction (two lanes
   crossing at a shallow angle thin into two forks and a short piece that both share). Where a lane
   coming into a junction would turn by max_turn degrees or more onto a lane going out, and it is
   not the straightest way on for either, the junction is split: each branch ends on its own vertex
   next to it, and edges join only the turns that a lane can take, so that crossing lanes stay apart.
7. Simplification: Douglas-Peucker with a tolerance of `tolerance` metres (skimage
   approximate_polygon); the ends stay, so branches still meet at their nodes.
Pixel (r, c) has its centre at x = x_min + (c + 0.5) * res, y = y_max - (r + 0.5) * res
(docs/guide/prepare.md).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from skimage.measure import approximate_polygon
from skimage.morphology import skeletonize

from pipeline.lane_graph import LaneGraph
from pipeline.raster import Grid, direction_vectors

NEIGHBOURS = [(-1, 0), (0, -1), (0, 1), (1, 0), (-1, -1), (-1, 1), (1, -1), (1, 1)]  # 4-neighbours first


def skeleton_adjacency(skeleton: np.ndarray) -> tuple[np.ndarray, list[list[int]]]:
    """(pixels (P, 2) as (row, col), neighbours of each pixel) under m-adjacency."""
    rows, cols = skeleton.shape
    pixels = np.argwhere(skeleton)
    index = np.full((rows + 2, cols + 2), -1, np.int64)
    index[1:-1, 1:-1][skeleton] = np.arange(len(pixels))
    on = index >= 0
    r, c = pixels[:, 0] + 1, pixels[:, 1] + 1
    src, dst = [], []
    for dr, dc in NEIGHBOURS:
        other = index[r + dr, c + dc]
        ok = other >= 0
        if dr and dc:  # diagonal: only when the two pixels share no 4-neighbour on the skeleton
            ok &= ~on[r + dr, c] & ~on[r, c + dc]
        src.append(np.flatnonzero(ok))
        dst.append(other[ok])
    src, dst = np.concatenate(src), np.concatenate(dst)
    neighbours: list[list[int]] = [[] for _ in range(len(pixels))]
    for p, q in zip(src.tolist(), dst.tolist()):
        neighbours[p].append(q)
    return pixels, neighbours


def trace(neighbours: list[list[int]]) -> tuple[np.ndarray, list[list[int]]]:
    """(node of each pixel, -1 for chain pixels; branches as pixel lists from node to node)."""
    degree = np.array([len(n) for n in neighbours], np.int64)
    node = np.where(degree != 2, 0, -1)
    # touching node pixels form one node
    is_node = np.flatnonzero(node >= 0)
    pairs = [(p, q) for p in is_node.tolist() for q in neighbours[p] if degree[q] != 2]
    pairs = np.array(pairs, np.int64).reshape(-1, 2)
    n = len(neighbours)
    _, label = connected_components(
        coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    )
    node[is_node] = label[is_node]

    branches: list[list[int]] = []
    done = np.zeros(n, bool)  # chain pixels already traced

    def follow(start: int, first: int) -> list[int]:
        branch, prev, cur = [start, first], start, first
        while node[cur] < 0:
            done[cur] = True
            step = neighbours[cur][0] if neighbours[cur][0] != prev else neighbours[cur][1]
            prev, cur = cur, step
            branch.append(cur)
            if cur == start:  # a loop closed on its own start
                break
        return branch

    for p in is_node.tolist():
        for q in neighbours[p]:
            if node[q] < 0 and not done[q]:
                branches.append(follow(p, q))
    for p in range(n):  # closed loops with no node: their first pixel becomes one
        if node[p] < 0 and not done[p]:
            node[p] = label.max() + 1 + p
            done[p] = True
            branches.append(follow(p, neighbours[p][0]))
    return node, branches


def headings(line: np.ndarray, reach: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions of travel of an oriented polyline where it leaves its start and enters its end,
    each over its first / last `reach` points (the whole line when shorter)."""
    k = min(reach, len(line) - 1)
    out, into = line[k] - line[0], line[-1] - line[-1 - k]
    return out / max(np.hypot(*out), 1e-12), into / max(np.hypot(*into), 1e-12)


def turns_allowed(into: np.ndarray, out: np.ndarray, max_turn: float) -> np.ndarray:
    """(I, O) bool: which incoming branches of a node continue into which outgoing ones. A pair is kept
    when its turn is below max_turn degrees, or when it is the straightest way on for either branch,
    so that no branch is left without a way on."""
    cos = into @ out.T
    ok = cos > np.cos(np.radians(max_turn))
    if cos.size:
        ok[np.arange(len(into)), cos.argmax(1)] = True
        ok[cos.argmax(0), np.arange(out.shape[0])] = True
    return ok


def direction_runs(agree: np.ndarray, window: int) -> list[int]:
    """Indices that cut a branch into runs along which the direction map agrees with the direction
    of tracing (agree > 0) or disagrees throughout: [0, ..., len - 1]. The sign is taken over a
    moving window, and runs shorter than the window join the run before them, so that a few pixels
    where another lane's bins were drawn on top do not cut."""
    sign = uniform_filter1d(agree.astype(np.float64), window, mode="nearest") >= 0
    cuts = [0]
    for i in np.flatnonzero(sign[1:] != sign[:-1]) + 1:
        if i - cuts[-1] >= window:
            cuts.append(int(i))
    if len(cuts) > 1 and len(agree) - 1 - cuts[-1] < window:
        cuts.pop()
    cuts.append(len(agree) - 1)
    # after the joins, neighbouring runs may run the same way: they are one
    way = [np.sum(agree[u : w + 1]) >= 0 for u, w in zip(cuts[:-1], cuts[1:])]
    return [0, *(c for c, a, b in zip(cuts[1:-1], way[:-1], way[1:]) if a != b), len(agree) - 1]


def join_close_junctions(
    lines: list[tuple[int, int, np.ndarray]], node_xy: np.ndarray, degree: np.ndarray, shortest: int
) -> tuple[list[tuple[int, int, np.ndarray]], np.ndarray, np.ndarray]:
    """(lines, node_xy, degree) once the junction nodes joined by a line shorter than `shortest` points
    are one node at their mean and those lines are gone: two lanes crossing at a shallow angle thin
    into two forks joined by a short piece that both share, and their turns are decided across both."""
    short = np.array(
        [(a, z) for a, z, line in lines if len(line) < shortest and min(degree[a], degree[z]) > 2], np.int64
    ).reshape(-1, 2)
    n = len(node_xy)
    _, junction = connected_components(coo_matrix((np.ones(len(short)), tuple(short.T)), shape=(n, n)))
    kept = [
        (junction[a], junction[z], line)
        for a, z, line in lines
        if not (junction[a] == junction[z] and a != z and len(line) < shortest)
    ]
    count = np.bincount(junction)
    joined_xy = np.stack([np.bincount(junction, node_xy[:, i]) / count for i in (0, 1)], axis=1)
    return kept, joined_xy, np.bincount(junction, degree)


def oriented_branches(branches, node, xy, pixel_vector, vertex_of_node, degree, n_nodes, min_spur,
                      heading_pixels):  # fmt: skip
    """(start node, end node, pixel polyline from node pixel to node pixel) of every branch but short
    spurs off a junction, oriented by the direction map, and the nodes the cuts make (numbered from
    n_nodes). A branch is cut where the direction map turns against it: two lanes whose lines touch at
    their ends, e.g. where they fork just outside the grid, make one skeleton branch with two directions."""
    extra: list[np.ndarray] = []
    lines: list[tuple[int, int, np.ndarray]] = []
    for b in branches:
        ends = (vertex_of_node[node[b[0]]], vertex_of_node[node[b[-1]]])
        low, high = sorted(degree[list(ends)])
        if len(b) < min_spur and low == 1 and high > 2:
            continue  # a short spur off a junction
        line = xy[b]
        agree = np.sum(np.gradient(line, axis=0) * pixel_vector[b], axis=1)
        cuts = direction_runs(agree, heading_pixels)
        stops = [ends[0]] + [n_nodes + len(extra) + i for i in range(len(cuts) - 2)] + [ends[1]]
        extra += [line[c] for c in cuts[1:-1]]
        for i, (u, w) in enumerate(zip(cuts[:-1], cuts[1:])):
            part, a, z = line[u : w + 1], stops[i], stops[i + 1]
            if np.sum(agree[u : w + 1]) < 0:  # the direction map says the other way
                part, a, z = part[::-1], z, a
            lines.append((a, z, part))
    return lines, np.reshape(extra, (-1, 2))


def junction_turns(lines, n_nodes, max_turn, heading_pixels):
    """Per node the branches coming in and going out, and for the nodes to split, the allowed (in, out)
    turns. At a node, lanes that cross in a junction meet as well as lanes that fork or merge; a single
    vertex would let every lane coming in go on along every lane going out. Where some of those turns
    are too sharp to be one lane, each branch ends on its own vertex next to the node and edges join
    only the turns a lane can take."""
    leaving = [headings(line, heading_pixels) for _, _, line in lines]
    ins: list[list[int]] = [[] for _ in range(n_nodes)]
    outs: list[list[int]] = [[] for _ in range(n_nodes)]
    for k, (start, end, _) in enumerate(lines):
        outs[start].append(k)
        ins[end].append(k)
    split: dict[int, np.ndarray] = {}
    for v in range(n_nodes):
        into = np.array([leaving[k][1] for k in ins[v]]).reshape(-1, 2)
        out = np.array([leaving[k][0] for k in outs[v]]).reshape(-1, 2)
        ok = turns_allowed(into, out, max_turn)
        if not ok.all():
            split[v] = ok
    return ins, outs, split


def lane_graph(lines, node_xy, degree, ins, outs, split, tolerance) -> LaneGraph:
    """The graph: every branch simplified to within `tolerance`, from its node's vertex (its own vertex
    next to a split node) to the next; a split node's turns as edges."""
    points: list[np.ndarray] = [node_xy]
    n_vertices = len(node_xy)
    edges: list[tuple[int, int]] = []
    first_vertex, last_vertex = {}, {}
    for k, (start, end, line) in enumerate(lines):
        line = line.copy()
        line[0], line[-1] = node_xy[start], node_xy[end]
        if start in split:
            line = line[1:]
        if end in split:
            line = line[:-1]
        if len(line) < 2:
            line = np.repeat(line, 2, axis=0)
        inner = approximate_polygon(line, tolerance)[1:-1] if len(line) > 2 else line[:0]
        a = n_vertices if start in split else start
        n_vertices += start in split
        first = n_vertices
        n_vertices += len(inner)
        b = n_vertices if end in split else end
        n_vertices += end in split
        points += [line[:1]] * (start in split) + [inner] + [line[-1:]] * (end in split)
        chain = [a, *range(first, first + len(inner)), b]
        edges += zip(chain[:-1], chain[1:])
        first_vertex[k], last_vertex[k] = a, b
    for v, ok in split.items():
        for i, o in zip(*np.nonzero(ok)):
            edges.append((last_vertex[ins[v][i]], first_vertex[outs[v][o]]))

    xy_out = np.concatenate(points)
    e = np.array(edges, np.int64).reshape(-1, 2)
    e = np.unique(e[e[:, 0] != e[:, 1]], axis=0)
    used = np.zeros(len(xy_out), bool)  # a split node's own vertex is left with no edge: drop it
    used[e.ravel()] = True
    used[: len(node_xy)] |= degree == 0
    renumber = np.cumsum(used) - 1
    xy_out, e = xy_out[used], renumber[e]
    return LaneGraph(xy_out[:, 0], xy_out[:, 1], e[:, 0].astype(np.int32), e[:, 1].astype(np.int32))


def pixel2graph(
    mask: np.ndarray,
    direction: np.ndarray,
    grid: Grid,
    tolerance: float = 0.15,
    min_spur: int = 5,
    max_turn: float = 60.0,
    heading_pixels: int = 10,
) -> LaneGraph:
    skeleton = skeletonize(np.asarray(mask) > 0)
    pixels, neighbours = skeleton_adjacency(skeleton)
    if len(pixels) == 0:
        return LaneGraph.empty()
    node, branches = trace(neighbours)
    xy = grid.pixel_centres(pixels[:, 0], pixels[:, 1])
    pixel_vector = direction_vectors(grid.direction_bins)[np.asarray(direction)[pixels[:, 0], pixels[:, 1]]]

    # nodes: at the mean of their pixels
    node_ids, node_of = np.unique(node[node >= 0], return_inverse=True)
    node_xy = np.stack([np.bincount(node_of, xy[node >= 0, i]) for i in (0, 1)], axis=1)
    node_xy /= np.bincount(node_of)[:, None]
    vertex_of_node = dict(zip(node_ids.tolist(), range(len(node_ids))))
    degree = np.zeros(len(node_ids), np.int64)
    for b in branches:
        degree[vertex_of_node[node[b[0]]]] += 1
        degree[vertex_of_node[node[b[-1]]]] += 1

    lines, cut_xy = oriented_branches(branches, node, xy, pixel_vector, vertex_of_node, degree, len(node_xy),
                                      min_spur, heading_pixels)  # fmt: skip
    node_xy = np.concatenate([node_xy, cut_xy])
    degree = np.concatenate([degree, np.full(len(cut_xy), 2)])
    lines, node_xy, degree = join_close_junctions(lines, node_xy, degree, heading_pixels)
    ins, outs, split = junction_turns(lines, len(node_xy), max_turn, heading_pixels)
    return lane_graph(lines, node_xy, degree, ins, outs, split, tolerance)
