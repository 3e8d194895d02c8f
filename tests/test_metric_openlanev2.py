"""OpenLane-V2's DET_l and TOP_ll (benchmark/metric/openlanev2.py) against a plain, slow reading of the
reference's definition written here, on hand-made graphs with values worked out by hand and on generated ones.

The slow reading follows `openlanev2/centerline/evaluation/` of OpenDriveLab/OpenLane-V2 (v1.1+) step by
step, in pure Python: the full distance matrix with its Chamfer mask and 1024 fill, the recursive discrete
Fréchet distance, the matching by confidence, the 11-point AP in float32 with the recall steps compared in
float32 (the reference's pinned numpy 1.23), and TOP_ll's carried adjacency with each lane's AP from float32
precisions. Ties are taken as the module's `ties` parameter says (Python's sort is stable).
"""

from __future__ import annotations

import functools
import itertools
import json
import math
import pickle

import numpy as np
import pytest

from benchmark.graph_table import graphs_from_table, read_graph_table
from benchmark.metric.openlanev2 import NO_SCORE, SCORED, lanes_of, openlanev2_frame, openlanev2_result
from benchmark.metric.params import OPENLANEV2_VERSION, OpenLaneV2Params
from pipeline.io import read_table
from pipeline.lane_graph import LaneGraph

F32 = np.float32
EPS32 = float(np.finfo(np.float32).eps)
STEPS = np.arange(0, 1 + 1e-3, 0.1).tolist()  # the reference's recall steps, its very floats

# ---------------------------------------------------------------------------------------------------
# The slow reading


def slow_lanes(graph: LaneGraph, points: int, scores=None):
    """(lanes as lists of (x, y), links as a set of (i, j), confidences): Graph2Piece's chains, plainly."""
    place, vertex = {}, []
    for x, y in zip(np.asarray(graph.x, np.float64).tolist(), np.asarray(graph.y, np.float64).tolist()):
        vertex.append(place.setdefault((x, y), len(place)))
    xy = list(place)
    edge_score = {}
    for k, (s, d) in enumerate(zip(graph.src.tolist(), graph.dst.tolist())):
        e = (vertex[s], vertex[d])
        if e[0] != e[1]:
            score = 1.0 if scores is None else float(scores[k])
            edge_score[e] = max(edge_score.get(e, -math.inf), score)
    edges = sorted(edge_score)
    out = {v: [] for v in range(len(xy))}
    indeg = {v: 0 for v in range(len(xy))}
    for s, d in edges:
        out[s].append(d)
        indeg[d] += 1
    junction = {v: indeg[v] != 1 or len(out[v]) != 1 for v in out}
    chains, visited = [], {v for v in out if junction[v]}
    for s, d in edges:
        if junction[s]:
            chain = [s, d]
            while not junction[d]:
                visited.add(d)
                d = out[d][0]
                chain.append(d)
            chains.append(chain)
    for v in sorted(out):  # the cycles without a junction, from their smallest vertex
        if v in visited:
            continue
        chain = [v]
        while True:
            visited.add(chain[-1])
            chain.append(out[chain[-1]][0])
            if chain[-1] == v:
                break
        chains.append(chain)
    lanes = [slow_resample([xy[v] for v in chain], points) for chain in chains]
    links = {(i, j) for i, a in enumerate(chains) for j, b in enumerate(chains) if a[-1] == b[0]}
    confidence = [sum(edge_score[e] for e in zip(c, c[1:])) / (len(c) - 1) for c in chains]
    return lanes, links, confidence


def slow_resample(line, n):
    """n points evenly by arc length, the first and last the line's own."""
    cum = [0.0]
    for a, b in zip(line, line[1:]):
        cum.append(cum[-1] + math.hypot(b[0] - a[0], b[1] - a[1]))
    out = []
    for k in range(n):
        s = cum[-1] * k / (n - 1)
        i = 0
        while i < len(line) - 2 and cum[i + 1] < s:
            i += 1
        span = cum[i + 1] - cum[i]
        t = min(max((s - cum[i]) / span, 0.0), 1.0) if span > 0 else 0.0
        a, b = line[i], line[i + 1]
        out.append((a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])))
    out[-1] = line[-1]
    return out


def slow_frechet(a, b) -> float:
    """The discrete Fréchet distance, recursively (Eiter and Mannila)."""

    @functools.cache
    def c(i, j):
        d = math.dist(a[i], b[j])
        if i == 0 and j == 0:
            return d
        if i == 0:
            return max(c(0, j - 1), d)
        if j == 0:
            return max(c(i - 1, 0), d)
        return max(min(c(i - 1, j), c(i, j - 1), c(i - 1, j - 1)), d)

    return c(len(a) - 1, len(b) - 1)


def slow_chamfer(gt, pred) -> float:
    if gt[0] == gt[-1]:
        gt = gt[:-1]
    to_gt = [min(math.dist(p, g) for g in gt) for p in pred]
    to_pred = [min(math.dist(p, g) for p in pred) for g in gt]
    return (sum(to_gt) / len(to_gt) + sum(to_pred) / len(to_pred)) / 2


def slow_lane_ap(truth: set, picked: list, grouped: bool) -> tuple[float, bool]:
    """(AP of one lane's links, whether it was ranked rather than a plain 0 or 1): picked is [(column,
    confidence)] in column order; each precision a float32 quotient, their sum rounded to float32."""
    if not truth and not picked:
        return 1.0, False
    if not truth or not picked:
        return 0.0, False
    ranked = sorted(picked, key=lambda p: -p[1])
    hits, count, total = 0, 0, 0.0
    if grouped:
        for _, group in itertools.groupby(ranked, key=lambda p: p[1]):
            group = list(group)
            new = sum(1 for column, _ in group if column in truth)
            hits, count = hits + new, count + len(group)
            total += new * float(F32(hits) / F32(count))
    else:
        for count, (column, _) in enumerate(ranked, 1):
            if column in truth:
                hits += 1
                total += float(F32(hits) / F32(count))
    return float(F32(total)) / len(truth), True


def slow_carried(a: int, b: int, match: dict, p_links: set, g_links: set) -> float:
    """The predicted link a -> b between GT lanes: that of their matched predictions where both have one,
    else 0 where the ground truth has the link and a false link at 0.5 + float32 eps where it has none."""
    if a in match and b in match:
        return 1.0 if (match[a], match[b]) in p_links else 0.0
    return (0.0 if (a, b) in g_links else 1.0) * (0.5 + EPS32)


def slow_frame(pred: LaneGraph, gt: LaneGraph, params: OpenLaneV2Params, scores=None) -> dict:
    p_lanes, p_links, p_conf = slow_lanes(pred, params.points, scores)
    g_lanes, g_links, _ = slow_lanes(gt, params.points)
    bound = params.thresholds[-1]
    dist = [[1024.0] * len(p_lanes) for _ in g_lanes]
    for g, gl in enumerate(g_lanes):
        ego = min(math.hypot(x, y) for x, y in gl)
        factor = max(params.relax_floor, 1 - params.relax_rate * ego)
        for p, pl in enumerate(p_lanes):
            if slow_chamfer(gl, pl) * factor < bound:  # the reference's mask
                dist[g][p] = slow_frechet(pl, gl) * factor
    order = sorted(range(len(p_lanes)), key=lambda i: -p_conf[i])
    grouped = params.ties == "threshold"
    tps, lane_aps = [], []
    for threshold in params.thresholds:
        tp, match, taken = [False] * len(p_lanes), {}, set()
        for i in order:
            column = [dist[g][i] for g in range(len(g_lanes))]
            if column and min(column) < threshold and column.index(min(column)) not in taken:
                taken.add(column.index(min(column)))
                tp[i], match[column.index(min(column))] = True, i
        tps.append(tp)
        n = len(g_lanes)
        if not n:
            continue
        carried = [[slow_carried(a, b, match, p_links, g_links) for b in range(n)] for a in range(n)]
        for a in range(n):  # each lane's successors, then each lane's predecessors
            truth = {b for b in range(n) if (a, b) in g_links}
            lane_aps.append(slow_lane_ap(truth, [(b, carried[a][b]) for b in range(n) if carried[a][b] > 0.5],
                                         grouped))  # fmt: skip
        for b in range(n):
            truth = {a for a in range(n) if (a, b) in g_links}
            lane_aps.append(slow_lane_ap(truth, [(a, carried[a][b]) for a in range(n) if carried[a][b] > 0.5],
                                         grouped))  # fmt: skip
    return {"conf": p_conf, "tp": tps, "n_gt": len(g_lanes), "lane_aps": [a for a, _ in lane_aps],
            "ranked": any(r for _, r in lane_aps)}  # fmt: skip


def slow_ap(conf, tp, n_gt, grouped) -> np.float32:
    """The 11-point AP in float32, the recall steps compared in float32 (numpy 1.23 casts the float64 step to
    the float32 recall's dtype)."""
    if not tp and n_gt == 0:
        return F32(1)
    ranked = sorted(zip(conf, tp), key=lambda c: -c[0])
    curve, hits = [], 0
    for k, (c, hit) in enumerate(ranked, 1):
        hits += hit
        if not grouped or k == len(ranked) or ranked[k][0] != c:
            curve.append((F32(hits) / F32(max(n_gt, EPS32)), F32(hits) / F32(k)))
    total = F32(0)
    for step in STEPS:
        reached = [p for r, p in curve if r >= F32(step)]
        if reached:
            total = F32(total + max(reached))
    return F32(total / F32(11))


def slow_scores(frames: list[dict], params: OpenLaneV2Params) -> dict:
    grouped = params.ties == "threshold"
    conf = [c for f in frames for c in f["conf"]]
    n_gt = sum(f["n_gt"] for f in frames)
    by = [slow_ap(conf, [t for f in frames for t in f["tp"][k]], n_gt, grouped) for k in range(3)]
    aps = [a for f in frames for a in f["lane_aps"]]
    if not aps:
        top = 0.0
    elif any(f["ranked"] for f in frames):  # the reference's mean: float64 with a ranked AP, else float32
        top = math.fsum(aps) / len(aps)
    else:
        top = float(F32(sum(aps)) / F32(len(aps)))
    return {"det_l": float(np.asarray(by, np.float32).mean()), "det_l_by_threshold": [float(b) for b in by],
            "top_ll": top}  # fmt: skip


# ---------------------------------------------------------------------------------------------------
# Helpers


def graph(*lines, links=()) -> LaneGraph:
    """A graph of polylines; points at identical coordinates are one vertex once cleaned."""
    x, y, src, dst = [], [], [], []
    for line in lines:
        start = len(x)
        x += [float(p[0]) for p in line]
        y += [float(p[1]) for p in line]
        src += list(range(start, start + len(line) - 1))
        dst += list(range(start + 1, start + len(line)))
    return LaneGraph(np.array(x), np.array(y), np.array(src, np.int32), np.array(dst, np.int32))


def score(pairs, params=None, scores=None) -> dict:
    """Our result of (pred, gt) pairs, after checking it against the slow reading's to 1e-9."""
    params = params or OpenLaneV2Params()
    scores = scores or [None] * len(pairs)
    ours = openlanev2_result([openlanev2_frame(p, g, params, s) for (p, g), s in zip(pairs, scores)])
    slow = slow_scores([slow_frame(p, g, params, s) for (p, g), s in zip(pairs, scores)], params)
    assert ours["det_l"] == pytest.approx(slow["det_l"], abs=1e-9)
    assert ours["top_ll"] == pytest.approx(slow["top_ll"], abs=1e-9)
    assert list(ours["det_l_by_threshold"].values()) == pytest.approx(slow["det_l_by_threshold"], abs=1e-9)
    return ours


FORK = graph([(0, 0), (0, 10)], [(0, 10), (0, 20)], [(0, 10), (5, 20)])


# ---------------------------------------------------------------------------------------------------
# The conversion


def test_lanes_are_the_pieces_with_their_successors():
    lanes = lanes_of(FORK)
    assert lanes.points.shape == (3, 11, 2)
    np.testing.assert_allclose(lanes.points[0], np.stack([np.zeros(11), np.arange(11.0)], 1), atol=1e-12)
    np.testing.assert_array_equal(lanes.adjacency, [[0, 1, 1], [0, 0, 0], [0, 0, 0]])
    np.testing.assert_array_equal(lanes.confidence, [1, 1, 1])
    slow, links, _ = slow_lanes(FORK, 11)
    np.testing.assert_allclose(lanes.points, np.array(slow), atol=1e-9)
    assert {tuple(e) for e in np.argwhere(lanes.adjacency)} == links


def test_a_closed_cycle_is_one_lane_its_own_successor():
    ring = [(10 * math.cos(a), 10 * math.sin(a)) for a in np.linspace(0, 2 * math.pi, 9)[:-1]]
    lanes = lanes_of(graph(ring + [ring[0]]))
    assert lanes.n == 1 and lanes.adjacency.tolist() == [[1.0]]
    np.testing.assert_array_equal(lanes.points[0, 0], lanes.points[0, -1])
    np.testing.assert_allclose(
        lanes.points[0], np.array(slow_lanes(graph(ring + [ring[0]]), 11)[0][0]), atol=1e-9
    )


def test_scores_per_edge_give_each_lane_their_mean():
    g = graph([(0, 0), (0, 5), (0, 10)], [(0, 10), (0, 20)], [(0, 10), (5, 20)])
    lanes = lanes_of(g, scores=[0.2, 0.4, 0.9, 0.5])
    np.testing.assert_allclose(lanes.confidence, [0.3, 0.9, 0.5])
    assert lanes.confidence.tolist() == pytest.approx(slow_lanes(g, 11, [0.2, 0.4, 0.9, 0.5])[2])
    with pytest.raises(ValueError, match="one per edge"):
        lanes_of(g, scores=[1.0])


def test_self_loops_repeats_and_isolated_vertices_make_no_lane():
    g = LaneGraph(np.array([0.0, 0, 0, 7]), np.array([0.0, 10, 10, 7]), np.array([0, 0, 1, 1], np.int32),
                  np.array([1, 1, 1, 2], np.int32))  # fmt: skip
    lanes = lanes_of(g)  # vertices 1 and 2 are one point: the edge 1 -> 2 is a self-loop once merged
    assert lanes.n == 1 and lanes.adjacency.tolist() == [[0.0]]
    assert lanes_of(LaneGraph.empty()).points.shape == (0, 11, 2)


def test_lanes_are_the_prepared_pieces(synth_prepared):
    data = synth_prepared["av2"]
    graphs = graphs_from_table(read_graph_table(data), data)
    pieces = read_table(data, "pieces").to_pylist()
    links = read_table(data, "piece_links").to_pylist()
    for frame_id in sorted(graphs)[:20]:
        lanes = lanes_of(graphs[frame_id], points=20)
        mine = sorted((p for p in pieces if p["frame_id"] == frame_id), key=lambda p: p["piece_index"])
        assert lanes.n == len(mine)
        prepared = np.array([np.stack([p["rx"], p["ry"]], 1) for p in mine], np.float32).reshape(-1, 20, 2)
        np.testing.assert_array_equal(lanes.points.astype(np.float32), prepared)
        expected = {(k["src_piece"], k["dst_piece"]) for k in links if k["frame_id"] == frame_id}
        assert {tuple(e) for e in np.argwhere(lanes.adjacency).tolist()} == expected


# ---------------------------------------------------------------------------------------------------
# Hand-made frames, values worked out by hand


def test_a_perfect_prediction_scores_one_and_says_its_confidences_are_not_scores():
    result = score([(FORK, FORK)])
    assert result["det_l"] == 1.0 and result["top_ll"] == 1.0
    assert result["confidences"] == NO_SCORE and "single point" in result["note"]
    assert result["version"] == OPENLANEV2_VERSION and result["frames"] == 1
    assert result["params"] == OpenLaneV2Params().to_dict()
    assert "30x60" in result["range"] and "100 x 50" in result["range"]
    json.dumps(result)


def test_ties_are_one_threshold_or_taken_in_lane_order():
    gt = graph([(0, 0), (0, 10)])
    pred = graph([(0, 0), (0, 10)], [(0.2, 0), (0.2, 10)])  # two lanes on one: one true, one false
    # one threshold: the single point (recall 1, precision 1/2) at every recall step
    assert score([(pred, gt)])["det_l"] == pytest.approx(0.5, abs=1e-12)
    # lane order: the first is walked alone, at precision 1
    assert score([(pred, gt)], OpenLaneV2Params(ties="order"))["det_l"] == pytest.approx(1.0, abs=1e-12)


def test_empty_prediction_empty_ground_truth_and_both():
    assert score([(LaneGraph.empty(), FORK)])["det_l"] == 0.0
    assert score([(LaneGraph.empty(), FORK)])["top_ll"] == 0.0  # unmatched lanes' links: AP 0
    empty_gt = score([(FORK, LaneGraph.empty())])
    assert empty_gt["det_l"] == 0.0 and empty_gt["top_ll"] == 0.0 and empty_gt["frames_with_gt_lanes"] == 0
    both = score([(LaneGraph.empty(), LaneGraph.empty())])
    assert both["det_l"] == 1.0 and both["top_ll"] == 0.0  # the reference: AP 1 with nothing on either side


def test_a_frame_without_ground_truth_links():
    gt = graph([(0, 0), (0, 10)], [(0, 10.5), (0, 20)])  # two lanes, 0.5 m apart, not linked
    assert score([(gt, gt)])["top_ll"] == 1.0  # every lane: no link on either side
    # a fork where the first ends: the second (Fréchet 0.5 m) and a false lane that matches nothing
    forked = graph([(0, 0), (0, 10)], [(0, 10), (0, 20)], [(0, 10), (5, 20)])
    result = score([(forked, gt)])
    assert result["det_l"] == pytest.approx(2 / 3, abs=1e-6)  # one point: recall 1, precision 2/3 (float32)
    # the first lane's successors and the second's predecessors hold a false link: AP 0; the others 1
    assert result["top_ll"] == pytest.approx(0.5, abs=1e-12)


def test_lanes_touching_the_border_are_relaxed_by_their_distance_to_the_ego():
    gt = graph([(15, -30), (15, 30)])  # on the border of the 30x60 range, 15 m from the ego
    pred = graph([(16.05, -30), (16.05, 30)])  # 1.05 m off: relaxed 1.05 * (1 - 0.005 * 15) = 0.971 m
    assert score([(pred, gt)])["det_l"] == 1.0
    strict = score([(pred, gt)], OpenLaneV2Params(relax_rate=0.0))
    assert strict["det_l_by_threshold"] == {"1.0": 0.0, "2.0": 1.0, "3.0": 1.0}


def test_a_closed_cycle_matches_only_from_the_same_start():
    ring = [(10 * math.cos(a), 5 + 10 * math.sin(a)) for a in np.linspace(0, 2 * math.pi, 13)[:-1]]
    gt = graph(ring + [ring[0]])
    result = score([(gt, gt)])
    assert result["det_l"] == 1.0 and result["top_ll"] == 1.0  # its own successor
    turned = graph(ring[4:] + ring[:4] + [ring[4]])  # the same ring, numbered from another point
    assert score([(turned, gt)])["det_l"] == 0.0


def test_distinct_confidences_walk_the_curve():
    gt = graph([(0, 0), (0, 10)], [(10, 0), (10, 10)])
    pred = graph([(0, 0), (0, 10)], [(-10, 0), (-10, 10)], [(10, 0), (10, 10)])
    result = score([(pred, gt)], scores=[[0.9, 0.8, 0.7]])
    # true (R 1/2, P 1), false (1/2, 1/2), true (1, 2/3): steps 0..0.5 take 1, steps 0.6..1 take 2/3
    assert result["det_l"] == pytest.approx(28 / 33, abs=1e-6)  # float32, as the reference's
    assert result["confidences"] == SCORED and "note" not in result


@pytest.mark.parametrize(("found", "expected"), [(7, 8 / 11), (9, 10 / 11), (3, 4 / 11)])
def test_recall_is_compared_in_float32_as_the_reference_s_numpy_compares_it(found, expected):
    gt = graph(*[[(4 * k - 18, 0), (4 * k - 18, 10)] for k in range(10)])
    pred = graph(*[[(4 * k - 18, 0), (4 * k - 18, 10)] for k in range(found)])
    # OpenLane-V2 pins numpy < 1.24, which casts each float64 step to the float32 recall's dtype: a recall of
    # float32(0.7) = 0.69999999 reaches float32(0.7000000000000001), the same float, so steps 0..0.7 take
    # precision 1 (numpy 2, comparing in float64, gives 7 / 11, as version 1 of this path did); 0.9 likewise;
    # float32(0.3) = 0.30000001 reaches its step either way
    assert score([(pred, gt)])["det_l"] == pytest.approx(expected, abs=1e-6)


def test_top_ll_carries_the_predicted_links_onto_the_matched_lanes():
    gt = graph([(0, 0), (0, 10)], [(0, 10), (0, 20)], [(0, 10), (-6, 16)], [(0.8, 10), (8, 15)])  # A, B, C, D
    pred = graph([(0, 0), (0, 10)], [(0, 10), (0, 20)], [(0, 10), (8, 15)])  # A, B, and D' after A
    # A's successors: B (true) and D (false) tie at 1.0; C is unmatched, so every lane's link to or from C
    # where the ground truth has none is a false link at 0.5 + eps: rows A..D 1/4 (tie) or 1/2 (B first),
    # 0, 0, 0; columns 0, 1, 0, 0
    result = score([(pred, gt)])
    assert result["det_l"] == pytest.approx(8 / 11, abs=1e-6)  # recall 3/4 at precision 1
    assert result["top_ll"] == pytest.approx(1.25 / 8, abs=1e-12)
    assert score([(pred, gt)], OpenLaneV2Params(ties="order"))["top_ll"] == pytest.approx(1.5 / 8, abs=1e-12)


def test_version_2_is_recorded_and_a_version_1_result_still_reads():
    from benchmark.metric.openlanev2_entry import console_tables, report_row

    # version 2: the graph path's DET_l and TOP_ll in the reference's float32 (version 1 read the recall
    # steps as numpy 2 does); a result written by version 1 has the same form and still shows
    result = score([(FORK, FORK)])
    assert result["version"] == OPENLANEV2_VERSION == 2
    old = json.loads(json.dumps({**result, "version": 1}))
    tables, notes = console_tables(old)
    assert len(tables) == 1 and report_row(old) == report_row(result) == ["100.0", "100.0"]


def test_params_are_checked_and_recorded():
    params = OpenLaneV2Params(thresholds=(0.5, 1.5), points=7, ties="order", bev_range="50x100")
    assert OpenLaneV2Params.from_dict(json.loads(json.dumps(params.to_dict()))) == params
    for bad in ({"thresholds": ()}, {"points": 1}, {"ties": "random"}, {"bev_range": "wide"}):
        with pytest.raises(ValueError):
            OpenLaneV2Params(**bad)
    frames = [openlanev2_frame(FORK, FORK), openlanev2_frame(FORK, FORK, params)]
    with pytest.raises(ValueError, match="different"):
        openlanev2_result(frames)
    assert "50x100" in openlanev2_result(frames[1:])["range"]


# ---------------------------------------------------------------------------------------------------
# Generated frames


def perturbed(gt: LaneGraph, rng: np.random.Generator) -> tuple[LaneGraph, np.ndarray | None]:
    """A prediction from the ground truth: noise, a shift, dropped edges, sometimes a shifted copy of some
    lanes (duplicates), and no scores, distinct scores or scores on a 0.1 grid (ties between values)."""
    keep = rng.random(len(gt.src)) >= rng.choice([0.0, 0.05, 0.2])
    noise, shift = rng.choice([0.05, 0.3, 0.8]), rng.normal(0.0, rng.choice([0.0, 0.5]), 2)
    x = gt.x + rng.normal(0.0, noise, len(gt.x)) + shift[0]
    y = gt.y + rng.normal(0.0, noise, len(gt.x)) + shift[1]
    src, dst = gt.src[keep], gt.dst[keep]
    if rng.random() < 0.3:
        copy = rng.random(len(src)) < 0.3
        x, y = np.r_[x, x + 0.4], np.r_[y, y]
        src, dst = np.r_[src, src[copy] + len(gt.x)], np.r_[dst, dst[copy] + len(gt.x)]
    pred = LaneGraph(x, y, src.astype(np.int32), dst.astype(np.int32))
    kind = rng.integers(3)
    scores = None if kind == 0 else rng.random(len(src)) if kind == 1 else np.round(rng.random(len(src)), 1)
    return pred, scores


@pytest.fixture(scope="module")
def generated(synth_prepared) -> list:
    rng = np.random.default_rng(0)
    pairs = []
    for name in ("av2", "nuscenes"):
        graphs = graphs_from_table(read_graph_table(synth_prepared[name]), synth_prepared[name])
        for frame_id in rng.choice(sorted(graphs), 20, replace=False):
            pred, scores = perturbed(graphs[frame_id], rng)
            pairs.append((pred, graphs[frame_id], scores))
    pairs.append((LaneGraph.empty(), pairs[0][1], None))
    pairs.append((pairs[1][0], LaneGraph.empty(), pairs[1][2]))
    return pairs


@pytest.mark.parametrize("ties", ["threshold", "order"])
def test_generated_frames_agree_with_the_slow_reading(generated, ties):
    params = OpenLaneV2Params(ties=ties)
    ours, slow = [], []
    for pred, gt, scores in generated:
        ours.append(openlanev2_frame(pred, gt, params, scores))
        slow.append(slow_frame(pred, gt, params, scores))
        np.testing.assert_array_equal(ours[-1]["tp"], np.array(slow[-1]["tp"], bool).reshape(3, -1))
        np.testing.assert_allclose(ours[-1]["lane_aps"].ravel(), slow[-1]["lane_aps"], atol=1e-9)
    result, expected = openlanev2_result(ours), slow_scores(slow, params)
    assert result["det_l"] == pytest.approx(expected["det_l"], abs=1e-9)
    assert result["top_ll"] == pytest.approx(expected["top_ll"], abs=1e-9)
    assert list(result["det_l_by_threshold"].values()) == pytest.approx(
        expected["det_l_by_threshold"], abs=1e-9
    )
    assert 0.05 < result["det_l"] < 0.95 and 0.05 < result["top_ll"] < 0.95  # neither trivial
    assert result["confidences"].startswith(SCORED + " where given")


def test_real_av2_frames_agree_with_the_slow_reading(prepared_av2):
    rng = np.random.default_rng(1)
    graphs = graphs_from_table(read_graph_table(prepared_av2), prepared_av2)
    pairs, scores = [], []
    for frame_id in rng.choice(sorted(graphs), 8, replace=False):
        pred, s = perturbed(graphs[frame_id], rng)
        pairs.append((pred, graphs[frame_id]))
        scores.append(s)
    score(pairs, scores=scores)


def test_frame_order_and_worker_processes_play_no_part(generated):
    frames = [openlanev2_frame(pred, gt, OpenLaneV2Params(), s) for pred, gt, s in generated]
    frames = [pickle.loads(pickle.dumps(f)) for f in frames]  # as they come back from worker processes
    result = openlanev2_result(frames)
    order = np.random.default_rng(2).permutation(len(frames))
    shuffled = openlanev2_result([frames[i] for i in order])
    # TOP_ll's mean is numpy's, in frame order as the reference takes it: another order moves its last bits
    top, shuffled_top = result.pop("top_ll_by_threshold"), shuffled.pop("top_ll_by_threshold")
    assert shuffled.pop("top_ll") == pytest.approx(result.pop("top_ll"), abs=1e-15)
    assert list(shuffled_top.values()) == pytest.approx(list(top.values()), abs=1e-15)
    assert shuffled == result
    json.dumps(result)
