"""Matplotlib pictures of lane graphs and training runs, shared by `cli report` and `cli viz`.

BEV panels: x right, y forward (up on the page), the perception range as the axes' limits. A graph is
drawn piece by piece (split at its junctions, pipeline/pieces.py), each piece in its own colour with an
arrow in its driving direction; the ego car is the grey outline at the origin, nose forward. Colours,
arrows and the ego car are benchmark/report/style.py's, which report.html's SVG drawings share.
Figures are plain `matplotlib.figure.Figure`s (no pyplot state) saved as PNG by `save_png`, atomically.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import matplotlib.style
import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Polygon

from benchmark.metric.candidates import candidate_pairs
from benchmark.metric.densify import densify
from benchmark.metric.matching import match
from benchmark.metric.params import MetricParams
from benchmark.report.style import STYLE
from pipeline.geometry import Range, ground_height
from pipeline.io import write_atomic
from pipeline.lane_graph import LaneGraph
from pipeline.pieces import graph_to_pieces

MATCHED, UNMATCHED = STYLE.matched, STYLE.unmatched  # vertices with / without a partner in the matching
PANEL_INCHES = 2.6  # width of one BEV panel; its height follows the range's aspect


def styled(draw):
    """Run `draw` under matplotlib's default style, whatever was set globally before (nuscenes-devkit's
    map API switches to seaborn's whitegrid on import), so that the same data gives the same picture."""

    @functools.wraps(draw)
    def wrapper(*args, **kwargs):
        with matplotlib.rc_context():
            matplotlib.style.use("default")
            return draw(*args, **kwargs)

    return wrapper


@styled
def save_png(figure: Figure, path: Path, dpi: int = 110) -> Path:
    """Write the figure to path (temp file, then rename)."""
    write_atomic(Path(path), lambda tmp: figure.savefig(tmp, format="png", dpi=dpi))
    return Path(path)


def piece_colour(index: int) -> str:
    return STYLE.piece(index)


def bev_axes(ax, crop: Range, title: str) -> None:
    ax.set_xlim(crop.x_min, crop.x_max)
    ax.set_ylim(crop.y_min, crop.y_max)
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=7)
    ax.tick_params(labelsize=5, length=2)
    ax.set_facecolor(STYLE.background)


def draw_ego(ax) -> None:
    """The ego car at the BEV origin, 1.9 m x 4.6 m, nose towards +y."""
    ax.add_patch(Polygon(STYLE.ego_outline, closed=True, facecolor=STYLE.ego_fill, edgecolor=STYLE.ego_edge,
                         lw=0.5, zorder=5))  # fmt: skip


def draw_graph(ax, graph: LaneGraph, lw: float = 1.2, alpha: float = 1.0) -> None:
    """Each piece of the graph in its own colour, an arrow halfway along it in its direction."""
    xy = np.stack([np.asarray(graph.x, np.float64), np.asarray(graph.y, np.float64)], axis=1)
    chains = graph_to_pieces(graph).chains
    for index, chain in enumerate(chains):
        points, colour = xy[chain], piece_colour(index)
        ax.plot(points[:, 0], points[:, 1], color=colour, lw=lw, alpha=alpha, solid_capstyle="round")
    for index, (tail, head) in enumerate(piece_arrows(xy, chains)):
        if tail < 0:
            continue
        middle, direction = (xy[head] + xy[tail]) / 2, xy[head] - xy[tail]
        shaft = STYLE.arrow_half_length * direction / np.linalg.norm(direction)
        ax.annotate(
            "", xy=middle + shaft, xytext=middle - shaft,
            arrowprops=dict(arrowstyle="-|>", color=piece_colour(index), lw=lw, alpha=alpha,
                            mutation_scale=STYLE.arrow_mutation_scale),
        )  # fmt: skip


def piece_arrows(xy: np.ndarray, chains) -> list[tuple[int, int]]:
    """(tail, head) vertices of the segment halfway along each piece, where its arrow goes; (-1, -1) for
    a piece of no length. The frame browser of report.html draws its arrows on the same segments."""
    arrows = []
    for chain in chains:
        chain = np.asarray(chain)
        steps = np.linalg.norm(np.diff(xy[chain], axis=0), axis=1)
        if len(steps) == 0 or steps.sum() <= 0:
            arrows.append((-1, -1))
            continue
        at = int(np.searchsorted(np.cumsum(steps), steps.sum() / 2))  # the segment halfway along
        arrows.append((int(chain[at]), int(chain[at + 1])))
    return arrows


@styled
def frame_grid(
    frames: list[tuple[str, str]], columns: list[tuple[str, dict[str, LaneGraph]]], crop: Range
) -> Figure:
    """Rows = frames (frame_id, row label), columns = (title, {frame_id: graph}): ground truth first,
    then each run's prediction. A frame missing from a column is drawn empty."""
    width = PANEL_INCHES * len(columns)
    height = PANEL_INCHES * (crop.y_max - crop.y_min) / (crop.x_max - crop.x_min) * len(frames)
    figure = Figure(figsize=(width, height + 0.3), layout="constrained")
    axes = figure.subplots(len(frames), len(columns), squeeze=False)
    for row, (frame_id, label) in enumerate(frames):
        for col, (title, graphs) in enumerate(columns):
            ax = axes[row, col]
            heading = ([title] if row == 0 else []) + ([label] if col == 0 else [])
            bev_axes(ax, crop, "\n".join(heading))
            draw_graph(ax, graphs.get(frame_id, LaneGraph.empty()))
            draw_ego(ax)
    return figure


@styled
def f1_bars(names: list[str], metrics: list[str], values: np.ndarray, floors: np.ndarray) -> Figure:
    """Grouped bars: one group per metric, one bar per run (values[run, metric], in %); each run's
    sensor-blind floor as a black tick across its bar (NaN: none recorded)."""
    figure = Figure(figsize=(1.6 + 1.4 * len(metrics), 3.2), layout="constrained")
    ax = figure.subplots()
    width = 0.8 / max(len(names), 1)
    for r, name in enumerate(names):
        x = np.arange(len(metrics)) + (r - (len(names) - 1) / 2) * width
        ax.bar(x, values[r], width, label=name, color=piece_colour(r))
        has = ~np.isnan(floors[r])
        ax.hlines(floors[r][has], x[has] - width / 2, x[has] + width / 2, colors="black", lw=1.5)
    if np.any(~np.isnan(floors)):
        ax.plot([], [], color="black", lw=1.5, label="sensor-blind floor")
    ax.set_xticks(np.arange(len(metrics)), metrics, fontsize=7)
    ax.set_ylabel("F1 (%)")
    ax.set_ylim(0, max(1.0, float(np.nanmax(np.concatenate([values.ravel(), floors.ravel(), [0]])))) * 1.15)
    ax.legend(fontsize=6)
    return figure


@styled
def loss_curves(curves: dict[str, tuple[np.ndarray, np.ndarray]]) -> Figure:
    """Training loss against step, one line per run (log scale when every loss is positive)."""
    figure = Figure(figsize=(5.5, 3.2), layout="constrained")
    ax = figure.subplots()
    for index, (name, (steps, losses)) in enumerate(curves.items()):
        ax.plot(steps, losses, marker="." if len(steps) < 20 else None, label=name, color=piece_colour(index))
    if all(np.all(losses > 0) for _, losses in curves.values()):
        ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("training loss")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6)
    return figure


@dataclass
class ValidationCurve:
    """One run's validation during training, in %, as `validation_curves` draws it."""

    name: str
    points: dict[str, tuple[np.ndarray, np.ndarray]]  # panel key -> (steps, values)
    constants: dict[str, float]  # panel key -> the run's best constant in hindsight, where known
    best: tuple[str, int, float] | None = None  # (panel key, step, value) of the checkpoint kept as best


@styled
def validation_curves(panels: list[tuple[str, str]], curves: list[ValidationCurve]) -> Figure:
    """Validation scores (%) against step, one panel per (key, title), one line per run in the same colour
    in every panel; its best constant as a dashed line of that colour, its best checkpoint as a star."""
    figure = Figure(figsize=(0.6 + 2.9 * len(panels), 3.2), layout="constrained")
    axes = figure.subplots(1, len(panels), squeeze=False)[0]
    for ax, (key, title) in zip(axes, panels):
        top = 1.0
        for index, curve in enumerate(curves):
            colour = piece_colour(index)
            if key in curve.points:
                steps, values = curve.points[key]
                marker = "." if len(steps) < 20 else None
                ax.plot(steps, values, marker=marker, color=colour, label=curve.name)
                top = max(top, float(np.max(values)))
            if key in curve.constants:
                ax.axhline(curve.constants[key], color=colour, ls="--", lw=1)
                top = max(top, curve.constants[key])
            if curve.best and curve.best[0] == key:
                ax.plot([curve.best[1]], [curve.best[2]], ls="none", marker="*", ms=10, color=colour,
                        mec="black", mew=0.5)  # fmt: skip
        ax.set_ylim(0, min(105.0, top * 1.1))  # room for a star at 100 %
        ax.set_title(title, fontsize=8)
        ax.set_xlabel("step")
        ax.set_ylabel("validation (%)")
        ax.grid(alpha=0.3)
    if any(curve.constants for curve in curves):
        axes[0].plot([], [], color="black", ls="--", lw=1, label="best constant (hindsight)")
    if any(curve.best for curve in curves):
        axes[0].plot([], [], ls="none", marker="*", ms=8, color="black", label="best.pt")
    # one legend beside the panels, each label once: a run may have points in one panel only
    legend = {label: handle for ax in axes for handle, label in zip(*ax.get_legend_handles_labels())}
    figure.legend(legend.values(), legend.keys(), loc="outside right upper", fontsize=6)
    return figure


def matched_vertices(pred: LaneGraph, gt: LaneGraph, params: MetricParams) -> tuple:
    """(pred xy, pred matched?, gt xy, gt matched?) of the densified graphs (directed mode), paired by
    the metric's own matching M(V_pred, V_gt) (docs/METRICS.md step 2)."""
    p, g = densify(pred, params.step)["directed"], densify(gt, params.step)["directed"]
    pairs = match(candidate_pairs(p.xy, g.xy, params.match_radius), p.n, g.n, params.matching)
    return p.xy, pairs.partner_a >= 0, g.xy, pairs.partner_b >= 0


@styled
def frame_view(
    pred: LaneGraph, gt: LaneGraph, params: MetricParams, title: str, camera: dict | None = None
) -> Figure:
    """Ground truth and prediction side by side, their densified vertices coloured matched / unmatched;
    with camera ({image, pixels_of}, see `front_camera`) a third panel projects both onto the image."""
    crop = Range.parse(params.bev_range)
    p_xy, p_ok, g_xy, g_ok = matched_vertices(pred, gt, params)
    panels = 3 if camera else 2
    figure = Figure(figsize=(PANEL_INCHES * 1.3 * panels, PANEL_INCHES * 2.6 + 0.4), layout="constrained")
    axes = figure.subplots(1, panels, squeeze=False)[0]
    sides = ((axes[0], "ground truth", gt, g_xy, g_ok), (axes[1], "prediction", pred, p_xy, p_ok))
    for ax, name, graph, xy, ok in sides:
        bev_axes(ax, crop, f"{name}: {int(ok.sum())} of {len(ok)} vertices matched")
        draw_graph(ax, graph, lw=0.8, alpha=0.6)
        ax.scatter(xy[~ok, 0], xy[~ok, 1], s=1.5, c=UNMATCHED, label="unmatched", zorder=3)
        ax.scatter(xy[ok, 0], xy[ok, 1], s=1.5, c=MATCHED, label="matched", zorder=4)
        draw_ego(ax)
        ax.legend(fontsize=5, loc="lower right", markerscale=3)
    if camera:
        ax = axes[2]
        ax.imshow(camera["image"])
        for graph, colour, name in ((gt, "#ffd000", "ground truth"), (pred, "#00c8ff", "prediction")):
            for k, uv in enumerate(camera["pixels_of"](graph)):
                ax.plot(uv[:, 0], uv[:, 1], color=colour, lw=1.2, label=name if k == 0 else None)
        ax.set_xlim(0, camera["image"].shape[1])
        ax.set_ylim(camera["image"].shape[0], 0)
        ax.set_title(camera["name"], fontsize=7)
        ax.axis("off")
        ax.legend(fontsize=5, loc="lower right")
    figure.suptitle(title, fontsize=7)
    return figure


def forward_camera(cameras: list[dict]) -> dict:
    """Of a frame's cameras (frames.cameras), the one whose optical axis points most along +y (forward)."""
    forward = [np.array(c["sensor_to_ego"]).reshape(4, 4)[:3, 2] @ np.array([0.0, 1.0, 0.0]) for c in cameras]
    return cameras[int(np.argmax(forward))]


def front_camera(data: Path, frame: dict) -> dict:
    """The frame's camera that looks most along +y (forward), its image, and a function that projects a
    graph laid on the ground (the plane of frames.ground_z and ground_slope) into it with the encoder's own
    `project_points` (pipeline/camera.py)."""
    import json

    import cv2
    import torch

    from pipeline.camera import project_points, scaled_intrinsics

    if not frame["cameras"]:
        raise ValueError(f"{data / 'frames'}: frame {frame['frame_id']} has no cameras")
    manifest = json.loads((Path(data) / "manifest.json").read_text())
    camera = forward_camera(frame["cameras"])
    path = Path(manifest["root"]) / camera["image_path"]
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise FileNotFoundError(f"{path}: image missing or unreadable")
    image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    height, width = image.shape[:2]
    k = np.array(camera["intrinsics"]).reshape(3, 3)
    k = scaled_intrinsics(k, width / camera["width"], height / camera["height"])
    intrinsics = torch.tensor(k, dtype=torch.float32)[None, None]
    extrinsics = np.array(camera["sensor_to_ego"]).reshape(4, 4)
    sensor_to_ego = torch.tensor(extrinsics, dtype=torch.float32)[None, None]
    sizes = torch.tensor([[[height, width]]])

    def pixels_of(graph: LaneGraph) -> list[np.ndarray]:
        """Each edge, cut into 0.25 m steps on the ground, as image (u, v); NaN where not visible."""
        xy = np.stack([np.asarray(graph.x, np.float64), np.asarray(graph.y, np.float64)], axis=1)
        lines = []
        for s, d in zip(np.asarray(graph.src), np.asarray(graph.dst)):
            steps = max(2, int(np.ceil(np.linalg.norm(xy[d] - xy[s]) / 0.25)) + 1)
            lines.append(xy[s] + (xy[d] - xy[s]) * np.linspace(0, 1, steps)[:, None])
        if not lines:
            return []
        ground = np.concatenate(lines)
        z = ground_height(ground[:, 0], ground[:, 1], frame["ground_z"], frame["ground_slope"])
        ground = np.column_stack([ground, z])
        uv, visible = project_points(
            torch.tensor(ground, dtype=torch.float32), intrinsics, sensor_to_ego, sizes
        )
        uv, visible = uv[0, 0].numpy().astype(np.float64), visible[0, 0].numpy()
        uv[~visible] = np.nan
        cuts = np.cumsum([len(line) for line in lines])[:-1]
        return [part for part, seen in zip(np.split(uv, cuts), np.split(visible, cuts)) if seen.any()]

    return {"image": image, "pixels_of": pixels_of, "name": camera["name"]}


def frame_f1(pred: LaneGraph, gt: LaneGraph, params: MetricParams) -> float:
    from benchmark.score import score_pairs

    return score_pairs([(pred, gt)], params)["directed"]["topo"]["f1"]


def viz(pred_path: Path, gt_path: Path, frame_id: str | None, out: Path, camera: bool = False) -> dict:
    """One frame of a prediction against the ground truth, written to `out` (PNG); frame_id None: the
    predicted frame (with a non-empty ground truth) of the lowest directed TOPO F1, ties to the frame
    with the most ground-truth vertices. Returns {frame_id, scores}."""
    from benchmark.graph_table import default_range, graphs_from_table, read_graph_table
    from benchmark.score import score_pairs

    gt_path, pred_path = Path(gt_path), Path(pred_path)
    params = MetricParams(bev_range=default_range(gt_path))
    gt = graphs_from_table(read_graph_table(gt_path), gt_path)
    pred = graphs_from_table(read_graph_table(pred_path), pred_path)
    unknown = sorted(set(pred) - set(gt))
    if unknown:
        raise ValueError(f"{pred_path}: frame {unknown[0]} is not in the ground truth {gt_path}")
    if frame_id is None:
        candidates = [f for f in sorted(pred) if len(gt[f].x)]
        if not candidates:
            raise ValueError(f"{pred_path}: no predicted frame has a non-empty ground truth in {gt_path}")
        frame_id = min(candidates, key=lambda f: (frame_f1(pred[f], gt[f], params), -len(gt[f].x), f))
    elif frame_id not in gt:
        raise ValueError(f"{gt_path}: no frame {frame_id!r} in the ground truth")
    prediction = pred.get(frame_id, LaneGraph.empty())
    scores = score_pairs([(prediction, gt[frame_id])], params)
    view = None
    if camera:
        from pyarrow.dataset import field

        from pipeline.io import read_table

        if not (gt_path / "frames").is_dir():
            raise ValueError(
                f"{gt_path}: --camera needs a prepared dataset folder (frames table), not a file"
            )
        frame = read_table(gt_path, "frames", filter=field("frame_id") == frame_id).to_pylist()[0]
        view = front_camera(gt_path, frame)
    d = scores["directed"]
    title = (
        f"{frame_id}   directed TOPO P {100 * d['topo']['precision']:.1f} R {100 * d['topo']['recall']:.1f} "
        f"F1 {100 * d['topo']['f1']:.1f}   Junction TOPO F1 {100 * d['junction_topo']['f1']:.1f} (%)"
    )
    save_png(frame_view(prediction, gt[frame_id], params, title, view), out)
    return {"frame_id": frame_id, "scores": scores}


@styled
def save_png_palette(figure: Figure, path: Path, dpi: int = 110, colours: int = 256) -> Path:
    """Write the figure to path as a PNG of at most `colours` colours (an adaptive octree palette, which
    keeps a colour map's hues apart from a photograph's): camera pictures take a quarter of the bytes of a
    full-colour PNG."""
    import io

    from PIL import Image

    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=dpi)
    image = Image.open(buffer).convert("RGB").quantize(colours, method=Image.Quantize.FASTOCTREE)
    write_atomic(Path(path), lambda tmp: image.save(tmp, format="PNG", optimize=True))
    return Path(path)


@styled
def camera_overlays(
    cameras: list[dict], title: str, columns: int = 3, max_depth: float = 40.0, panel_inches: float = 3.6
) -> Figure:
    """Camera images in a grid, each with points drawn on it: per camera a dict of `name`, `image` (H, W, 3)
    and `layers`, a list of (uv (N, 2) pixels of that image, colour values (N,) or None, style dict of
    `Axes.scatter`); values are coloured by depth in metres (turbo, near red, far blue, up to max_depth)."""
    from matplotlib import colormaps

    rows = -(-len(cameras) // columns)
    aspect = max(c["image"].shape[0] / c["image"].shape[1] for c in cameras)
    figure = Figure(
        figsize=(panel_inches * columns, panel_inches * aspect * rows + 0.5), layout="constrained"
    )
    axes = figure.subplots(rows, columns, squeeze=False)
    colour_map = colormaps["turbo_r"]
    mappable = None
    for ax, camera in zip(axes.ravel(), cameras):
        ax.imshow(camera["image"])
        for uv, values, style in camera["layers"]:
            if values is None:
                ax.scatter(uv[:, 0], uv[:, 1], **style)
            else:
                order = np.argsort(-values)  # near points drawn last, on top
                mappable = ax.scatter(
                    uv[order, 0], uv[order, 1], c=values[order], cmap=colour_map, vmin=0.0, vmax=max_depth,
                    **style,
                )  # fmt: skip
        ax.set_xlim(-0.5, camera["image"].shape[1] - 0.5)
        ax.set_ylim(camera["image"].shape[0] - 0.5, -0.5)
        ax.set_title(camera["name"], fontsize=7)
        ax.axis("off")
    for ax in axes.ravel()[len(cameras) :]:
        ax.axis("off")
    if mappable is not None:
        bar = figure.colorbar(mappable, ax=axes, shrink=0.6, pad=0.01, aspect=30)
        bar.set_label("depth (m)", fontsize=6)
        bar.ax.tick_params(labelsize=5)
    figure.suptitle(title, fontsize=7)
    return figure


@styled
def sweep_over_map(
    points: np.ndarray,
    ground_z: float,
    ground_slope: tuple[float, float],
    edges: list[np.ndarray],
    paint: list[tuple[np.ndarray, str]],
    graph: LaneGraph,
    crop: Range,
    title: str,
    intensity_max: float = 0.2,
) -> Figure:
    """A LiDAR sweep in the BEV frame over a map, two panels: the returns coloured by height above the
    ground (the plane z = ground_z + a x + b y of frames.ground_z and ground_slope) under the road edges
    (`edges`: (n, 2) polylines), and the returns within 0.3 m of the ground coloured by intensity (0..1,
    white from intensity_max: asphalt returns are dark, paint bright) under the painted lane boundaries
    (`paint`: (polyline, colour)) and the lane graph."""
    figure = Figure(figsize=(PANEL_INCHES * 2.7, PANEL_INCHES * 2.3), layout="constrained")
    axes = figure.subplots(1, 2)
    height = points[:, 2] - ground_height(points[:, 0], points[:, 1], ground_z, ground_slope)
    inside = (
        (points[:, 0] >= crop.x_min) & (points[:, 0] <= crop.x_max)
        & (points[:, 1] >= crop.y_min) & (points[:, 1] <= crop.y_max)
    )  # fmt: skip
    ax = axes[0]
    bev_axes(ax, crop, "returns by height above the ground; road edges (red)")
    shown = inside & (height < 2.5)
    order = np.argsort(height[shown])
    dots = ax.scatter(points[shown, 0][order], points[shown, 1][order], c=height[shown][order], s=0.6,
                      cmap="viridis", vmin=-0.1, vmax=0.5, linewidths=0, rasterized=True)  # fmt: skip
    for line in edges:
        ax.plot(line[:, 0], line[:, 1], color="#e8221b", lw=0.7)
    bar = figure.colorbar(dots, ax=ax, shrink=0.5, pad=0.01)
    bar.set_label("height above the ground (m)", fontsize=6)
    bar.ax.tick_params(labelsize=5)
    draw_ego(ax)
    ax = axes[1]
    bev_axes(ax, crop, "ground returns by intensity; paint (dashed), lane graph")
    ground = inside & (np.abs(height) < 0.3)
    order = np.argsort(points[ground, 3])
    ax.set_facecolor("black")
    dots = ax.scatter(points[ground, 0][order], points[ground, 1][order], c=points[ground, 3][order], s=1.0,
                      cmap="gray", vmin=0.0, vmax=intensity_max, linewidths=0, rasterized=True)  # fmt: skip
    bar = figure.colorbar(dots, ax=ax, shrink=0.5, pad=0.01, extend="max")
    bar.set_label("intensity (0..1)", fontsize=6)
    bar.ax.tick_params(labelsize=5)
    for line, colour in paint:
        ax.plot(line[:, 0], line[:, 1], color=colour, lw=0.6, ls=(0, (3, 2)), alpha=0.9)
    draw_graph(ax, graph, lw=0.7, alpha=0.8)
    draw_ego(ax)
    figure.suptitle(title, fontsize=7)
    return figure
