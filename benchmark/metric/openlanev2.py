"""The `openlanev2` metric variant: OpenLane-V2's DET_l and TOP_ll (v1.1+) of lane graphs cut into lanes at
their junctions (lanes_of), one frame's contribution (openlanev2_frame) and the scores (openlanev2_result),
under OpenLaneV2Params (params.py, with OPENLANEV2_VERSION: the table of metrics names them
without loading this module). On OpenLane-V2's own data, its lane path: the annotated lanes against a
submission's lanes or a graph's (annotated_of_graph), as OpenLane-V2's code scores them
(openlanev2_lanes_frame)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from benchmark.metric.densify import identical_points, unique_edges
from benchmark.metric.params import OPENLANEV2_VERSION, OpenLaneV2Params
from pipeline.geometry import Range, ground_height, resample_polylines
from pipeline.kernels import kernel
from pipeline.lane_graph import BEV_FROM_OPENLANEV2_EGO, LaneGraph
from pipeline.pieces import graph_to_pieces
from pipeline.records import AnnotatedLanes

# The definition, as OpenLane-V2's `openlanev2/centerline/evaluation/` computes it (docs/METRICS.md says where
# it differs from our TOPO):
#
# - Lanes. Each piece of a graph (Graph2Piece's chain between junctions; a junction-free cycle is one closed
#   piece) is a lane of `points` points, even by arc length, its own first and last points kept; lane j is a
#   successor of lane i when it starts where i ends. A predicted lane's confidence is its score where the
#   format carries one, else 1.0; a predicted link has confidence 1.0.
# - Distance. The discrete Fréchet distance of every (GT, predicted) pair, times the GT lane's relaxation
#   max(relax_floor, 1 - relax_rate * d), d its point nearest to the ego origin.
# - Matching at threshold t. Predictions in decreasing confidence: one whose nearest GT lane (the first on
#   ties) is closer than t is a true positive if that lane is not taken yet, else a false positive; a
#   prediction never falls back to its second-nearest GT lane.
# - DET_l. Over all frames, predictions in decreasing confidence: recall and precision as float32 quotients;
#   the AP is the float32 sum over the recall steps 0, 0.1, ..., 1.0 of the best precision at a recall >= the
#   step (0 where none), over 11; DET_l is the float32 mean of the AP at t = 1, 2, 3 m. No lane at all on
#   either side: AP 1.
# - TOP_ll. Per threshold and frame with GT lanes: the predicted adjacency carried over onto the GT lanes
#   through the matching; a GT entry no matched pair covers is 0 where the GT has a link and a false link
#   of confidence 0.5 + float32 eps where it has none. Each GT lane's row (successors) and column
#   (predecessors) gives an AP: the predicted entries above 0.5 ranked by confidence, the sum of the
#   float32 precision at each true one, rounded to float32, over the number of true ones (1 when both sides
#   are empty, 0 when one is). TOP_ll is the mean of all those APs over the thresholds and frames, in
#   float32 when every AP is a plain 0 or 1 (the reference's mixed scalars), else in float64.
# - Ties (equal confidences). `ties="threshold"` (the default) makes equal confidences one threshold of the
#   curve (precision and recall are read where the tie ends), so no score depends on the order of lanes or
#   frames, and with every confidence 1.0 each AP is one point of its curve. `ties="order"` walks them in
#   lane order, frame by frame: the reference's answer wherever numpy's argsort keeps ties in order (its
#   default sort does not promise to: on AVX-512 machines it reorders them). The matching always gives a
#   GT lane to the lowest-index prediction among equals.

# The recall steps of the 11-point AP, OpenLane-V2's np.arange floats. Its pinned numpy (1.23) compares the
# float32 recall with each step cast to float32, so a recall of exactly 0.7 or 0.9 reaches its step, which
# numpy 2 (comparing in float64 with 0.7000000000000001) would not: both paths read it as numpy 1.23 does.
RECALL_STEPS = np.arange(0.0, 1.0 + 1e-3, 0.1)
# A predicted link counts when its confidence is above this (THRESHOLD_RELATIONSHIP_CONFIDENCE).
RELATIONSHIP_THRESHOLD = 0.5
EPS32 = np.finfo(np.float32).eps
# A GT non-link that no matched pair of predictions covers becomes a false link of this confidence.
UNCOVERED_CONFIDENCE = 0.5 + float(EPS32)

NO_SCORE = "1.0 for every lane (the format carries no score)"
SCORED = "the prediction's scores"


@dataclass
class Lanes:
    """A graph's lanes in OpenLane-V2's form."""

    points: np.ndarray  # (L, points, 2) float64, metres in the BEV frame
    adjacency: np.ndarray  # (L, L) float64: 1.0 where lane j starts where lane i ends, else 0.0
    confidence: np.ndarray  # (L,) float64

    @property
    def n(self) -> int:
        return len(self.points)


# ---------------------------------------------------------------------------------------------------
# The conversion


def clean_graph(graph: LaneGraph) -> tuple[LaneGraph, np.ndarray]:
    """The graph with points at identical coordinates made one vertex (at the first one), self-loops and
    repeated edges dropped, edges sorted by (src, dst), as the TOPO metric reads a graph; and for each
    input edge its edge in the result (-1 for a self-loop)."""
    xy = np.stack([np.asarray(graph.x, np.float64), np.asarray(graph.y, np.float64)], axis=1)
    if len(xy):
        vertex, n = identical_points(xy)
    else:
        vertex, n = np.zeros(0, np.int64), 0
    first = np.empty(n, np.int64)
    first[vertex[::-1]] = np.arange(len(xy))[::-1]
    src, dst = vertex[np.asarray(graph.src, np.int64)], vertex[np.asarray(graph.dst, np.int64)]
    edges = unique_edges(LaneGraph(xy[first, 0], xy[first, 1], src, dst), directed=True)
    key = edges[:, 0] * max(n, 1) + edges[:, 1]
    edge_of = np.where(src != dst, np.searchsorted(key, src * max(n, 1) + dst), -1)
    return LaneGraph(xy[first, 0], xy[first, 1], edges[:, 0], edges[:, 1]), edge_of


def lanes_of(graph: LaneGraph, points: int = 11, scores=None) -> Lanes:
    """The lanes of a graph: its pieces between junctions (pipeline.pieces.graph_to_pieces, in that order),
    each resampled to `points` points evenly by arc length with its first and last points kept, lane j a
    successor of lane i when it starts at the vertex where i ends.

    `scores`, if given, has one score per edge of `graph` (its src / dst order); a lane's confidence is the
    mean of its edges' scores (a repeated edge: the higher one). Without it every confidence is 1.0.
    Points at identical coordinates are one vertex and self-loops and repeated edges are dropped first,
    as the TOPO metric reads a graph; isolated vertices are no lane.
    """
    if scores is not None:
        scores = np.asarray(scores, np.float64)
        if scores.shape != (len(graph.src),):
            raise ValueError(f"scores: one per edge ({len(graph.src)}) is needed, not shape {scores.shape}")
    clean, edge_of = clean_graph(graph)
    n = max(len(clean.x), 1)
    pieces = graph_to_pieces(clean)
    lanes = len(pieces.chains)
    adjacency = np.zeros((lanes, lanes))
    adjacency[pieces.link_src, pieces.link_dst] = 1.0
    if not lanes:
        return Lanes(np.zeros((0, points, 2)), adjacency, np.zeros(0))
    ids = np.concatenate(pieces.chains)
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in pieces.chains])])
    xy = np.stack([clean.x[ids], clean.y[ids]], axis=1)
    resampled, _ = resample_polylines(np.ascontiguousarray(xy), offsets, points)
    confidence = np.ones(lanes)
    if scores is not None:
        edge_score = np.full(len(clean.src), -np.inf)
        np.maximum.at(edge_score, edge_of[edge_of >= 0], scores[edge_of >= 0])
        # the edges of each chain: consecutive vertex pairs, found among the sorted clean edges
        inner = np.ones(len(ids), bool)
        inner[offsets[1:] - 1] = False
        key = clean.src.astype(np.int64) * n + clean.dst
        along = np.searchsorted(key, ids[:-1][inner[:-1]] * n + ids[1:][inner[:-1]])
        lane = np.repeat(np.arange(lanes), np.diff(offsets) - 1)
        confidence = np.bincount(lane, edge_score[along], lanes) / np.bincount(lane, minlength=lanes)
    return Lanes(resampled, adjacency, confidence)


def relaxation(gt: Lanes, params: OpenLaneV2Params) -> np.ndarray:
    """Each GT lane's factor on its distances: max(relax_floor, 1 - relax_rate * its distance to the ego)."""
    if not gt.n:
        return np.zeros(0)
    ego = np.sqrt(gt.points[..., 0] * gt.points[..., 0] + gt.points[..., 1] * gt.points[..., 1]).min(axis=1)
    return np.maximum(params.relax_floor, 1.0 - params.relax_rate * ego)


# ---------------------------------------------------------------------------------------------------
# The kernels


@kernel
def _point_distance(a, i, b, j):
    """The Euclidean distance of points a[i] and b[j], their squared differences summed in coordinate order
    (as scipy's cdist sums them)."""
    dx, dy = a[i, 0] - b[j, 0], a[i, 1] - b[j, 1]
    total = dx * dx + dy * dy
    for k in range(2, a.shape[1]):
        d = a[i, k] - b[j, k]
        total += d * d
    return np.sqrt(total)


@kernel
def _block_sum(values, start, n):
    """numpy's pairwise_sum of values[start:start + n] for n <= 128: a plain sum below 8, else eight running
    sums combined pairwise, then the rest one by one."""
    if n < 8:
        total = 0.0
        for i in range(start, start + n):
            total += values[i]
        return total
    r = values[start : start + 8].copy()
    i = 8
    while i < n - n % 8:
        for k in range(8):
            r[k] += values[start + i + k]
        i += 8
    total = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    while i < n:
        total += values[start + i]
        i += 1
    return total


@kernel
def _numpy_sum(values):
    """values' sum as numpy's add.reduce sums a float64 array (its pairwise summation: above 128 values, the
    two halves, cut at a multiple of 8, summed apart), so that a mean equals numpy's to the last bit. Its
    recursion is walked with a stack."""
    starts, lengths, stage = np.zeros(64, np.int64), np.zeros(64, np.int64), np.zeros(64, np.int64)
    sums = np.zeros(64)
    depth, done = 0, 0
    lengths[0] = len(values)
    while depth >= 0:
        n = lengths[depth]
        if n <= 128:
            sums[done] = _block_sum(values, starts[depth], n)
            done += 1
            depth -= 1
            continue
        half = n // 2 - (n // 2) % 8
        if stage[depth] < 2:  # the left half, then the right half
            first = stage[depth] == 0
            stage[depth] += 1
            starts[depth + 1] = starts[depth] if first else starts[depth] + half
            lengths[depth + 1] = half if first else n - half
            stage[depth + 1] = 0
            depth += 1
            continue
        done -= 1
        sums[done - 1] += sums[done]
        depth -= 1
    return sums[0]


@kernel
def _chamfer(gt, g0, g1, pred, p0, p1):
    """The reference's chamfer_distance of GT points gt[g0:g1] and predicted points pred[p0:p1]: the mean of
    (the mean over predicted points of the nearest GT point, the same over GT points); a GT lane that ends
    where it starts drops its last point (a lane of one point keeps it: there the reference fails)."""
    closed = True
    for k in range(gt.shape[1]):
        closed = closed and gt[g0, k] == gt[g1 - 1, k]
    if closed and g1 - g0 > 1:
        g1 -= 1
    to_gt = np.empty(p1 - p0)
    to_pred = np.full(g1 - g0, np.inf)
    for i in range(p0, p1):
        nearest = np.inf
        for j in range(g0, g1):
            d = _point_distance(pred, i, gt, j)
            nearest = min(nearest, d)
            to_pred[j - g0] = min(to_pred[j - g0], d)
        to_gt[i - p0] = nearest
    return (_numpy_sum(to_gt) / len(to_gt) + _numpy_sum(to_pred) / len(to_pred)) / 2


@kernel
def nearest_lanes(gt, gt_start, pred, pred_start, factor, bound, chamfer_mask):
    """For each predicted lane (pred[pred_start[p]:pred_start[p + 1]], points of any dimension), the GT lane
    (gt[gt_start[g]:gt_start[g + 1]]) at the smallest relaxed discrete Fréchet distance (the first on ties)
    and that distance; (-1, inf) when none is below `bound`. `chamfer_mask`: a pair whose relaxed Chamfer
    distance is not below `bound` is no candidate, as the reference's mask makes it (its 1024 fill).

    Pairs that cannot come below `bound` or the best so far are cut short, without changing the answer:
    the distance is at least that of the two first points and of the two last points (any coupling
    pairs them), and at least the smallest value of each row of the dynamic programme (any coupling
    crosses every row).
    """
    n_pred = len(pred_start) - 1
    nearest = np.full(n_pred, -1, np.int64)
    best = np.full(n_pred, np.inf)
    longest = 1
    for g in range(len(gt_start) - 1):
        longest = max(longest, gt_start[g + 1] - gt_start[g])
    row = np.empty(longest)
    for p in range(n_pred):
        p0, p1 = pred_start[p], pred_start[p + 1]
        for g in range(len(gt_start) - 1):
            g0, g1 = gt_start[g], gt_start[g + 1]
            m = g1 - g0
            limit = min(bound, best[p])
            ends = max(_point_distance(pred, p0, gt, g0), _point_distance(pred, p1 - 1, gt, g1 - 1))
            if ends * factor[g] >= limit:
                continue
            # discrete Fréchet (Eiter and Mannila): row i of ca[i, j] = max(min(three before), d(i, j))
            row[0] = _point_distance(pred, p0, gt, g0)
            for j in range(1, m):
                row[j] = max(row[j - 1], _point_distance(pred, p0, gt, g0 + j))
            cut = False
            for i in range(p0 + 1, p1):
                diagonal = row[0]
                row[0] = max(row[0], _point_distance(pred, i, gt, g0))
                smallest = row[0]
                for j in range(1, m):
                    up = row[j]
                    row[j] = max(min(up, row[j - 1], diagonal), _point_distance(pred, i, gt, g0 + j))
                    diagonal = up
                    smallest = min(smallest, row[j])
                if smallest * factor[g] >= limit:
                    cut = True
                    break
            if cut:
                continue
            distance = row[m - 1] * factor[g]
            if distance < best[p]:
                if (
                    chamfer_mask
                    and distance < bound
                    and _chamfer(gt, g0, g1, pred, p0, p1) * factor[g] >= bound
                ):
                    continue
                best[p], nearest[p] = distance, g
    return nearest, best


@kernel
def greedy_match(order, nearest, best, threshold, n_gt):
    """The predictions in `order`: each whose nearest GT lane is closer than `threshold` takes it if it
    is free (a true positive), else it is a false positive. Returns (tp, the GT lane of each tp or -1)."""
    tp = np.zeros(len(nearest), np.bool_)
    match = np.full(len(nearest), -1, np.int64)
    taken = np.zeros(n_gt, np.bool_)
    for i in order:
        if best[i] < threshold and not taken[nearest[i]]:
            taken[nearest[i]] = True
            tp[i] = True
            match[i] = nearest[i]
    return tp, match


@kernel
def lane_aps(truth, confidence, threshold, grouped):
    """Each row's AP as the reference computes it: the columns with `truth` against those with `confidence`
    above `threshold`, ranked by decreasing confidence (ties in column order): the sum of the precision at
    each true one over their number; 1 when both are empty, 0 when one is. Each precision is a float32
    quotient, their sum rounded to float32 (numpy's dot of float32 vectors: a double sum, rounded), divided
    by the number in float64. `grouped`: a tie is read where it ends."""
    out = np.empty(truth.shape[0])
    for i in range(truth.shape[0]):
        n_true = 0
        for j in range(truth.shape[1]):
            n_true += truth[i, j]
        picked = np.flatnonzero(confidence[i] > threshold)
        if n_true == 0 or len(picked) == 0:
            out[i] = 1.0 if n_true == len(picked) else 0.0
            continue
        score = confidence[i][picked]
        order = np.argsort(-score, kind="mergesort")
        hits, pending, total = 0, 0, 0.0
        for k in range(len(order)):
            hit = truth[i, picked[order[k]]]
            hits += hit
            precision = np.float64(np.float32(hits) / np.float32(k + 1))
            if not grouped:
                if hit:
                    total += precision
                continue
            pending += hit
            if k + 1 == len(order) or score[order[k + 1]] != score[order[k]]:
                total += pending * precision
                pending = 0
        out[i] = np.float64(np.float32(total)) / n_true
    return out


# ---------------------------------------------------------------------------------------------------
# A frame and a set of frames (both paths)


def _flat(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lanes of equal length (L, n, d) as nearest_lanes takes them: their points in one (L * n, d) array
    and where each lane starts."""
    lanes, n, dims = points.shape
    return np.ascontiguousarray(points.reshape(lanes * n, dims)), np.arange(lanes + 1, dtype=np.int64) * n


def matched_links(
    order, nearest, best, truth: np.ndarray, pred_links: np.ndarray, params: OpenLaneV2Params
) -> dict:
    """Per threshold: each prediction's true-positive flag (the matching in `order`) and the AP of each GT
    lane's successors, then predecessors (the predicted links `pred_links` carried onto the GT lanes, whose
    links are `truth`, 0 or 1), with whether the reference ranks that AP (a float64 there) rather than
    returning a plain float32 0 or 1."""
    n_gt, grouped = len(truth), params.ties == "threshold"
    tp = np.zeros((len(params.thresholds), len(order)), bool)
    aps = np.zeros((len(params.thresholds), 2 * n_gt))
    ranked = np.zeros((len(params.thresholds), 2 * n_gt), bool)
    for k, threshold in enumerate(params.thresholds):
        tp[k], match = greedy_match(order, nearest, best, threshold, n_gt)
        if not n_gt:
            continue
        # the predicted links on the GT lanes, through the matching; uncovered entries as there
        carried = (1.0 - truth) * UNCOVERED_CONFIDENCE
        matched = np.flatnonzero(match >= 0)
        carried[np.ix_(match[matched], match[matched])] = pred_links[np.ix_(matched, matched)]
        for side, (t, c) in enumerate(((truth, carried), (truth.T, carried.T))):
            t, c = np.ascontiguousarray(t), np.ascontiguousarray(c)
            aps[k, side * n_gt : (side + 1) * n_gt] = lane_aps(t, c, RELATIONSHIP_THRESHOLD, grouped)
            ranked[k, side * n_gt : (side + 1) * n_gt] = (t.sum(1) > 0) & (c > RELATIONSHIP_THRESHOLD).any(1)
    return {"tp": tp, "lane_aps": aps, "ranked": ranked}


def openlanev2_frame(
    pred: LaneGraph, gt: LaneGraph, params: OpenLaneV2Params | None = None, pred_scores=None
) -> dict:
    """What one frame contributes (picklable): per threshold, each prediction's true-positive flag with its
    confidence (DET_l) and the AP of each GT lane's successors and predecessors (TOP_ll; none when the
    frame has no GT lane). `pred_scores`: one score per edge of `pred` (lanes_of), else confidences 1.0."""
    params = params or OpenLaneV2Params()
    p, g = lanes_of(pred, params.points, pred_scores), lanes_of(gt, params.points)
    nearest, best = nearest_lanes(
        *_flat(g.points), *_flat(p.points), relaxation(g, params), max(params.thresholds), False
    )
    order = np.argsort(-p.confidence, kind="stable")
    return {
        "n_gt": g.n,
        "confidence": p.confidence,
        **matched_links(order, nearest, best, g.adjacency.astype(np.int64), p.adjacency, params),
        "scored": pred_scores is not None,
        "params": params.to_dict(),
    }


def average_precision(confidence: np.ndarray, tp: np.ndarray, n_gt: int, grouped: bool) -> np.float32:
    """The reference's _AP and _pr_curve: the 11-point AP of predictions (confidence, tp flag) against n_gt GT
    lanes, walked in decreasing confidence (ties in the given order; `grouped`: a tie is one point of the
    curve), in float32 as there, the recall steps compared in float32 as its numpy 1.23 compares them."""
    if not len(tp) and n_gt == 0:
        return np.float32(1)
    order = np.argsort(-confidence, kind="stable")
    hits = np.cumsum(tp[order]).astype(np.float32)
    count = np.arange(1, len(tp) + 1).astype(np.float32)
    if grouped and len(tp):
        ranked = confidence[order]
        ends = np.flatnonzero(np.append(ranked[1:] != ranked[:-1], True))
        hits, count = hits[ends], count[ends]
    recall = hits / np.float32(max(n_gt, EPS32))
    precision = hits / count
    total = np.float32(0)
    for step in RECALL_STEPS.astype(np.float32):
        reached = precision[recall >= step]
        if len(reached):
            total = np.float32(total + reached.max())
    return np.float32(total / np.float32(len(RECALL_STEPS)))


def mean_ap(aps: np.ndarray, ranked: np.ndarray) -> np.floating:
    """The mean of the lanes' APs as the reference takes it: numpy's mean, in float64 when any AP was ranked,
    else in float32 (every AP a plain 0 or 1); 0 with no AP."""
    if not len(aps):
        return np.float32(0)
    return aps.mean() if ranked.any() else aps.astype(np.float32).mean()


def _scores(frames: list[dict], params: OpenLaneV2Params) -> dict:
    """DET_l and TOP_ll of either path's frames, as the reference computes them, with the counts."""
    grouped = params.ties == "threshold"
    confidence = np.concatenate([f["confidence"] for f in frames] or [np.zeros(0)])
    n_gt = sum(f["n_gt"] for f in frames)
    det, top, every, every_ranked = {}, {}, [], []
    for k, threshold in enumerate(params.thresholds):
        tp = np.concatenate([f["tp"][k] for f in frames] or [np.zeros(0, bool)])
        det[str(float(threshold))] = average_precision(confidence, tp, n_gt, grouped)
        aps = np.concatenate([f["lane_aps"][k] for f in frames] or [np.zeros(0)])
        ranked = np.concatenate([f["ranked"][k] for f in frames] or [np.zeros(0, bool)])
        top[str(float(threshold))] = float(mean_ap(aps, ranked))
        every.append(aps)
        every_ranked.append(ranked)
    scored = sum(f["scored"] for f in frames)
    return {
        "det_l": float(np.asarray(list(det.values()), np.float32).mean()),
        "top_ll": float(mean_ap(np.concatenate(every), np.concatenate(every_ranked))),
        "det_l_by_threshold": {t: float(v) for t, v in det.items()},
        "top_ll_by_threshold": top,
        "frames": len(frames),
        "frames_with_gt_lanes": sum(1 for f in frames if f["n_gt"]),
        "lanes": {"pred": len(confidence), "gt": n_gt},
        "confidences": NO_SCORE if not scored else SCORED if scored == len(frames) else
        f"{SCORED} where given ({scored} of {len(frames)} frames), 1.0 for every lane elsewhere",
    }  # fmt: skip


def _range_text(bev_range: str) -> str:
    r = Range.parse(bev_range)
    return (
        f"lanes inside this project's perception range {bev_range} m (x {r.x_min:g}..{r.x_max:g} m across, "
        f"y {r.y_min:g}..{r.y_max:g} m along the driving direction); OpenLane-V2 evaluates 100 x 50 m "
        "(+-50 m along, +-25 m across)"
    )


def openlanev2_result(frames: list[dict]) -> dict:
    """DET_l and TOP_ll over the frames (openlanev2_frame's or openlanev2_lanes_frame's dicts, in frame
    order), JSON-able."""
    params = [f["params"] for f in frames]
    if any(p != params[0] for p in params):
        raise ValueError("the frames were computed with different OpenLaneV2Params")
    params = OpenLaneV2Params.from_dict(params[0]) if params else OpenLaneV2Params()
    lane_path = [bool(f.get("lane_path")) for f in frames]
    if any(lane_path):
        if not all(lane_path):
            raise ValueError(
                f"{lane_path.count(False)} of {len(frames)} frames have no OpenLane-V2 annotated lanes: "
                "OpenLane-V2's own lanes and lanes cut from graphs are not scored together"
            )
        return _lanes_result(frames, params)
    result = {
        **_scores(frames, params),
        "range": _range_text(params.bev_range),
        "params": params.to_dict(),
        "version": OPENLANEV2_VERSION,
    }
    if note := _note(frames, params):
        result["note"] = note
    return result


def _note(frames: list[dict], params: OpenLaneV2Params) -> str | None:
    """What a reader must know when the predictions carry no ranking."""
    confidence = np.concatenate([f["confidence"] for f in frames] or [np.zeros(0)])
    if not len(confidence) or not (confidence == 1.0).all():
        return None
    if params.ties == "threshold":
        return (
            "every lane's confidence is 1.0: each AP is a single point of its precision-recall curve "
            "(DET_l: the final precision at each recall step reached; TOP_ll: each lane's link precision "
            "times recall), not the area under a ranked curve"
        )
    return "every lane's confidence is 1.0: ties are walked in lane order, so DET_l depends on that order"


# ---------------------------------------------------------------------------------------------------
# The lane path: OpenLane-V2's own lanes, as its evaluation code scores them
#
# Where the lane path follows the reference rather than the graph path above:
# - GT lanes are the annotated lanes as OpenLane-V2's val and test collections hold them (preprocess.py's
#   collect with point_interval 20: every 20th point, the first kept, as float32; its 201-point lanes
#   become 11 points). Predicted lanes are taken as they are: any number of points, no resampling.
# - The distance is the discrete Fréchet distance in 3D (similaritymeasures' frechet_dist), relaxed by the
#   GT lane's 3D distance to the ego (scipy's float32 norm of its float32 points), and a pair counts only
#   if its relaxed Chamfer distance is below the largest threshold too (the reference's mask).
# DET_l and TOP_ll are then the graph path's arithmetic (average_precision, lane_aps, mean_ap: the
# reference's float32, under its numpy 1.23), shared by both paths.

REFERENCE = (
    "OpenDriveLab/OpenLane-V2 v2.1.0 (evaluation code unchanged to f085b3d): "
    "openlanev2/centerline/evaluation/evaluate.py's DET_l and TOP_ll on the GT of its preprocess.py's "
    "val/test collections, under its numpy 1.23"
)
# preprocess.py collects the val and test splits with point_interval = 20 (its train split keeps every point)
GT_POINT_INTERVAL = 20
EGO_FROM_BEV = np.linalg.inv(BEV_FROM_OPENLANEV2_EGO)
NOT_COMPUTED = "DET_t, TOP_lt and the OpenLane-V2 Score (OLS) are not computed: traffic elements are not read"
FROM_SUBMISSION = "the submission's lanes as they are (3D points, confidences, topology_lclc probabilities)"
FROM_GRAPH = "the predicted graph cut into lanes at its junctions, heights from the ground plane, links 1.0"


def annotated_of_graph(
    graph: LaneGraph, ground: tuple | None, scores=None, points: int = 11
) -> AnnotatedLanes:
    """A BEV lane graph as OpenLane-V2 lanes: its lanes as lanes_of cuts them (pieces between junctions,
    `points` points each, confidences from `scores` per edge, else 1.0), in OpenLane-V2's ego frame (x
    forward, y left, z up), heights from the ground plane `ground` (ground_z, a, b: z = ground_z + a x + b y
    in the BEV frame; None: z = 0), links 1.0 where lane j starts where lane i ends."""
    lanes = lanes_of(graph, points, scores)
    x, y = lanes.points[..., 0], lanes.points[..., 1]
    z = np.zeros_like(x) if ground is None else ground_height(x, y, ground[0], (ground[1], ground[2]))
    bev = np.stack([x, y, z], axis=-1)
    ego = bev @ EGO_FROM_BEV[:3, :3].T
    return AnnotatedLanes(
        points=[np.ascontiguousarray(lane) for lane in ego],
        links=lanes.adjacency,
        ids=[str(i) for i in range(lanes.n)],
        confidence=lanes.confidence,
    )


def evaluated_gt_points(lanes: AnnotatedLanes) -> list[np.ndarray]:
    """The GT lanes' points as the reference evaluates them: every GT_POINT_INTERVAL-th annotated point, the
    first kept, rounded to float32 (held in float64)."""
    return [np.asarray(p)[::GT_POINT_INTERVAL].astype(np.float32).astype(np.float64) for p in lanes.points]


def relaxation_3d(gt_points: list[np.ndarray], params: OpenLaneV2Params) -> np.ndarray:
    """Each GT lane's factor on its distances, as the reference's pairwise(relax=True):
    max(relax_floor, 1 - relax_rate * d), d the 3D distance of its point nearest to the ego, each point's
    norm rounded to float32 as scipy's euclidean gives it for float32 points."""
    out = np.empty(len(gt_points))
    for i, p in enumerate(gt_points):
        norm = np.sqrt(p[:, 0] * p[:, 0] + p[:, 1] * p[:, 1] + p[:, 2] * p[:, 2]).astype(np.float32)
        out[i] = max(params.relax_floor, 1.0 - params.relax_rate * float(norm.min()))
    return out


def _stacked(lanes: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Lanes of any lengths as nearest_lanes takes them: all their points and where each lane starts."""
    start = np.zeros(len(lanes) + 1, np.int64)
    start[1:] = np.cumsum([len(p) for p in lanes])
    points = np.concatenate(lanes) if lanes else np.zeros((0, 3))
    return np.ascontiguousarray(points, np.float64), start


def openlanev2_lanes_frame(
    pred: AnnotatedLanes,
    gt: AnnotatedLanes,
    params: OpenLaneV2Params | None = None,
    source: str = FROM_SUBMISSION,
    scored: bool | None = None,
) -> dict:
    """What one frame contributes on the lane path (picklable): OpenLane-V2's annotated lanes `gt` against
    the predicted lanes `pred` (a submission's, or annotated_of_graph's), per threshold each prediction's
    true-positive flag with its confidence (DET_l) and the AP of each GT lane's successors and predecessors
    (TOP_ll), as the reference computes them. `source` says where the predicted lanes come from; `scored`
    whether their confidences are scores (None: whether `pred` has confidences; without, each is 1.0)."""
    params = params or OpenLaneV2Params()
    gt_points = evaluated_gt_points(gt)
    n_gt, n_pred = len(gt_points), len(pred)
    confidence = np.ones(n_pred) if pred.confidence is None else np.asarray(pred.confidence, np.float64)
    pred_links = np.asarray(pred.links, np.float64).reshape(n_pred, n_pred)
    truth = (np.asarray(gt.links).reshape(n_gt, n_gt) != 0).astype(np.int64)
    bound = max(params.thresholds)
    nearest, best = nearest_lanes(
        *_stacked(gt_points), *_stacked([np.asarray(p, np.float64) for p in pred.points]),
        relaxation_3d(gt_points, params), bound, True,
    )  # fmt: skip
    order = np.argsort(-confidence, kind="stable")
    return {
        "lane_path": True,
        "n_gt": n_gt,
        "one_point_gt": sum(1 for q in gt_points if len(q) == 1),
        "confidence": confidence,
        **matched_links(order, nearest, best, truth, pred_links, params),
        "scored": pred.confidence is not None if scored is None else scored,
        "source": source,
        "params": params.to_dict(),
    }


def _lanes_result(frames: list[dict], params: OpenLaneV2Params) -> dict:
    """openlanev2_result of lane-path frames: the shared scores, with where the lanes come from."""
    sources = sorted({f["source"] for f in frames})
    result = {
        **_scores(frames, params),
        "range": (
            "OpenLane-V2's annotated lanes as its files hold them (its 100 x 50 m: +-50 m along, +-25 m "
            f"across), every {GT_POINT_INTERVAL}th point as its val and test collections keep them; "
            "predictions not clipped"
        ),
        "predictions": "; ".join(sources),
        "follows": REFERENCE,
        "not_computed": NOT_COMPUTED,
        "params": params.to_dict(),
        "version": OPENLANEV2_VERSION,
    }  # fmt: skip
    notes = [_note(frames, params)]
    if one_point := sum(f["one_point_gt"] for f in frames):
        notes.append(
            f"{one_point} of {result['lanes']['gt']} GT lanes have {GT_POINT_INTERVAL} points or fewer: "
            "OpenLane-V2's collection keeps only their first point (its own evaluation fails on them; its "
            "annotations have 201 points)"
        )
    if any(notes):
        result["note"] = "; ".join(n for n in notes if n)
    return result
