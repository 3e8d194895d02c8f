"""The measured tables of report.md as markdown cells: the main table (paper Tab. 1), the settings, mIoU,
the ablations, the scores by junction count and the round trips' post-processing accuracy (Tab. 10).

Each table is (header, rows) built from the runs' own numbers (benchmark/report/runs.py), the best F1 of a
column among the runs in bold; the one exception that scores anything is the scores by junction count,
which score each run's predictions.parquet on the frames of each bucket with the project's own metric.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from benchmark.graph_table import graphs_from_table, read_graph_table
from benchmark.metric.densify import densify
from benchmark.metric.params import MetricParams
from benchmark.report.runs import (
    EXTERNAL_NAMES,
    Block,
    Run,
    find_data,
    is_synthetic,
    percent,
    read_json,
    shown,
)
from benchmark.score import score_pairs
from pipeline.lane_graph import LaneGraph

MODES = ("directed", "undirected")
METRICS = ("junction_topo", "topo")  # the paper's Tab. 1 order: Junction TOPO first
STATS = ("precision", "recall", "f1")
SHORT = {"directed": "dir", "undirected": "undir", "junction_topo": "J-TOPO", "topo": "TOPO",
         "precision": "P", "recall": "R", "f1": "F1"}  # fmt: skip
F1_COLUMNS = [(mode, metric) for mode in MODES for metric in ("topo", "junction_topo")]
VIA_NAMES = {"path": "Path2Graph (paths)", "piece": "Piece2Graph (pieces)", "pixel": "Pixel2Graph (rasters)"}
# config fields that do not change what a run learns: never the varied field of an ablation
IGNORED_FIELDS = {
    "data.num_workers",
    "data.cache_samples",
    "data.sensor_root",
    "train.threads",
    "train.log_every",
}
FIELD_NAMES = {"decoder.path_points": "points per path", "decoder.bezier_points": "Bezier control points",
               "decoder.aux_seg": "auxiliary segmentation", "encoder.modality": "modality",
               "train.epochs": "epochs"}  # fmt: skip
JUNCTION_BUCKETS = ((0, 0, "0"), (1, 2, "1-2"), (3, 5, "3-5"), (6, math.inf, "6+"))
GRID_JUNCTION_FRAMES = 4  # grid rows: the frames with the most junctions, then one plain road
JUNCTION_DEFINITION = (
    "A frame's junction count is the number of vertices of its ground-truth lane graph with in-degree "
    ">= 2 or out-degree >= 2 once points at identical coordinates are one vertex: the forks and merges "
    "that directed Junction TOPO anchors at (docs/METRICS.md, step 1 and Junction TOPO)."
)


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A markdown table; a `|` inside a cell (a run folder's or a method's name) is escaped, so that it stays
    in its cell rather than starting another."""

    def line(cells: list[str]) -> str:
        return "| " + " | ".join(str(cell).replace("|", "\\|") for cell in cells) + " |"

    return "\n".join([line(header), line(["---"] * len(header)), *map(line, rows)])


def bold_best(cells: list[list[str]], values: list[list[float]]) -> None:
    """Bold, in each column, every cell holding the column's maximum: only among two rows or more, and
    only when a row is below it (a column of ties has no best)."""
    if len(values) < 2:
        return
    for col in range(len(values[0])):
        best = max(row[col] for row in values)
        if best == min(row[col] for row in values):
            continue
        for row, row_values in zip(cells, values):
            if row_values[col] == best:
                row[col] = f"**{row[col]}**"


def score_cells(result: dict) -> list[str]:
    return [percent(result[mode][metric][stat]) for mode in MODES for metric in METRICS for stat in STATS]


SCORE_HEADER = [
    f"{SHORT[mode]} {SHORT[metric]} {SHORT[stat]}" for mode in MODES for metric in METRICS for stat in STATS
]


# (metrics.json key, format, divisor) of the main table's last columns: Params (M), GFLOPs, FPS_net, FPS
MEASURED_CELLS = (("params", ".2f", 1e6), ("gflops", ".2f", 1), ("fps_net", ".1f", 1), ("fps", ".1f", 1))


def cell_or(value: float | None, spec: str, missing: str, divisor: float = 1) -> str:
    """A measured number formatted, or `missing` when it is null."""
    return missing if value is None else format(value / divisor, spec)


def main_table(block: Block) -> tuple[list[str], list[list[str]]]:
    """Tab. 1's layout: a row per run, then the sensor-blind floor rows and the best constant in
    hindsight; the best F1 of each column (among the runs) in bold. Scores in %, each run's F1 with its
    95 % interval when drawn."""
    header = [
        "run",
        "method",
        "modeling",
        "modality",
        *SCORE_HEADER,
        "Params (M)",
        "GFLOPs",
        "FPS_net",
        "FPS",
    ]
    f1_at = [i for i, name in enumerate(SCORE_HEADER) if name.endswith("F1")]
    rows, values = [], []
    for run in block.scored:
        m = run.metrics
        cells = [run.f1_cell(mode, metric) if stat == "f1" else percent(m[mode][metric][stat])
                 for mode in MODES for metric in METRICS for stat in STATS]  # fmt: skip
        values.append([float(m[mode][metric]["f1"]) for mode in MODES for metric in METRICS])
        missing = "unknown" if run.external is not None else "–"  # an external run's: not measured here
        extra = [cell_or(m.get(key), spec, missing, divisor) for key, spec, divisor in MEASURED_CELLS]
        rows.append([run.name, run.method, m.get("modeling", "–"), run.modality, *cells, *extra])
    f1_cells = [[row[4 + i] for i in f1_at] for row in rows]
    bold_best(f1_cells, values)
    for row, cells in zip(rows, f1_cells):
        for i, cell in zip(f1_at, cells):
            row[4 + i] = cell
    priors, best = {}, {}
    for run in block.scored:
        floor = run.metrics.get("floor") or {}
        prior = floor.get("constant_prior")
        if prior:
            label = f"GT of {prior['frame_id']} ({prior.get('split', 'train')})"
            priors[prior["frame_id"]] = ["constant prior", label, "–", "none", *score_cells(prior)]
        if floor.get("best_constant"):
            constant = floor["best_constant"]
            label = f"GT of {constant['frame_id']} ({constant.get('split', 'train')})"
            cells = score_cells(constant)
            best[constant["frame_id"]] = ["best constant (hindsight)", label, "–", "none", *cells]
        if floor.get("other_log_sensors"):
            cells = score_cells(floor["other_log_sensors"])
            rows.append([f"{run.name}: other log's sensors", run.method, "–", run.modality, *cells])
    rows += list(priors.values()) + list(best.values())
    for row in rows:
        row += ["–"] * (len(header) - len(row))
    for run in block.runs:
        if not run.scored:
            rows.append([run.name, "not scored: " + "; ".join(run.reasons)] + ["–"] * (len(header) - 2))
    return header, rows


def settings_table(block: Block) -> tuple[list[str], list[list[str]]]:
    header = ["run", "device", "precision", "preset", "epochs trained / set", "schedule",
              "batch size (total)", "processes x micro-batches x frames", "split"]  # fmt: skip
    rows = []
    for run in block.runs:
        if run.external is not None:  # no config, run.json or log: only what cli score knew
            preset = f"external ({run.external.get('format', '?')})"
            rows.append([run.name, "–", "–", preset, "–", "–", "–", "–", str(run.split or "–")])
            continue
        config = run.config or {}
        train = config.get("train", {})
        trained = max((entry.get("epoch", 0) for entry in run.log), default=None)
        info, metrics = run.info, run.metrics or {}
        split_batch = "–"
        if "batch_per_forward" in info:
            split_batch = f"{info['world_size']} x {info['accumulate']} x {info['batch_per_forward']}"
        epochs = f"{trained if trained is not None else '–'} / {train.get('epochs', '–')}"
        rows.append([
            run.name, str(metrics.get("device", "–")), str(metrics.get("precision", "–")),
            str(config.get("preset", "–")), epochs, str(info.get("schedule", "–")),
            str(train.get("batch_size", "–")), split_batch, str(run.split or "–"),
        ])  # fmt: skip
    return header, rows


def params_line(params: dict) -> str:
    return ", ".join(f"{key} {value}" for key, value in params.items())


def floor_notes(block: Block) -> list[str]:
    notes = []
    for run in block.scored:
        floor = run.metrics.get("floor")
        if run.external is not None:  # external_notes says why it has none
            continue
        if floor is None:
            notes.append(f"{run.name}: no sensor-blind floor recorded (evaluated with `--no-floor`).")
            continue
        for name, reason in (floor.get("absent") or {}).items():
            notes.append(f"{run.name}: no `{name}` floor row: {reason}.")
    return notes


def external_notes(block: Block) -> list[str]:
    """A note per external run of the block: what `cli score` read (format, file, its sha256, the class
    and score kept), on which frames, and what is unknown of it."""
    notes = []
    for run in block.scored:
        ext = run.external
        if ext is None:
            continue
        fmt, source, digest = ext.get("format"), ext.get("source"), ext.get("sha256")
        what = f"{EXTERNAL_NAMES.get(fmt, fmt)} `{Path(source).name if source else '?'}`"
        what += f", sha256 {digest[:12]}" if digest else ", no sha256 recorded"
        parts = []
        if ext.get("class_name") is not None:
            kept = f" above score {ext['min_score']:g}" if ext.get("min_score") is not None else ""
            parts.append(f"class `{ext['class_name']}`{kept}")
        split = f"the {run.split} split's" if run.split else "the ground truth's"
        absent = run.metrics.get("frames_missing") or 0
        if fmt == "graph":  # a graph table: the split's frames it lacks are scored as empty predictions
            parts.append(f"{run.metrics['frames']} of {split} frames scored, {absent} of them not in its "
                         "file (scored as empty predictions)")  # fmt: skip
        else:  # another codebase's JSON: the frames in its file alone
            if ext.get("frames_in_file") is not None:
                parts.append(f"{ext['frames_in_file']} frames in its file scored")
            missing = ext.get("frames_not_in_file")
            if missing is not None:
                fewer = (" (its F1 is over fewer frames, so no paired lead is tested between it and a run "
                         "scored on other frames)") if missing > 0 else ""  # fmt: skip
                parts.append(f"{missing} of {split} frames not in its file{fewer}")
        if ext.get("points_clipped") is not None:
            parts.append(f"{ext['points_clipped']} points outside the range clipped")
        if ext.get("vectors_read") is not None:
            parts.append(f"{ext.get('vectors_kept', '?')} of {ext['vectors_read']} vectors kept")
        notes.append(
            f"{run.name}: external ({what}), scored by `cli score` with this report's metric on the same "
            f"ground truth" + (": " + "; ".join(parts) if parts else "") + ". Its parameter count, GFLOPs, "
            "FPS and sensor-blind floor are unknown: its training and sensors are not ours."
        )
    return notes


def miou_table(block: Block) -> tuple[list[str], list[list[str]]]:
    rows, values = [], []
    for run in block.scored:
        if run.metrics.get("miou") is not None:
            rows.append([run.name, run.method, run.modality, percent(run.metrics["miou"])])
            values.append([float(run.metrics["miou"])])
    cells = [[row[3]] for row in rows]
    bold_best(cells, values)
    for row, (cell,) in zip(rows, cells):
        row[3] = cell
    return ["run", "method", "modality", "mIoU"], rows


def ablations(block: Block) -> list[tuple[str, list[Run]]]:
    """(field, runs sorted by its value) for every set of runs (of one block, so one dataset and split)
    whose saved configs differ in exactly that one field; IGNORED_FIELDS never count."""

    def flat(config: dict) -> dict:
        out = {}
        for key, value in config.items():
            if isinstance(value, dict):
                out.update({f"{key}.{k}": v for k, v in value.items()})
            else:
                out[key] = value
        return {k: v for k, v in out.items() if k not in IGNORED_FIELDS}

    runs = [run for run in block.scored if run.config and run.external is None]
    configs = {id(run): flat(run.config) for run in runs}
    found = []
    for name in sorted(set().union(*configs.values()) if configs else ()):
        groups: dict[str, list[Run]] = {}
        for run in runs:
            rest = {k: v for k, v in configs[id(run)].items() if k != name}
            groups.setdefault(json.dumps(rest, sort_keys=True), []).append(run)
        for members in groups.values():
            if len({json.dumps(configs[id(run)].get(name)) for run in members}) >= 2:
                found.append((name, sorted(members, key=lambda run: sort_key(configs[id(run)].get(name)))))
    return found


def sort_key(value) -> tuple:
    """Numbers (and booleans) in order, before anything else in text order."""
    return (0, value, "") if isinstance(value, int | float) else (1, 0, str(value))


def ablation_table(name: str, runs: list[Run]) -> tuple[list[str], list[list[str]]]:
    header = [FIELD_NAMES.get(name, name), "run"] + [f"{SHORT[m]} {SHORT[k]} F1" for m, k in F1_COLUMNS]
    header += ["mIoU", "FPS"]
    rows, values = [], []
    for run in runs:
        value = flat_value(run.config, name)
        values.append([run.score(mode, metric) for mode, metric in F1_COLUMNS])
        rows.append([str(value), run.name] + [run.f1_cell(mode, metric) for mode, metric in F1_COLUMNS])
    cells = [row[2:] for row in rows]
    bold_best(cells, values)
    for row, run, cell in zip(rows, runs, cells):
        row[2:] = cell + [percent(run.metrics.get("miou")), f"{run.metrics['fps']:.1f}"]
    return header, rows


def flat_value(config: dict, name: str):
    section, _, key = name.partition(".")
    return config[section][key] if key else config[section]


def junction_count(graph: LaneGraph, step: float) -> int:
    """JUNCTION_DEFINITION: the directed junctions of the metric's own densified graph."""
    return int(np.count_nonzero(densify(graph, step)["directed"].junction))


def bucket_of(count: int) -> str:
    return next(label for low, high, label in JUNCTION_BUCKETS if low <= count <= high)


def block_graphs(block: Block) -> tuple[dict[str, LaneGraph], dict[str, dict[str, LaneGraph]], list[str]]:
    """(ground truth of the block's frames, {run name: predictions}, notes) of the scored runs."""
    notes, predictions = [], {}
    for run in block.scored:
        file = run.path / "predictions.parquet"
        if file.is_file():
            predictions[run.name] = graphs_from_table(read_graph_table(file), file)
        else:
            notes.append(
                f"{run.name}: no predictions.parquet, left out of the per-frame tables and pictures."
            )
    frames = sorted(set().union(*predictions.values())) if predictions else []
    gt = graphs_from_table(read_graph_table(block.data), block.data) if frames else {}
    unknown = [f for f in frames if f not in gt]
    if unknown:
        raise ValueError(f"{block.data}: frame {unknown[0]} of the predictions is not in the ground truth")
    return {f: gt[f] for f in frames}, predictions, notes


def junction_table(
    gt: dict[str, LaneGraph], predictions: dict[str, dict[str, LaneGraph]], counts: dict[str, int],
    params: MetricParams, workers: int = 1, own_frames: frozenset[str] = frozenset(),
) -> tuple[list[str], list[list[str]]]:  # fmt: skip
    """Directed TOPO and Junction TOPO F1 of every run on the frames of each junction-count bucket;
    scored here with the metric (a frame a run did not predict is an empty prediction, as `cli score`;
    the runs named in `own_frames`, external ones, are scored on their predicted frames alone, as their
    metrics.json)."""
    header = ["GT junctions", "frames"]
    for name in predictions:
        header += [f"{name} dir TOPO F1", f"{name} dir J-TOPO F1"]
    rows = []
    for _, _, label in JUNCTION_BUCKETS:
        frames = [f for f in sorted(gt) if bucket_of(counts[f]) == label]
        row = [label, str(len(frames))]
        for name, graphs in predictions.items():
            scored = [f for f in frames if f in graphs] if name in own_frames else frames
            if not scored:
                row += ["–", "–"]
                continue
            pairs = [(graphs.get(f, LaneGraph.empty()), gt[f]) for f in scored]
            result = score_pairs(pairs, params, workers)["directed"]
            row += [
                percent(result["topo"]["f1"]),
                "–" if label == "0" else percent(result["junction_topo"]["f1"]),
            ]
        rows.append(row)
    return header, rows


def grid_frames(counts: dict[str, int], gt: dict[str, LaneGraph]) -> list[str]:
    """The frames with the most junctions, then one plain road: the frame with the fewest junctions
    and the most ground-truth vertices (ties by frame_id)."""
    by_junctions = sorted(counts, key=lambda f: (-counts[f], f))
    chosen = by_junctions[:GRID_JUNCTION_FRAMES]
    rest = [f for f in counts if f not in chosen]
    if rest:
        chosen.append(min(rest, key=lambda f: (counts[f], -len(gt[f].x), f)))
    return chosen


def short_id(frame_id: str) -> str:
    parts = frame_id.split("/")
    return f"{parts[-2][:8]}/{parts[-1]}" if len(parts) >= 2 else frame_id


def load_roundtrips(paths: list[Path]) -> list[tuple[Path, dict]]:
    out = []
    for path in map(Path, paths):
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such roundtrip JSON")
        result = read_json(path)
        if "params" in result and "metric_params" not in result:  # a file from before the key's rename
            result["metric_params"] = result.pop("params")
        missing = [k for k in ("via", "frames", "directed", "undirected", "metric_params") if k not in result]
        if missing:
            raise ValueError(f"{path}: not a `cli roundtrip` result (no {', '.join(missing)})")
        out.append((path, result))
    return out


def roundtrip_tables(
    roundtrips: list[tuple[Path, dict]],
) -> list[tuple[str, list[str], list[list[str]], dict]]:
    """(title, header, rows, metric params) per data folder."""
    groups: dict[str, list[tuple[Path, dict]]] = {}
    for path, result in roundtrips:
        groups.setdefault(str(result.get("data", "?")), []).append((path, result))
    tables = []
    for data, members in sorted(groups.items()):
        params = members[0][1]["metric_params"]
        for path, result in members[1:]:
            if result["metric_params"] != params:
                differ = [k for k in sorted(params) if params.get(k) != result["metric_params"].get(k)]
                raise ValueError(
                    f"{path}: scored with other metric parameters ({', '.join(differ)}) than "
                    f"{members[0][0]}; they cannot share a table"
                )
        found, dataset = find_data([data])
        if found is not None and is_synthetic(read_json(found / "manifest.json")):
            dataset = f"{dataset} (synthetic, `cli synth`)"
        rows = []
        for path, result in sorted(
            members, key=lambda m: list(VIA_NAMES).index(m[1]["via"]) if m[1]["via"] in VIA_NAMES else 9
        ):
            name = VIA_NAMES.get(result["via"], result["via"])
            rows.append(
                [name, path.name, str(result["frames"]), *score_cells(result), percent(result.get("miou"))]
            )
        header = ["representation", "file", "frames", *SCORE_HEADER, "mIoU"]
        tables.append((f"{dataset}: `{shown(data) if found else data}`", header, rows, params))
    return tables
