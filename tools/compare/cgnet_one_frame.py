"""CGNet's evaluator on one frame, as a whole process: the yardstick of tools/bench_startup.py, and on many
frames the reference of tools/compare/cgnet.py. It runs under the Python of a CGNet environment (numpy,
networkx, scipy, shapely, cv2, rtree, utm), never ours, and imports nothing of this project.

    python tools/compare/cgnet_one_frame.py CGNET_CHECKOUT FRAME.json topo|full

FRAME.json: {"gt"|"pred": {"pos": [[x, y], ...] in metres, "edges": [[u, v], ...]}}, or a list of such frames.
Each graph is built as CGNet's dataset class builds its own, `nx.DiGraph(adjacency)` with float32 positions,
so that its edges run in (src, dst) order whatever order the file gives. `full` is
`GraphEvaluator(radius=5, interp_dist=2.5, prop_dist=80).evaluate_graph`, as CGNet's nuScenes dataset calls it
(with its Graph IoU, APLS and SDA); `topo` is only its GEO / TOPO / JTOPO (GeoTopoEvaluator.topoMetric, as
evaluate_graph calls it), what `cli score --metric cgnet` computes. With a list of frames, `topo` prints one
JSON line per frame: {"geo" | "topo" | "jtopo": [precision, recall, f1]}, or null where the evaluator raised
ZeroDivisionError (a frame without true nodes). topoMetric returns no JTOPO precision and recall: they are
read from its three calls of its module's f1_score, which is wrapped, not changed.
"""

import json
import sys
from pathlib import Path

checkout, frame_file, mode = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
package = checkout / "projects" / "mmdet3d_plugin" / "datasets"
sys.path[:0] = [str(package), str(package / "topo_eval")]  # topo_metrics imports geotopo as a top module

import networkx as nx  # noqa: E402
import numpy as np  # noqa: E402
from topo_eval import geotopo  # noqa: E402
from topo_eval.topo_evaluator import (  # noqa: E402
    GeoTopoEvaluator,
    GraphEvaluator,
    assign_edge_lengths,
    nx_to_geo_topo_format,
)

F1_CALLS: list = []  # (precision, recall, f1) of each f1_score call in topoMetric: GEO, TOPO, JTOPO
_f1_score = geotopo.f1_score


def observed_f1_score(precision, recall):
    F1_CALLS.append((float(precision), float(recall), float(_f1_score(precision, recall))))
    return _f1_score(precision, recall)


def graph(record: dict) -> nx.DiGraph:
    pos = np.asarray(record["pos"], np.float32).reshape(-1, 2)
    adjacency = np.zeros((len(pos), len(pos)))
    for u, v in record["edges"]:
        adjacency[u, v] = 1
    g = nx.DiGraph(adjacency)
    for i, node in enumerate(g.nodes()):
        g.nodes[node]["pos"] = pos[i]
    return g


def topo(frame: dict):
    gt, pred = (nx_to_geo_topo_format(assign_edge_lengths(graph(frame[k]))) for k in ("gt", "pred"))
    return GeoTopoEvaluator(gt, pred, 2.5, 80, "direct").topoMetric(thr=5, verbose=False)


def topo_all(frame: dict):
    """The frame's nine numbers; topoMetric's own seven are checked against the observed calls."""
    F1_CALLS.clear()
    numbers = topo(frame)
    if not F1_CALLS:  # no predicted node: topoMetric returns its zeros before any f1_score
        F1_CALLS.extend([(float(numbers[0]), float(numbers[1]), float(numbers[4]))] * 3)
    (gp, gr, gf), (tp, tr, tf), (jp, jr, jf) = F1_CALLS
    returned = (gp, gr, tp, tr, gf, tf, jf)
    same = all(a == b or a != a and b != b for a, b in zip(returned, map(float, numbers)))
    assert same, (returned, numbers)
    return {"geo": [gp, gr, gf], "topo": [tp, tr, tf], "jtopo": [jp, jr, jf]}


frames = json.loads(Path(frame_file).read_text())
if isinstance(frames, list):
    geotopo.f1_score = observed_f1_score
    for frame in frames:
        try:
            numbers = topo_all(frame)
        except ZeroDivisionError:
            numbers = None
        print(json.dumps(numbers), flush=True)
elif mode == "full":
    gt, pred = graph(frames["gt"]), graph(frames["pred"])
    print(GraphEvaluator(radius=5, interp_dist=2.5, prop_dist=80, gmode="direct").evaluate_graph(gt, pred))
else:
    print(topo(frames))
