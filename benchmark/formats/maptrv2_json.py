"""MapTRv2 / LaneGAP's result JSON (`--format maptrv2`): `pts_bbox/nuscmap_results.json` (on AV2
`av2map_results.json`) of MapTRv2's `_w_centerline` configs, four classes, each centerline (type 3) a whole
lane path, start to end (its ground truth is every start-to-end path). Its graph is Path2Graph's
(benchmark/graphs/path2graph.py, the parameters our LaneGAP's post-processing uses). The schema's reading
is result_json.py's; docs/guide/score.md is the user's page.
"""

from __future__ import annotations

import numpy as np

from benchmark.formats import result_json
from benchmark.formats.base import GroundTruth, Options, PredictionFormat, Predictions, Source
from pipeline.lane_graph import LaneGraph

CLASSES = ("divider", "ped_crossing", "boundary", "centerline")  # MapTRv2's `_w_centerline` configs
# the kept score of MapTRv2's prediction drawing (tools/maptrv2/nusc_vis_pred.py and av2_vis_pred.py,
# --score-thresh)
MIN_SCORE = 0.4


def path2graph(paths: list[np.ndarray], scores: np.ndarray) -> tuple[LaneGraph, np.ndarray]:
    """(Path2Graph's graph of one frame's paths, each edge's score)."""
    from benchmark.graphs.path2graph import path2graph_scored  # loaded only where a MapTRv2 file is converted

    return path2graph_scored(paths, scores)


CODEBASE = result_json.Codebase("maptrv2", CLASSES, MIN_SCORE, path2graph)


def detect(source: Source) -> bool:
    """A result JSON holding MapTRv2's class-3 centerline or one of its other classes."""
    kinds = result_json.vector_kinds(source)
    return kinds is not None and (any(name in CLASSES[:3] for name, _ in kinds) or ("centerline", 3) in kinds)


def check(source: Source, options: Options) -> str | None:
    return result_json.check(CODEBASE, options)


def read(source: Source, options: Options, gt: GroundTruth) -> Predictions:
    return result_json.read(FORMAT, CODEBASE, source, options, gt)


FORMAT = PredictionFormat(
    name="maptrv2",
    title="MapTRv2 / LaneGAP JSON",
    modeling="path",
    external=True,
    detect=detect,
    check=check,
    read=read,
)
