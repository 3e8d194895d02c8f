"""The openlanev2 metric's lane path (benchmark/metric/openlanev2.py: OpenLane-V2's annotated lanes against a
submission's lanes, or a graph's through annotated_of_graph) on hand-computed cases, and against a plain,
slow reading of OpenLane-V2's evaluation code written here.

The slow reading follows OpenDriveLab/OpenLane-V2 v2.1.0 step by step in pure Python: preprocess.py's
collection of the val split (every 20th GT point, as float32), evaluate.py's pairwise distances (the
Chamfer mask, the 1024 fill, the 3D discrete Fréchet distance, the relaxation by the 3D distance to the
ego), the matching by confidence, the 11-point AP in float32 with the recall steps compared in float32 (its
numpy 1.23), and TOP_ll's carried adjacency with each lane's AP from float32 precisions. Ties are taken in
lane order (Python's sort is stable), as `ties: "order"` does.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmark.metric.frame import Frame
from benchmark.metric.openlanev2 import (
    FROM_GRAPH,
    NOT_COMPUTED,
    REFERENCE,
    annotated_of_graph,
    openlanev2_frame,
    openlanev2_lanes_frame,
    openlanev2_result,
)
from benchmark.metric.openlanev2_entry import frame_of
from benchmark.metric.params import MetricParams, OpenLaneV2Params
from pipeline.lane_graph import LaneGraph
from pipeline.records import AnnotatedLanes

F32 = np.float32
EPS32 = float(np.finfo(np.float32).eps)
STEPS = np.arange(0, 1 + 1e-3, 0.1).tolist()

# ---------------------------------------------------------------------------------------------------
# The slow reading


def slow_gt(points) -> list[list[tuple[float, ...]]]:
    """collect(point_interval=20): every 20th point, the first kept, as float32."""
    return [[tuple(float(F32(c)) for c in q) for q in np.asarray(p).tolist()[::20]] for p in points]


def slow_distance(a, b) -> float:
    return math.sqrt(sum((x - y) * (x - y) for x, y in zip(a, b)))


def slow_frechet(pred, gt) -> float:
    ca = [[0.0] * len(gt) for _ in pred]
    for i, p in enumerate(pred):
        for j, g in enumerate(gt):
            d = slow_distance(p, g)
            if i == 0 and j == 0:
                ca[i][j] = d
            elif i == 0:
                ca[i][j] = max(ca[i][j - 1], d)
            elif j == 0:
                ca[i][j] = max(ca[i - 1][j], d)
            else:
                ca[i][j] = max(min(ca[i - 1][j], ca[i][j - 1], ca[i - 1][j - 1]), d)
    return ca[-1][-1]


def slow_chamfer(gt, pred) -> float:
    if gt[0] == gt[-1] and len(gt) > 1:
        gt = gt[:-1]
    to_gt = [min(slow_distance(p, g) for g in gt) for p in pred]
    to_pred = [min(slow_distance(p, g) for p in pred) for g in gt]
    return (sum(to_gt) / len(to_gt) + sum(to_pred) / len(to_pred)) / 2


def slow_distances(gt, pred) -> list[list[float]]:
    """pairwise(gt, pred, frechet_distance, mask=chamfer < 3, relax=True): [g][p]."""
    out = []
    for g in gt:
        ego = min(float(F32(math.sqrt(sum(c * c for c in q)))) for q in g)
        factor = max(0.5, 1 - 5e-3 * ego)
        row = []
        for p in pred:
            masked = slow_chamfer(g, p) * factor >= 3.0
            row.append(1024.0 if masked else slow_frechet(p, g) * factor)
        out.append(row)
    return out


def slow_ap32(confidence, tp, n_gt) -> np.float32:
    if not tp and n_gt == 0:
        return F32(1)
    order = sorted(range(len(tp)), key=lambda i: -confidence[i])
    hits, recalls, precisions = 0, [], []
    for k, i in enumerate(order):
        hits += tp[i]
        recalls.append(F32(hits) / F32(max(n_gt, EPS32)))
        precisions.append(F32(hits) / F32(k + 1))
    total = F32(0)
    for step in STEPS:
        reached = [p for r, p in zip(recalls, precisions) if r >= F32(step)]
        if reached:
            total = F32(total + max(reached))
    return F32(total / F32(11))


def slow_vertex_ap(truth: set, picked: list[tuple[int, float]]) -> tuple[float, bool]:
    """(AP, whether it was ranked rather than a plain 0 or 1)."""
    if not truth and not picked:
        return 1.0, False
    if not truth or not picked:
        return 0.0, False
    hits, total = 0, 0.0
    for k, (j, _) in enumerate(sorted(picked, key=lambda e: -e[1])):
        if j in truth:
            hits += 1
            total += float(F32(hits) / F32(k + 1))
    return float(F32(total)) / len(truth), True


def slow_score(frames: list[tuple[AnnotatedLanes, AnnotatedLanes]]) -> tuple[float, float]:
    """(DET_l, TOP_ll) of (GT, prediction) frames."""
    per_frame = []
    for gt, pred in frames:
        g = slow_gt(gt.points)
        p = [[tuple(q) for q in np.asarray(x, np.float64).tolist()] for x in pred.points]
        conf = [1.0] * len(p) if pred.confidence is None else [float(c) for c in pred.confidence]
        per_frame.append((g, p, conf, slow_distances(g, p), gt, pred))
    aps, lane_aps = [], []
    for threshold in (1.0, 2.0, 3.0):
        confidence, tps, n_gt, matches = [], [], 0, []
        for g, p, conf, dist, _, _ in per_frame:
            tp, match, taken = [0] * len(p), [-1] * len(p), set()
            for i in sorted(range(len(p)), key=lambda i: -conf[i]):
                column = [dist[j][i] for j in range(len(g))]
                if column and min(column) < threshold:
                    nearest = column.index(min(column))
                    if nearest not in taken:
                        taken.add(nearest)
                        tp[i], match[i] = 1, nearest
            confidence += conf
            tps += tp
            n_gt += len(g)
            matches.append(match)
        aps.append(slow_ap32(confidence, tps, n_gt))
        for (g, _, _, _, gt, pred), match in zip(per_frame, matches):
            n = len(g)
            if not n:
                continue
            links = np.asarray(gt.links)
            carried = [[None] * n for _ in range(n)]
            for a, ga in enumerate(match):
                for b, gb in enumerate(match):
                    if ga >= 0 and gb >= 0:
                        carried[ga][gb] = float(np.asarray(pred.links)[a, b])
            for a in range(n):
                for b in range(n):
                    if carried[a][b] is None:
                        carried[a][b] = (1 - int(links[a, b])) * (0.5 + EPS32)
            for a in range(n):  # successors, then predecessors
                truth = {b for b in range(n) if links[a, b]}
                lane_aps.append(
                    slow_vertex_ap(truth, [(b, carried[a][b]) for b in range(n) if carried[a][b] > 0.5])
                )
            for b in range(n):
                truth = {a for a in range(n) if links[a, b]}
                lane_aps.append(
                    slow_vertex_ap(truth, [(a, carried[a][b]) for a in range(n) if carried[a][b] > 0.5])
                )
    det = float(np.asarray(aps, np.float32).mean())
    if not lane_aps:
        return det, 0.0
    values = [v for v, _ in lane_aps]
    top = (
        math.fsum(values) / len(values)
        if any(r for _, r in lane_aps)
        else float(F32(sum(values)) / F32(len(values)))
    )
    return det, top


# ---------------------------------------------------------------------------------------------------
# Helpers


def lanes(points, links=None, confidence=None) -> AnnotatedLanes:
    n = len(points)
    links = np.zeros((n, n)) if links is None else np.asarray(links, np.float64)
    conf = None if confidence is None else np.asarray(confidence, np.float64)
    return AnnotatedLanes(
        [np.asarray(p, np.float64) for p in points], links, [str(i) for i in range(n)], conf
    )


def straight(start, direction=(1.0, 0.0, 0.0), length=20.0, n=201) -> np.ndarray:
    t = np.linspace(0.0, length, n)[:, None]
    return np.asarray(start, np.float64) + t * np.asarray(direction, np.float64)


def score(frames, ties="threshold") -> dict:
    params = OpenLaneV2Params(ties=ties)
    return openlanev2_result([openlanev2_lanes_frame(pred, gt, params) for gt, pred in frames])


def random_frame(rng: np.random.Generator, n_gt: int):
    gt_points = []
    for _ in range(n_gt):
        start = rng.uniform([-40, -20, -1], [40, 20, 1])
        heading = rng.uniform(-np.pi, np.pi)
        gt_points.append(straight(start, (np.cos(heading), np.sin(heading), rng.uniform(-0.05, 0.05)),
                                  rng.uniform(5, 30), int(rng.integers(21, 202))))  # fmt: skip
    links = (rng.random((n_gt, n_gt)) < 0.2).astype(np.float64)
    preds, source = [], []
    for i, p in enumerate(gt_points):
        if rng.random() < 0.8:
            k = int(rng.integers(2, 25))
            at = np.linspace(0, len(p) - 1, k)
            lane = np.stack([np.interp(at, np.arange(len(p)), p[:, d]) for d in range(3)], axis=1)
            preds.append(lane + rng.normal(0, rng.uniform(0, 1.5), 3) + rng.normal(0, 0.3, (k, 3)))
            source.append(i)
    for _ in range(int(rng.integers(0, 3))):
        preds.append(rng.uniform([-40, -20, -1], [40, 20, 1], (int(rng.integers(2, 12)), 3)))
        source.append(-1)
    k = len(preds)
    true = np.array([[s >= 0 and t >= 0 and links[s, t] > 0 for t in source] for s in source]).reshape(k, k)
    probability = np.where(true, rng.uniform(0.3, 1.0, (k, k)), rng.uniform(0.0, 0.7, (k, k)))
    return lanes(gt_points, links), lanes(preds, probability, rng.random(k))


# ---------------------------------------------------------------------------------------------------
# Hand-computed cases


def test_a_perfect_submission_scores_one_and_names_the_reference():
    gt = lanes([straight((0, 3.0 * i, 0.5)) for i in range(3)], np.eye(3, k=1))
    pred = lanes(
        [p[::20] for p in gt.points], 0.9 * np.eye(3, k=1) + 0.1 * (1 - np.eye(3, k=1)), [0.9, 0.8, 0.7]
    )
    result = score([(gt, pred)])
    assert result["det_l"] == 1.0 and result["top_ll"] == 1.0
    assert result["follows"] == REFERENCE and "v2.1.0" in REFERENCE and result["not_computed"] == NOT_COMPUTED
    assert result["lanes"] == {"pred": 3, "gt": 3} and "note" not in result


@pytest.mark.parametrize(("height", "expected"), [(0.5, 1.0), (1.5, 2 / 3), (2.5, 1 / 3), (3.5, 0.0)])
def test_heights_decide_a_match(height, expected):
    # a GT lane through the ego (relaxation 1) and a prediction on its very points, `height` metres above:
    # the 3D Fréchet distance is the height, so the thresholds 1, 2, 3 m each match or not
    gt = lanes([straight((0, 0, 0))])
    pred = lanes([gt.points[0][::20] + [0, 0, height]], confidence=[0.5])
    assert score([(gt, pred)])["det_l"] == pytest.approx(expected, abs=1e-7)


def test_the_relaxation_counts_the_height_of_the_gt_lane():
    # nearest GT point (40, 0, 30): 50 m from the ego in 3D (factor 0.75), 40 m on the ground (0.8); the
    # prediction 1.3 m aside is 0.975 < 1 relaxed in 3D (matched at 1 m), 1.04 on the ground (not)
    high = lanes([straight((40, 0, 30))])
    low = lanes([straight((40, 0, 0))])
    assert score([(high, lanes([high.points[0][::20] + [0, 1.3, 0]], confidence=[1.0]))])["det_l"] == 1.0
    low_score = score([(low, lanes([low.points[0][::20] + [0, 1.3, 0]], confidence=[1.0]))])["det_l"]
    assert low_score == pytest.approx(2 / 3, abs=1e-7)


def test_the_gt_is_every_20th_annotated_point_and_predictions_are_not_resampled():
    gt = lanes([straight((0, 0, 0), length=30.0)])  # 201 points 0.15 m apart: 11 points 3 m apart are kept
    on_kept = lanes([gt.points[0][::20]], confidence=[1.0])
    every = lanes([gt.points[0]], confidence=[1.0])  # its 201 points: 1.5 m from the nearest kept point
    assert score([(gt, on_kept)])["det_l"] == 1.0
    assert score([(gt, every)])["det_l"] == pytest.approx(2 / 3, abs=1e-7)
    # a GT lane of 20 points or fewer is its first point alone (the reference itself cannot score it)
    short = lanes([straight((0, 0, 0), length=2.0, n=20)])
    result = score([(short, lanes([np.zeros((1, 3))], confidence=[1.0]))])
    assert result["det_l"] == 1.0 and "1 of 1 GT lanes have 20 points or fewer" in result["note"]


def test_recall_is_compared_in_float32_as_numpy_1_23_compares_it():
    gt = lanes([straight((-20, 4.0 * i - 18, 0)) for i in range(10)])
    for found, expected in ((7, 8 / 11), (3, 4 / 11)):
        pred = lanes([gt.points[i][::20] for i in range(found)], confidence=0.9 - 0.05 * np.arange(found))
        # recall 0.7 in float32 reaches float32(0.7000000000000001): steps 0..0.7 take precision 1
        assert score([(gt, pred)])["det_l"] == pytest.approx(expected, abs=1e-7)


def test_ties_are_one_point_of_the_curve_or_taken_in_lane_order():
    gt = lanes([straight((0, 0, 0)), straight((0, 10, 0))])
    true, false = gt.points[0][::20], straight((0, -15, 0), n=11)
    assert score([(gt, lanes([true, false], confidence=[0.5, 0.5]))])["det_l"] == pytest.approx(
        3 / 11, abs=1e-7
    )
    assert score([(gt, lanes([true, false], confidence=[0.5, 0.5]))], "order")["det_l"] == pytest.approx(
        6 / 11, abs=1e-7
    )
    assert score([(gt, lanes([false, true], confidence=[0.5, 0.5]))], "order")["det_l"] == pytest.approx(
        3 / 11, abs=1e-7
    )


def test_empty_frames():
    nothing = lanes([], confidence=[])
    some = lanes([straight((0, 0, 0))], confidence=[0.5])
    both_empty = score([(lanes([]), nothing)])
    assert (
        both_empty["det_l"] == 1.0 and both_empty["top_ll"] == 0.0 and both_empty["frames_with_gt_lanes"] == 0
    )
    assert score([(lanes([]), some)])["det_l"] == 0.0
    no_prediction = score([(lanes([straight((0, 0, 0))], [[1.0]]), nothing)])
    assert no_prediction["det_l"] == 0.0 and no_prediction["top_ll"] == 0.0


def test_top_ll_takes_link_probabilities_above_one_half_and_drops_unmatched_lanes_links():
    # GT: a fork A -> B, A -> C. Predicted A -> B 0.8 (a link), A -> C exactly 0.5 (not one), B -> C 0.6
    # (a false link), others 0.1; a fourth, unmatched prediction D, linked 0.95 to and from A, plays no part.
    a, b, c = straight((0, 0, 0)), straight((20, 0, 0), (1, 0.3, 0)), straight((20, 0, 0), (1, -0.3, 0))
    gt = lanes([a, b, c], [[0, 1, 1], [0, 0, 0], [0, 0, 0]])
    probability = np.full((4, 4), 0.1)
    probability[0, 1], probability[0, 2], probability[1, 2] = 0.8, 0.5, 0.6
    probability[0, 3] = probability[3, 0] = 0.95
    d = straight((0, -20, 0), n=11)
    pred = lanes([a[::20], b[::20], c[::20], d], probability, [0.9, 0.8, 0.7, 0.6])
    # successors: A {B, C} finds B (1/2), B {} picks C (0), C {} nothing (1); predecessors: A (1), B {A} (1),
    # C {A} picks B (0): 3.5 / 6 at every threshold
    assert score([(gt, pred)])["top_ll"] == pytest.approx(7 / 12, abs=1e-12)
    probability[0, 2] = 0.5000001  # now a link: A's successors both found, C's predecessors B, A
    assert score([(gt, lanes(pred.points, probability, pred.confidence))])["top_ll"] == pytest.approx(
        (1 + 0 + 1 + 1 + 1 + 0.5) / 6, abs=1e-7
    )


def test_a_lanes_links_are_ranked_by_probability():
    # GT A -> B, A -> C, not A -> D; predicted A -> D 0.9, A -> B 0.8, A -> C 0.7: A's successors
    # (1/2 + 2/3) / 2; every other lane's row and column is exact (1), B's and C's predecessors too
    starts = [(0, 0, 0), (25, 5, 0), (25, -5, 0), (25, 15, 0)]
    gt = lanes([straight(s) for s in starts], [[0, 1, 1, 0], [0] * 4, [0] * 4, [0] * 4])
    probability = np.zeros((4, 4))
    probability[0, 1:] = [0.8, 0.7, 0.9]
    pred = lanes([p[::20] for p in gt.points], probability, [0.9, 0.8, 0.7, 0.6])
    # columns: B {A} picks A (1), C {A} picks A (1), D {} picks A (0); rows B, C, D (1); column A (1)
    expected = ((0.5 + 2 / 3) / 2 + 1 + 1 + 1 + 1 + 1 + 1 + 0) / 8
    assert score([(gt, pred)])["top_ll"] == pytest.approx(expected, abs=1e-7)


def test_lanes_frames_and_graph_frames_are_not_mixed():
    gt = lanes([straight((0, 0, 0))])
    lane_frame = openlanev2_lanes_frame(lanes([gt.points[0][::20]], confidence=[1.0]), gt)
    g = LaneGraph(
        np.array([0.0, 0.0], np.float32), np.array([0.0, 10.0], np.float32), np.array([0]), np.array([1])
    )
    with pytest.raises(ValueError, match="1 of 2 frames have no OpenLane-V2 annotated lanes"):
        openlanev2_result([lane_frame, openlanev2_frame(g, g)])


# ---------------------------------------------------------------------------------------------------
# annotated_of_graph and the entry's lane path


def fork_graph() -> LaneGraph:
    # BEV: (0, 0) -> (0, 10) -> (0, 20) and (0, 10) -> (5, 20): three lanes, the first a predecessor of both
    x = np.array([0, 0, 0, 5], np.float32)
    y = np.array([0, 10, 20, 20], np.float32)
    return LaneGraph(x, y, np.array([0, 1, 1], np.int32), np.array([1, 2, 3], np.int32))


def test_annotated_of_graph_heights_from_the_ground_plane_in_openlanev2_ego_frame():
    lanes_ = annotated_of_graph(fork_graph(), (1.0, 0.1, 0.2), scores=[0.2, 0.4, 0.9])
    assert len(lanes_) == 3 and lanes_.ids == ["0", "1", "2"]
    first = lanes_.points[0]  # BEV (0, t): ego (t forward, 0 left), z = 1 + 0.2 t
    np.testing.assert_allclose(
        first,
        np.stack([np.linspace(0, 10, 11), np.zeros(11), 1 + 0.2 * np.linspace(0, 10, 11)], 1),
        atol=1e-12,
    )
    fork = lanes_.points[2]  # BEV (0, 10) -> (5, 20): ego (10 -> 20 forward, 0 -> -5 left: to the right)
    np.testing.assert_allclose(fork[-1], [20.0, -5.0, 1 + 0.1 * 5 + 0.2 * 20], atol=1e-12)
    np.testing.assert_array_equal(lanes_.links, [[0, 1, 1], [0, 0, 0], [0, 0, 0]])
    np.testing.assert_allclose(lanes_.confidence, [0.2, 0.4, 0.9])
    level = annotated_of_graph(fork_graph(), None)
    assert all((p[:, 2] == 0).all() for p in level.points)
    np.testing.assert_array_equal(level.confidence, [1.0, 1.0, 1.0])


def test_the_entry_scores_a_submission_or_the_graph_against_the_annotated_lanes():
    # GT: the fork's lanes 2.5 m up (201 points each); the graph prediction is the same fork
    graph = fork_graph()
    gt = annotated_of_graph(graph, (2.5, 0.0, 0.0), points=201)
    gt.confidence = None
    params = MetricParams()
    on_plane = frame_of(Frame(pred=graph, gt=graph, gt_lanes=gt, ground=(2.5, 0.0, 0.0)), params)
    result = openlanev2_result([on_plane])
    assert result["det_l"] == 1.0 and result["top_ll"] == 1.0
    assert result["predictions"] == FROM_GRAPH and "1.0 for every lane" in result["confidences"]
    # on level ground the prediction is 2.5 m below, relaxed by at most 1 - 0.005 * 2.5: matched at 3 m only
    level = openlanev2_result([frame_of(Frame(pred=graph, gt=graph, gt_lanes=gt), params)])
    assert level["det_l"] == pytest.approx(1 / 3, abs=1e-7)
    # a submission's lanes are taken as they are, the graph unread
    submitted = annotated_of_graph(graph, (2.5, 0.0, 0.0), scores=[0.3, 0.2, 0.1])
    empty = LaneGraph.empty()
    sub = openlanev2_result(
        [frame_of(Frame(pred=empty, gt=graph, gt_lanes=gt, pred_lanes=submitted), params)]
    )
    assert sub["det_l"] == 1.0 and sub["confidences"] == "the prediction's scores"
    # without annotated lanes the graph path stays
    assert "follows" not in openlanev2_result([frame_of(Frame(pred=graph, gt=graph), params)])


# ---------------------------------------------------------------------------------------------------
# Against the slow reading


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_frames_agree_with_the_slow_reading(seed):
    rng = np.random.default_rng(seed)
    frames = [random_frame(rng, int(rng.integers(0, 8))) for _ in range(6)]
    det, top = slow_score(frames)
    result = score(frames, "order")
    assert result["det_l"] == det  # float32 arithmetic, step by step: the very same float
    assert result["top_ll"] == pytest.approx(top, abs=1e-12)
    assert 0 < det < 1 and 0 < top < 1  # the cases are not degenerate


# ---------------------------------------------------------------------------------------------------
# Through `cli score`'s reading: an OpenLane-V2 prepared dataset takes the lane path


def test_score_of_an_openlanev2_dataset_takes_the_lane_path(tmp_path):
    from test_openlanev2_prepare import segment

    from benchmark.formats.openlanev2_submission import write_submission
    from benchmark.metric.table import parse_metrics
    from benchmark.score import score as cli_score
    from pipeline.io import read_annotated_lanes, read_openlanev2_keys
    from pipeline.prepare import prepare
    from pipeline.targets import TargetOptions

    root, data = tmp_path / "olv2", tmp_path / "prepared"
    # OpenLane-V2's annotations: 201 points a lane; a fork (0 -> 1, 0 -> 2) and a lane beside
    fork = [
        straight((-20, 0, 0.1)),
        straight((0, 0, 0.1), (1, 0.1, 0.01)),
        straight((0, 0, 0.1), (1, -0.1, 0)),
    ]
    annotation = {"lanes": [p.tolist() for p in [*fork, straight((-20, 3.5, 0.1), length=40.0)]],
                  "links": [[0, 1, 1, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]]}  # fmt: skip
    segment(root, "seg-b", 2, "val", **annotation)
    segment(root, "seg-c", 2, "val", translation=(500.0, 200.0, 10.0), **annotation)
    prepare("openlanev2", root, data, TargetOptions())
    keys, annotated = read_openlanev2_keys(data), read_annotated_lanes(data)
    rng = np.random.default_rng(0)
    moved = {  # the annotated lanes 0-2 m off, distinct confidences and link probabilities
        f: lanes(
            [p + rng.uniform(0, 2, 3) for p in a.points],
            rng.uniform(0.2, 0.9, (len(a), len(a))),
            rng.random(len(a)),
        )  # fmt: skip
        for f, a in annotated.items()
    }
    submission = tmp_path / "submission.pkl"
    write_submission(submission, "mine", {keys[f]: moved[f] for f in moved})
    metric = parse_metrics("openlanev2")
    result = cli_score(submission, data, bootstrap=0, metrics=metric)["openlanev2"]
    det, top = slow_score([(annotated[f], moved[f]) for f in sorted(annotated)])
    assert result["follows"] == REFERENCE and result["lanes"]["gt"] == sum(len(a) for a in annotated.values())
    assert result["det_l"] == pytest.approx(det, abs=1e-12) and result["top_ll"] == pytest.approx(
        top, abs=1e-12
    )
    assert 0 < det < 1 and 0 < top < 1 and "note" not in result
    # the prepared graphs themselves as a graph table: the graph path's lanes with heights, on the lane path
    assert "follows" in cli_score(data, data, bootstrap=0, metrics=metric)["openlanev2"]


def test_the_chamfer_mean_sums_as_numpy_sums():
    from benchmark.metric.openlanev2 import _numpy_sum

    rng = np.random.default_rng(3)
    for n in [1, 7, 8, 9, 127, 128, 129, 136, 255, 256, 257, 1000, 5000]:
        values = rng.random(n) * 10.0 ** rng.integers(-3, 4, n)
        assert _numpy_sum(values) == np.add.reduce(values)  # the very float: pairwise, not in order
