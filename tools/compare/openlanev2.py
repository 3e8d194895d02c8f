"""`--metric openlanev2`'s lane path (OpenLane-V2's annotated lanes against a submission's lanes or a graph's)
against OpenLane-V2's own evaluation code, run unchanged under its own Python; prints DET_l and TOP_ll of
each case by both and their differences (a check run by hand: CI has no OpenLane-V2).

    python -m tools.compare.openlanev2 --openlanev2 CHECKOUT --openlanev2-python PYTHON [--data DIR ...]

CHECKOUT is a checkout of OpenDriveLab/OpenLane-V2 (v2.1.0 or later), PYTHON a Python with numpy 1.23, scipy,
similaritymeasures and tqdm (its evaluation's packages; cv2, ortools, iso3166 and shapely, which DET_l and
TOP_ll do not use, are stubbed). Each case is a set of frames: the reference writes them in its layout
(`val/<segment>/info/<timestamp>.json`), collects them as its preprocess.py collects the val split
(point_interval 20) and runs its `evaluate()` on that collection and the predictions (its F-score, which
needs ortools, is skipped). Ours scores the same AnnotatedLanes with benchmark.metric.openlanev2. --data adds
frames of prepared datasets: their graphs as OpenLane-V2 lanes of 201 points (annotated_of_graph), against
the graph with 0.1 m of noise and one edge in ten dropped, scored per edge; without --data the real AV2 logs
of ../shared/data are prepared in a temporary folder when they are there. The same frames are also scored on
the graph path (cases named "graph path: ..."): both graphs as lanes_of cuts them (11 points, z = 0), the
reference given those very lanes as its ground truth, uncollected, beside our openlanev2_frame.

The same file is the reference's side (`--reference-side`): that part imports nothing of this project.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import types
from pathlib import Path

import numpy as np

# ---------------------------------------------------------------------------------------------------
# The reference's side: runs under OpenLane-V2's Python


def _stub_unused_imports() -> None:
    """Modules the reference imports but DET_l and TOP_ll never call (images, the F-score's min-cost flow,
    the submission's country check, the SD map)."""
    stubs = {
        "cv2": {},
        "ortools": {},
        "ortools.graph": {},
        "ortools.graph.pywrapgraph": {},
        "iso3166": {"countries": types.SimpleNamespace(get=lambda name: name)},
        "shapely": {},
        "shapely.geometry": {"LineString": None, "box": None},
    }
    for name, attributes in stubs.items():
        module = types.ModuleType(name)
        module.__dict__.update(attributes)
        sys.modules.setdefault(name, module)


def reference_side(checkout: Path, cases_file: Path, root: Path) -> None:
    """For each case of cases_file: its frames written in OpenLane-V2's layout under root, collected and
    evaluated by the reference; prints one JSON line per case: {"name", "DET_l", "TOP_ll"}."""
    sys.path.insert(0, str(checkout))
    _stub_unused_imports()
    from openlanev2.centerline.evaluation import evaluate  # noqa: F401 (loads the module)
    from openlanev2.centerline.io import io
    from openlanev2.centerline.preprocessing import collect

    module = sys.modules["openlanev2.centerline.evaluation.evaluate"]
    module.f1 = types.SimpleNamespace(bench_one_submit=lambda gts, preds: None)  # needs ortools
    for case in json.loads(cases_file.read_text()):
        folder = root / case["name"].replace(" ", "_").replace(":", "").replace(",", "")
        segments: dict[str, list[str]] = {}
        results, uncollected = {}, {}
        for frame in case["frames"]:
            segment, timestamp = frame["segment"], frame["timestamp"]
            segments.setdefault(segment, []).append(timestamp)
            gt, pred = frame["gt"], frame["pred"]
            info = {
                "version": "v2.1.0",
                "segment_id": segment,
                "meta_data": {"source": "compare", "source_id": segment},
                "timestamp": timestamp,
                "pose": {"rotation": np.eye(3).tolist(), "translation": [0.0, 0.0, 0.0]},
                "sensor": {},
                "annotation": {
                    "lane_centerline": [{"id": i, "points": p} for i, p in enumerate(gt["points"])],
                    "traffic_element": [],
                    "topology_lclc": gt["topology"],
                    "topology_lcte": [[] for _ in gt["points"]],
                },
            }
            if case.get("uncollected"):  # the graph path: the lanes as they are, float64
                n = len(gt["points"])
                info["annotation"]["lane_centerline"] = [
                    {"id": i, "points": np.asarray(q, np.float64)} for i, q in enumerate(gt["points"])
                ]
                info["annotation"]["topology_lclc"] = np.asarray(gt["topology"], np.int8).reshape(n, n)
                info["annotation"]["topology_lcte"] = np.zeros((n, 0), np.int8)
                uncollected[("val", segment, timestamp)] = info
            else:
                path = folder / "val" / segment / "info" / f"{timestamp}.json"
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(json.dumps(info))
            k = len(pred["points"])
            results[("val", segment, timestamp)] = {
                "predictions": {
                    "lane_centerline": [
                        {"id": i, "points": np.asarray(p, np.float64), "confidence": c}
                        for i, (p, c) in enumerate(zip(pred["points"], pred["confidence"]))
                    ],
                    "traffic_element": [],
                    "topology_lclc": np.asarray(pred["topology"], np.float64).reshape(k, k),
                    "topology_lcte": np.zeros((k, 0)),
                }
            }
        if case.get("uncollected"):
            ground_truth = uncollected
        else:
            collect(str(folder), {"val": segments}, "collection", point_interval=20)
            ground_truth = io.pickle_load(str(folder / "collection.pkl"))
        submission = {
            "method": "compare",
            "authors": [],
            "e-mail": "-",
            "institution / company": "-",
            "country / region": "-",
            "results": results,
        }
        metrics = evaluate(ground_truth, submission, verbose=False)["OpenLane-V2 Score"]
        print(
            json.dumps(
                {"name": case["name"], "DET_l": float(metrics["DET_l"]), "TOP_ll": float(metrics["TOP_ll"])}
            )
        )


# ---------------------------------------------------------------------------------------------------
# Our side: the cases, our scores, the comparison


def lane_curve(rng: np.random.Generator, n: int = 201) -> np.ndarray:
    """A smooth 3D lane of n points in OpenLane-V2's ego frame: an arc of 5-40 m, sloped, anywhere in its
    100 x 50 m."""
    length = rng.uniform(5.0, 40.0)
    s = np.linspace(0.0, length, n)
    heading = rng.uniform(-np.pi, np.pi) + rng.uniform(-0.02, 0.02) * s
    step = np.diff(s, prepend=0.0)
    x = rng.uniform(-45.0, 45.0) + np.cumsum(step * np.cos(heading))
    y = rng.uniform(-22.0, 22.0) + np.cumsum(step * np.sin(heading))
    z = rng.uniform(-1.0, 1.0) + rng.uniform(-0.05, 0.05) * s + 0.2 * np.sin(s / rng.uniform(3.0, 10.0))
    return np.stack([x, y, z], axis=1)


def resampled(points: np.ndarray, k: int) -> np.ndarray:
    """k points of a polyline at even steps of its index."""
    at = np.linspace(0.0, len(points) - 1.0, k)
    return np.stack([np.interp(at, np.arange(len(points)), points[:, d]) for d in range(3)], axis=1)


def random_frame(rng: np.random.Generator, lanes: int, found: float = 0.8, false: int = 3, copies: int = 1):
    """(GT, prediction) as AnnotatedLanes: random GT lanes and links; each GT lane predicted `copies` times
    with probability `found` (2-30 points, noise and offsets across the thresholds, heights included) plus
    up to `false` false lanes, in shuffled order; distinct confidences and link probabilities."""
    from pipeline.records import AnnotatedLanes

    gt_points = [lane_curve(rng) for _ in range(lanes)]
    links = (rng.random((lanes, lanes)) < 0.15).astype(np.float64)
    source, points = [], []
    for i, p in enumerate(gt_points):
        for _ in range(copies):
            if rng.random() < found:
                offset = rng.normal(0.0, rng.uniform(0.0, 1.5), 3)
                noise = rng.normal(0.0, rng.uniform(0.0, 0.6), (1, 3))
                lane = resampled(p, int(rng.integers(2, 31)))
                points.append(lane + offset + noise * rng.standard_normal((len(lane), 1)))
                source.append(i)
    for _ in range(int(rng.integers(0, false + 1))):
        points.append(resampled(lane_curve(rng), int(rng.integers(2, 31))))
        source.append(-1)
    order = rng.permutation(len(points))
    points, source = [points[o] for o in order], np.asarray(source, np.int64)[order]
    k = len(points)
    true_link = np.zeros((k, k), bool)
    for a in range(k):
        for b in range(k):
            true_link[a, b] = source[a] >= 0 and source[b] >= 0 and links[source[a], source[b]] > 0
    probability = np.where(true_link, rng.uniform(0.3, 1.0, (k, k)), rng.uniform(0.0, 0.7, (k, k)))
    gt = AnnotatedLanes(gt_points, links, [str(i) for i in range(lanes)])
    pred = AnnotatedLanes(points, probability, [str(i) for i in range(k)], rng.random(k))
    return gt, pred


def hand_cases(rng: np.random.Generator) -> list[tuple[str, list]]:
    """The hand-built cases: (name, [(gt, pred), ...])."""
    from pipeline.records import AnnotatedLanes

    def lanes(points, links=None, confidence=None):
        n = len(points)
        links = np.zeros((n, n)) if links is None else np.asarray(links, np.float64)
        return AnnotatedLanes(
            [np.asarray(p, np.float64) for p in points],
            links,
            [str(i) for i in range(n)],
            None if confidence is None else np.asarray(confidence, np.float64),
        )

    def straight(x0, y0, z0=0.0, length=20.0, n=201, dx=1.0, dy=0.0):
        t = np.linspace(0.0, length, n)
        return np.stack([x0 + dx * t, y0 + dy * t, np.full(n, z0)], axis=1)

    empty = lanes([], confidence=[])
    cases = []
    cases.append(("empty frames", [(lanes([]), empty)] * 3))
    cases.append(("frames with no GT", [(lanes([]), random_frame(rng, 4)[1]) for _ in range(3)]))
    cases.append(("frames with no prediction", [(random_frame(rng, 6)[0], empty) for _ in range(3)]))
    cases.append(
        (
            "no GT and no prediction beside others",
            [(lanes([]), empty)] + [random_frame(rng, 5) for _ in range(3)],
        )
    )
    cases.append(
        ("three times more predictions than GT", [random_frame(rng, 6, 0.9, 2, copies=3) for _ in range(5)])
    )
    gt = [straight(5.0, 3.0 * i - 9.0) for i in range(7)]
    heights = [(gt[i][::20] + [0.0, 0.0, 0.5 * (i + 1)]) for i in range(7)]  # xy exact, z 0.5 .. 3.5 m off
    chain = np.eye(7, k=1)
    cases.append(
        (
            "heights decide the matches",
            [(lanes(gt, chain), lanes(heights, chain * 0.9, 1.0 - 0.1 * np.arange(7)))],
        )
    )
    ten = [straight(-20.0, 4.0 * i - 18.0) for i in range(10)]
    for found in (7, 3):
        preds = [ten[i][::20] for i in range(found)]
        cases.append(
            (
                f"recall of exactly 0.{found}",
                [(lanes(ten), lanes(preds, None, 0.9 - 0.05 * np.arange(found)))],
            )
        )
    angle = np.linspace(0.0, 2.0 * np.pi, 201)
    ring = np.stack([10.0 + 6.0 * np.cos(angle), 6.0 * np.sin(angle), np.zeros(201)], axis=1)
    ring[-1] = ring[0]
    cases.append(("a closed GT lane", [(lanes([ring], [[1.0]]), lanes([ring[::10] + 0.3], [[0.8]], [0.7]))]))
    full = [straight(2.0, 3.0 * i, n=201, length=30.0) for i in range(4)]
    dense = [p + [0.0, 0.4, 0.0] for p in full]  # 201 points against the 11 the reference keeps
    cases.append(
        (
            "predictions of 201 points",
            [(lanes(full, np.eye(4, k=1)), lanes(dense, np.eye(4, k=1) * 0.7, [0.9, 0.8, 0.7, 0.6]))],
        )
    )
    return cases


def graph_cases(data: list[Path], rng: np.random.Generator) -> list[tuple[str, list]]:
    """Prepared datasets' frames: GT as annotated_of_graph of the graph at 201 points, prediction
    annotated_of_graph of the noisy graph with a random score per edge; heights from each frame's ground."""
    from benchmark.graph_table import graphs_from_table, read_graph_table
    from benchmark.metric.openlanev2 import annotated_of_graph
    from pipeline import io
    from tools.bench_metrics import noisy

    cases = []
    for folder in data:
        graphs = graphs_from_table(read_graph_table(folder), folder)
        table = io.read_table(folder, "frames", columns=["frame_id", "ground_z", "ground_slope"])
        ground = {
            f: (float(z), *map(float, s))
            for f, z, s in zip(*(table.column(c).to_pylist() for c in table.column_names))
        }
        frames = []
        for frame_id in sorted(graphs):
            gt = graphs[frame_id]
            pred = noisy(gt, rng)
            gt_lanes = annotated_of_graph(gt, ground[frame_id], points=201)
            gt_lanes.confidence = None
            pred_lanes = annotated_of_graph(pred, ground[frame_id], rng.random(len(pred.src)))
            frames.append((gt_lanes, pred_lanes))
        cases.append((f"{folder.name}: graphs (links 1.0), ties in order", frames))
    return cases


GRAPH_PATH = "graph path: "  # a case name's start: frames of (prediction graph, GT graph, edge scores)


def graph_path_cases(data: list[Path], rng: np.random.Generator) -> list[tuple[str, list]]:
    """The graph path: prepared datasets' graphs against themselves with 0.1 m noise and one edge in ten
    dropped, a random score per edge; 10 straight GT lanes of which 7 or 9 are found (recall of exactly
    0.7 or 0.9), distinct scores; empty frames. Frames: (prediction graph, GT graph, scores per edge)."""
    from benchmark.graph_table import graphs_from_table, read_graph_table
    from pipeline.lane_graph import LaneGraph
    from tools.bench_metrics import noisy

    cases = []
    for folder in data:
        graphs = graphs_from_table(read_graph_table(folder), folder)
        frames = []
        for frame_id in sorted(graphs):
            pred = noisy(graphs[frame_id], rng)
            frames.append((pred, graphs[frame_id], rng.random(len(pred.src))))
        cases.append(
            (f"{GRAPH_PATH}{folder.name}, 0.1 m noise, one edge in ten dropped, a score per edge", frames)
        )

    def straight_lanes(count: int) -> LaneGraph:
        x = np.repeat(4.0 * np.arange(count) - 18.0, 2)
        y = np.tile([0.0, 10.0], count)
        return LaneGraph(
            x, y, np.arange(0, 2 * count, 2, dtype=np.int32), np.arange(1, 2 * count, 2, dtype=np.int32)
        )

    for found in (7, 9):
        scores = 0.9 - 0.05 * np.arange(found)
        cases.append(
            (
                f"{GRAPH_PATH}recall of exactly 0.{found}",
                [(straight_lanes(found), straight_lanes(10), scores)],
            )
        )
    empty, three = LaneGraph.empty(), straight_lanes(3)
    nothing = [
        (empty, empty, np.zeros(0)),
        (empty, three, np.zeros(0)),
        (three, empty, np.array([0.9, 0.8, 0.7])),
    ]
    cases.append((f"{GRAPH_PATH}an empty frame, an empty prediction, an empty GT", nothing))
    return cases


def case_record(name: str, frames: list) -> dict:
    """A case as the reference's side reads it (JSON floats: exact); a graph path case as lanes_of cuts its
    graphs, the GT given to the reference uncollected."""
    if name.startswith(GRAPH_PATH):
        return {
            **case_record(name.removeprefix(GRAPH_PATH), lanes_of_graphs(frames)),
            "name": name,
            "uncollected": True,
        }
    out = []
    for i, (gt, pred) in enumerate(frames):
        confidence = np.ones(len(pred)) if pred.confidence is None else pred.confidence
        out.append(
            {
                "segment": f"segment{i // 10:03d}",
                "timestamp": f"{315970000000000000 + i:d}",
                "gt": {
                    "points": [p.tolist() for p in gt.points],
                    "topology": np.asarray(gt.links).astype(int).tolist(),
                },
                "pred": {
                    "points": [p.tolist() for p in pred.points],
                    "confidence": [float(c) for c in confidence],
                    "topology": np.asarray(pred.links, np.float64).tolist(),
                },
            }
        )
    return {"name": name, "frames": out}


def lanes_of_graphs(frames: list) -> list:
    """Graph path frames as (GT, prediction) AnnotatedLanes: lanes_of's lanes (11 points, links 0 or 1) at
    z = 0, as the reference takes only 3D points (a zero adds nothing to any distance)."""
    from benchmark.metric.openlanev2 import lanes_of
    from pipeline.records import AnnotatedLanes

    def level(points: np.ndarray) -> list[np.ndarray]:
        return list(np.concatenate([points, np.zeros(points.shape[:-1] + (1,))], axis=-1))

    out = []
    for pred, gt, scores in frames:
        g, p = lanes_of(gt), lanes_of(pred, scores=scores)
        out.append((
            AnnotatedLanes(level(g.points), g.adjacency, [str(i) for i in range(g.n)]),
            AnnotatedLanes(level(p.points), p.adjacency, [str(i) for i in range(p.n)], p.confidence),
        ))  # fmt: skip
    return out


def ours(name: str, frames: list, ties: str) -> dict:
    from benchmark.metric.openlanev2 import openlanev2_frame, openlanev2_lanes_frame, openlanev2_result
    from benchmark.metric.params import OpenLaneV2Params

    params = OpenLaneV2Params(ties=ties)
    if name.startswith(GRAPH_PATH):
        return openlanev2_result([openlanev2_frame(pred, gt, params, scores) for pred, gt, scores in frames])
    return openlanev2_result([openlanev2_lanes_frame(pred, gt, params) for gt, pred in frames])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--openlanev2", type=Path, help="a checkout of OpenDriveLab/OpenLane-V2")
    parser.add_argument("--openlanev2-python", type=Path, help="a Python with its evaluation's packages")
    parser.add_argument(
        "--data", type=Path, nargs="*", help="prepared datasets (default: ../shared/data's AV2)"
    )
    parser.add_argument("--random-cases", type=int, default=8, help="cases of 20 random frames each")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--reference-side", nargs=3, metavar=("CHECKOUT", "CASES", "ROOT"), help=argparse.SUPPRESS
    )
    args = parser.parse_args()
    if args.reference_side:
        reference_side(*map(Path, args.reference_side))
        return
    for option, path in (("--openlanev2", args.openlanev2), ("--openlanev2-python", args.openlanev2_python)):
        if path is None or not path.exists():
            parser.error(f"{option}: {path} does not exist")
    if not (args.openlanev2 / "openlanev2" / "centerline" / "evaluation" / "evaluate.py").is_file():
        parser.error(f"--openlanev2: {args.openlanev2} has no openlanev2/centerline/evaluation/evaluate.py")
    from rich.console import Console
    from rich.table import Table

    rng = np.random.default_rng(args.seed)
    cases = [
        (
            f"random {i}: 20 frames of 0-14 lanes",
            [random_frame(rng, int(rng.integers(0, 15))) for _ in range(20)],
        )
        for i in range(args.random_cases)
    ]
    cases += hand_cases(rng)
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if data is None:
            from tools.bench_metrics import SHARED_AV2

            data = []
            if SHARED_AV2.is_dir():
                from pipeline.prepare import prepare
                from pipeline.targets import TargetOptions

                prepare("av2", SHARED_AV2, Path(tmp) / "real_av2", TargetOptions())
                data = [Path(tmp) / "real_av2"]
        cases += graph_cases(data, rng)
        cases += graph_path_cases(data, rng)
        cases_file = Path(tmp) / "cases.json"
        cases_file.write_text(json.dumps([case_record(name, frames) for name, frames in cases]))
        run = subprocess.run(
            [
                str(args.openlanev2_python),
                __file__,
                "--reference-side",
                str(args.openlanev2),
                str(cases_file),
                tmp,
            ],
            capture_output=True,
            text=True,
        )
        if run.returncode:
            sys.exit(f"the reference failed:\n{run.stderr[-3000:]}")
    theirs = {r["name"]: r for r in map(json.loads, run.stdout.splitlines())}
    table = Table(
        "case",
        "frames",
        "GT / pred lanes",
        "DET_l ours",
        "DET_l theirs",
        "|diff|",
        "TOP_ll ours",
        "TOP_ll theirs",
        "|diff|",
    )
    worst = 0.0
    for name, frames in cases:
        ties = "order" if "ties in order" in name else "threshold"
        mine, ref = ours(name, frames, ties), theirs[name]
        d_det, d_top = abs(mine["det_l"] - ref["DET_l"]), abs(mine["top_ll"] - ref["TOP_ll"])
        worst = max(worst, d_det, d_top)
        lanes = mine["lanes"]
        table.add_row(
            name,
            str(len(frames)),
            f"{lanes['gt']} / {lanes['pred']}",
            f"{mine['det_l']:.9f}",
            f"{ref['DET_l']:.9f}",
            f"{d_det:.1e}",
            f"{mine['top_ll']:.9f}",
            f"{ref['TOP_ll']:.9f}",
            f"{d_top:.1e}",
        )
    console = Console(width=200)
    console.print(table)
    console.print(f"largest difference: {worst:.1e}")


if __name__ == "__main__":
    main()
