"""CGNet's evaluator on one frame, as a whole process: the yardstick of tools/bench_startup.py. It runs under
the Python of a CGNet environment (numpy, networkx, scipy, shapely, cv2, rtree, utm), never ours, and imports
nothing of this project.

    python tools/cgnet_one_frame.py CGNET_CHECKOUT FRAME.json topo|full

FRAME.json: {"gt"|"pred": {"pos": [[x, y], ...] in metres, "edges": [[u, v], ...]}}. `full` is
`GraphEvaluator(radius=5, interp_dist=2.5, prop_dist=80).evaluate_graph`, as CGNet's nuScenes dataset calls it
(with its Graph IoU, APLS and SDA); `topo` is only its GEO / TOPO / JTOPO (GeoTopoEvaluator.topoMetric, as
evaluate_graph calls it), what `cli score --metric cgnet` computes.
"""

import json
import sys
from pathlib import Path

checkout, frame_file, mode = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
package = checkout / "projects" / "mmdet3d_plugin" / "datasets"
sys.path[:0] = [str(package), str(package / "topo_eval")]  # topo_metrics imports geotopo as a top module

import networkx as nx  # noqa: E402
import numpy as np  # noqa: E402
from topo_eval.topo_evaluator import (  # noqa: E402
    GeoTopoEvaluator,
    GraphEvaluator,
    assign_edge_lengths,
    nx_to_geo_topo_format,
)


def graph(record: dict) -> nx.DiGraph:
    g = nx.DiGraph()
    for i, pos in enumerate(np.asarray(record["pos"], np.float32)):
        g.add_node(i, pos=pos)
    g.add_edges_from(map(tuple, record["edges"]))
    return g


frame = json.loads(Path(frame_file).read_text())
gt, pred = graph(frame["gt"]), graph(frame["pred"])
if mode == "full":
    print(GraphEvaluator(radius=5, interp_dist=2.5, prop_dist=80, gmode="direct").evaluate_graph(gt, pred))
else:
    gt, pred = (nx_to_geo_topo_format(assign_edge_lengths(g)) for g in (gt, pred))
    print(GeoTopoEvaluator(gt, pred, 2.5, 80, "direct").topoMetric(thr=5, verbose=False))
