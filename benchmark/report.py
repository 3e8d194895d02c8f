"""`cli report`: the comparison tables and pictures of finished runs, as DIR/report.md and its PNGs.

Reads what `cli train` and `cli eval` (RUN/metrics.json, predictions.parquet, config.json, run.json,
log.jsonl, val.jsonl) and `cli roundtrip` (JSON) wrote, and never recomputes a score, with one exception
that says so: the scores by junction count, which score each run's predictions.parquet on subsets of its
frames with the project's own metric. Runs are grouped in blocks, one per prepared dataset and split
(read from the data's manifest.json): runs scored on different frames never share a table.

Each F1 has a 95 % interval from a bootstrap over the block's frames (benchmark/bootstrap.py), drawn from
the per-frame counts `cli eval` keeps (RUN/frame_counts.parquet); the summary calls a run's lead a lead
only when the paired interval of the difference (same frames, same draws) excludes 0. With
`reference="paper"`, the paper's published tables (benchmark/reference.py) stand beside the measured
ones they match, as reference tables of their own. Paths are written relative to the working directory.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from benchmark import bootstrap, figures
from benchmark.metrics import MetricParams, densify
from benchmark.reference import SCORE_KEYS, ReferenceTable, load_reference
from benchmark.score import graphs_from_table, read_graph_table, score_pairs
from pipeline.geometry import Range
from pipeline.io import write_atomic
from pipeline.lane_graph import LaneGraph

MODES = ("directed", "undirected")
METRICS = ("junction_topo", "topo")  # the paper's Tab. 1 order: Junction TOPO first
STATS = ("precision", "recall", "f1")
SHORT = {"directed": "dir", "undirected": "undir", "junction_topo": "J-TOPO", "topo": "TOPO",
         "precision": "P", "recall": "R", "f1": "F1"}  # fmt: skip
F1_COLUMNS = [(mode, metric) for mode in MODES for metric in ("topo", "junction_topo")]
METHOD_NAMES = {"lanegap": "LaneGAP", "maptr": "MapTR", "stsu": "STSU", "hdmapnet": "HDMapNet"}
VIA_NAMES = {"path": "Path2Graph (paths)", "piece": "Piece2Graph (pieces)", "pixel": "Pixel2Graph (rasters)"}
RUN_FILES = ("metrics.json", "config.json", "run.json", "checkpoint.pt", "log.jsonl", "predictions.parquet")
REQUIRED = ("frames", "directed", "undirected", "metric_params", "params", "fps_net", "fps", "split", "data")
MEASURED = ("params", "fps_net", "fps")  # null only in an external run's metrics.json (not measured here)
# an external run (`cli score --out RUN_DIR`: another codebase's result file, metrics.json's "external")
EXTERNAL_NAMES = {"maptrv2": "MapTRv2 / LaneGAP JSON", "cgnet": "CGNet JSON", "graph": "graph table"}
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

FLOOR_NOTE = (
    "Rows `constant prior` and `<run>: other log's sensors` are the sensor-blind floor (`cli eval`): what "
    "a model that ignores its frame's sensors scores on the same frames. Row `best constant (hindsight)`: "
    "of the constant prior's candidate graphs, the one that scores best on these frames themselves, an "
    "upper bound for any constant prediction (chosen on the evaluated frames, so not a blind model)."
)
REFERENCE_NOTE = (
    "Tables headed *Reference* hold the paper's published numbers (benchmark/paper_reference.toml, each "
    "from the LaTeX table named in its rows), not numbers measured here: the paper trained on the full "
    "datasets on 8 RTX 3090 GPUs; each row's label names its schedule and the GPU of its FPS. They are "
    "context for the measured tables beside them, never bolded, ranked or averaged with measured rows."
)
SYNTHETIC_NOTE = (
    "These runs are on synthetic data (`cli synth`): the paper's rows are context for them, not a "
    "like-for-like comparison."
)
UNKNOWN_ORIGIN_NOTE = (
    "Whether these runs are on synthetic data is unknown: the raw data their dataset's manifest names is "
    "gone. The paper's rows are context, not a like-for-like comparison."
)
# where each paper table is shown, for the list of those no measured table matched
REFERENCE_PLACES = {
    "tab:modeling": "under a dataset block of nuScenes or AV2 at 30 x 60 m on its own split",
    "tab:iou": "beside the mIoU table of a nuScenes or AV2 block at 30 x 60 m on its own split",
    "tab:postproc": "beside the post-processing accuracy of `--roundtrip` results",
    "tab:perception_range": "under a dataset block prepared at 50 x 100 m",
    "tab:newsplit": "under a dataset block prepared with `--split-file` (a geographic split)",
}
EXTERNAL_NOTE = (
    "A run whose method ends in *(external)* is another codebase's result file, scored by `cli score --out "
    "RUN_DIR` with the same metric on the same ground truth (its metrics.json, not `cli eval`'s): ranked "
    "and bolded with the runs, but its size, speed, sensors and sensor-blind floor are unknown (the note "
    "under its table says what was read)."
)
VALIDATION_FILE = "val.jsonl"
# val.jsonl's keys drawn, one panel each, with the best constant's F1 (metrics.json floor) of each
VALIDATION_PANELS = (("directed_topo_f1", "directed", "topo"),
                     ("directed_junction_topo_f1", "directed", "junction_topo"))  # fmt: skip
VALIDATION_NAMES = {"directed_topo_f1": "directed TOPO F1",
                    "directed_junction_topo_f1": "directed Junction TOPO F1",
                    "undirected_topo_f1": "undirected TOPO F1",
                    "undirected_junction_topo_f1": "undirected Junction TOPO F1", "miou": "mIoU"}  # fmt: skip
VALIDATION_NOTE = (
    "From each run's val.jsonl (`cli train --eval-every`: one point per validation, on the frames its line "
    "names, a fixed subset with `--eval-frames`). Dashed: the run's best constant in hindsight from its "
    "metrics.json, scored on `cli eval`'s frames. Star: the checkpoint kept as best.pt (`best` in run.json)."
)
GRID_NOTE = "Each piece in its own colour, arrows in the driving direction, the ego car in grey."


@dataclass
class Run:
    path: Path
    name: str
    metrics: dict | None  # metrics.json; None when the run has no usable one (see reasons)
    config: dict | None  # config.json (else the copy in metrics.json)
    data: Path | None  # the prepared dataset it was scored on (or trained on), when found
    dataset: str  # the data manifest's dataset name; "unknown" when the data is not found
    split: str | None
    world_size: int | None
    log: list[dict] = field(default_factory=list)
    reasons: list[str] = field(default_factory=list)  # why it has no scores
    frame_ids: list[str] = field(default_factory=list)  # sorted; the rows of counts
    counts: np.ndarray | None = None  # per-frame metric sums (bootstrap.FRAME_COUNTS); None: see no_counts
    no_counts: str = ""  # why a scored run has no per-frame counts (so no intervals)
    intervals: dict | None = None  # {mode: {metric: [low, high]}} of each F1, drawn for its block
    info: dict = field(default_factory=dict)  # run.json: processes, accumulation, schedule
    validation: list[dict] | None = None  # val.jsonl's records (validation during training); None: no file
    cut: list[str] = field(default_factory=list)  # the files whose cut-short last line was left out

    @property
    def scored(self) -> bool:
        return self.metrics is not None

    @property
    def external(self) -> dict | None:
        """metrics.json's "external": what `cli score` read of another codebase's result file; None for
        a run trained here."""
        return (self.metrics or {}).get("external")

    @property
    def method(self) -> str:
        if self.external is not None:
            fmt = self.external.get("format")
            return f"{EXTERNAL_NAMES.get(fmt, fmt)} (external)"
        model = (self.metrics or {}).get("model") or (self.config or {}).get("model") or "?"
        return METHOD_NAMES.get(model, model)

    @property
    def modality(self) -> str:
        if self.external is not None:
            return "unknown"
        return (self.config or {}).get("encoder", {}).get("modality", "-")

    def score(self, mode: str, metric: str, stat: str = "f1") -> float:
        return float(self.metrics[mode][metric][stat])

    def f1_cell(self, mode: str, metric: str) -> str:
        """The F1 in %, then its 95 % interval when drawn."""
        cell = percent(self.score(mode, metric))
        if self.intervals:
            low, high = self.intervals[mode][metric]
            cell += f" [{percent(low)}, {percent(high)}]"
        return cell

    def f1_text(self, mode: str, metric: str) -> str:
        """The F1 in words: "40.7 % (95 % interval 22.5-55.1 %)"."""
        text = f"{percent(self.score(mode, metric))} %"
        if self.intervals:
            low, high = self.intervals[mode][metric]
            text += f" (95 % interval {percent(low)}-{percent(high)} %)"
        return text

    def floor_f1(self, mode: str, metric: str) -> float | None:
        f1 = ((self.metrics or {}).get("floor") or {}).get("f1")
        return None if not f1 else f1[mode][metric]


@dataclass
class Block:
    """The runs of one prepared dataset and split: one main table."""

    dataset: str
    data: Path | None
    split: str | None
    runs: list[Run]
    manifest: dict = field(default_factory=dict)  # the data's manifest.json ({} when not found)
    synthetic: bool | None = None  # made by `cli synth`; None: its raw data is gone, so unknown

    @property
    def name(self) -> str:
        """The dataset's name as the report writes it: synthetic data says so."""
        return f"{self.dataset} (synthetic, `cli synth`)" if self.synthetic else self.dataset

    @property
    def parameters(self) -> dict:
        return self.manifest.get("parameters", {})

    @property
    def scored(self) -> list[Run]:
        return [run for run in self.runs if run.scored]

    @property
    def metric_params(self) -> dict | None:
        return self.scored[0].metrics["metric_params"] if self.scored else None

    @property
    def title(self) -> str:
        frames = ""
        if self.scored:
            ours = [run for run in self.scored if run.external is None] or self.scored
            frames = f", {ours[0].metrics['frames']} frames"
            fewer = [run for run in self.scored if run.metrics["frames"] != ours[0].metrics["frames"]]
            if fewer:
                frames += " (" + "; ".join(f"{run.name}: {run.metrics['frames']}" for run in fewer) + ")"
        data = shown(self.data) if self.data else "data not found"
        return f"{self.name}: `{data}`, {self.split or '?'} split{frames}"


def shown(path: Path | str) -> str:
    """A path as the report writes it: relative to the working directory, so that a report made in a
    temporary folder (or moved) names no absolute path."""
    return os.path.relpath(Path(path).absolute())


def read_json(path: Path) -> dict:
    try:
        return json.loads(Path(path).read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}: not valid JSON ({error})") from error


def read_jsonl(path: Path) -> tuple[list[dict], bool]:
    """The records of a JSON-lines file that training appends to (log.jsonl, val.jsonl), and whether its
    last line was cut short: a kill mid-write leaves a line without its newline, left out unparsed. NaN
    and Infinity (Python's json writes a non-finite loss so) read back as floats."""
    *complete, tail = Path(path).read_text(errors="replace").split("\n")
    records = []
    for number, line in enumerate(complete, 1):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError as error:
            raise ValueError(f"{shown(path)}, line {number}: not valid JSON ({error})") from error
    return records, bool(tail.strip())


def find_runs(paths: list[Path]) -> list[Path]:
    """Run folders: each path is a run folder (it holds config.json, metrics.json, ...) or a folder whose
    every sub-folder is taken as a run (an empty one then appears as a run without scores)."""
    found: list[Path] = []
    for path in map(Path, paths):
        if not path.is_dir():
            raise FileNotFoundError(f"{path}: no such run folder")
        if any((path / name).exists() for name in RUN_FILES):
            found.append(path)
            continue
        inner = sorted(p for p in path.iterdir() if p.is_dir() and not p.name.startswith("."))
        if not inner:
            raise ValueError(
                f"{path}: neither a run folder (no {', '.join(RUN_FILES[:3])}) nor a folder of runs"
            )
        found += inner
    unique = {p.resolve(): p for p in found}
    return list(unique.values())


def find_data(candidates: list) -> tuple[Path | None, str]:
    """(data folder, manifest dataset name) of the first candidate folder holding a manifest.json."""
    for candidate in candidates:
        if candidate and (Path(candidate) / "manifest.json").is_file():
            manifest = read_json(Path(candidate) / "manifest.json")
            return Path(candidate).resolve(), str(manifest.get("dataset", "unknown"))
    return None, "unknown"


def is_synthetic(manifest: dict) -> bool | None:
    """Whether a prepared dataset was made from `cli synth` output: its manifest names the raw root, and
    synth writes its marker (synth.json) at most two folders above the roots it writes. None when the raw
    root no longer exists (then nobody can tell)."""
    from pipeline.synth import MARKER

    if not manifest.get("root") or not Path(manifest["root"]).exists():
        return None
    root = Path(manifest["root"]).resolve()
    for folder in (root, *list(root.parents)[:2]):
        if (folder / MARKER).is_file():
            try:
                marker = json.loads((folder / MARKER).read_text())
            except json.JSONDecodeError:
                continue
            roots = [marker.get(key) for key in ("av2_root", "nuscenes_root")]
            if any(r and (folder / r).resolve() == root for r in roots):
                return True
    return False


def load_run(path: Path, name: str) -> Run:
    """A run folder as found: a missing or unusable file becomes a reason, never an exception."""
    reasons, metrics, config, info = [], None, None, {}
    for file_name in ("config.json", "run.json", "metrics.json"):
        file = path / file_name
        if not file.is_file():
            continue
        try:
            value = read_json(file)
        except ValueError as error:
            reasons.append(str(error).replace(str(file), shown(file), 1))
            continue
        config, info, metrics = (
            (value, info, metrics) if file_name == "config.json"
            else (config, value, metrics) if file_name == "run.json"
            else (config, info, value)
        )  # fmt: skip
    external = isinstance(metrics, dict) and metrics.get("external") is not None
    if not external and not (path / "checkpoint.pt").is_file():  # an external run was never trained here
        reasons.append("no checkpoint.pt (training did not finish)")
    if metrics is None and not (path / "metrics.json").is_file():
        reasons.append(f"no metrics.json (not evaluated: `cli eval --run {shown(path)}`)")
    elif metrics is not None:
        missing = [key for key in REQUIRED if key not in metrics]
        missing += [key for key in MEASURED if key in metrics and metrics[key] is None and not external]
        if missing:
            reasons.append(f"{shown(path / 'metrics.json')} lacks {', '.join(missing)} (re-run `cli eval`)")
            metrics = None
    config = config or (metrics or {}).get("config")
    data, dataset = find_data([(metrics or {}).get("data"), info.get("data")])
    split = (metrics or {}).get("split") or (config or {}).get("train", {}).get("val_split")
    log, cut = [], []
    if (path / "log.jsonl").is_file():
        log, cut_short = read_jsonl(path / "log.jsonl")
        cut += ["log.jsonl"] if cut_short else []
    validation = None
    if (path / VALIDATION_FILE).is_file():
        validation, cut_short = read_jsonl(path / VALIDATION_FILE)
        cut += [VALIDATION_FILE] if cut_short else []
    if metrics is None and not reasons:
        reasons.append("no metrics.json")
    run = Run(path, name, metrics, config, data, dataset, split, info.get("world_size"), log, reasons)
    run.info, run.validation, run.cut = info, validation, cut
    if metrics is not None:
        load_counts(run)
    return run


def load_counts(run: Run) -> None:
    """The run's per-frame counts (sorted by frame id), checked against its metrics.json: they must hold
    its frames and pool back to its F1 scores. Otherwise run.no_counts says why."""
    file = run.path / bootstrap.FRAME_COUNTS
    if not file.is_file():
        run.no_counts = f"no {bootstrap.FRAME_COUNTS} (evaluated before per-frame counts: re-run `cli eval`)"
        return
    try:
        frame_ids, counts = bootstrap.read_frame_counts(file)
    except ValueError as error:
        run.no_counts = str(error).replace(str(file), shown(file), 1)
        return
    order = np.argsort(frame_ids, kind="stable")
    frame_ids, counts = [frame_ids[i] for i in order], counts[order]
    if len(frame_ids) != run.metrics["frames"]:
        run.no_counts = f"{shown(file)} holds {len(frame_ids)} frames, metrics.json {run.metrics['frames']}"
        return
    pooled = bootstrap.pooled_f1(counts, np.ones((1, len(counts))))
    if any(abs(f1[0] - run.score(*key)) > 1e-9 for key, f1 in pooled.items()):
        run.no_counts = f"{shown(file)} does not pool to the F1 of metrics.json (re-run `cli eval`)"
        return
    run.frame_ids, run.counts = frame_ids, counts


def load_runs(paths: list[Path]) -> list[Run]:
    folders = find_runs(paths)
    names = [p.name for p in folders]
    return [load_run(p, p.name if names.count(p.name) == 1 else f"{p.parent.name}/{p.name}") for p in folders]


def group_blocks(runs: list[Run]) -> list[Block]:
    """One block per (dataset, data folder, split); each block's runs must share the metric parameters."""
    blocks: dict[tuple, Block] = {}
    for run in runs:
        key = (run.dataset, str(run.data or ""), run.split or "")
        blocks.setdefault(key, Block(run.dataset, run.data, run.split, [])).runs.append(run)
    for block in blocks.values():
        check_metric_params(block.scored)
        if block.data is not None:
            block.manifest = read_json(block.data / "manifest.json")
            block.synthetic = is_synthetic(block.manifest)
    return [blocks[key] for key in sorted(blocks)]


def check_metric_params(runs: list[Run]) -> None:
    """Refuse to put runs scored with different metric thresholds in one table."""
    for run in runs[1:]:
        first, this = runs[0].metrics["metric_params"], run.metrics["metric_params"]
        differ = [k for k in sorted(set(first) | set(this)) if first.get(k) != this.get(k)]
        if differ:
            what = "; ".join(f"{k} {this.get(k)} vs {first.get(k)}" for k in differ)
            raise ValueError(
                f"{run.path / 'metrics.json'}: scored with other metric parameters than "
                f"{runs[0].path / 'metrics.json'} ({what}); they cannot share a table: re-run `cli eval` "
                "on one of them or report them apart"
            )


# ---------------------------------------------------------------------------------------------------
# Tables


def percent(value: float | None) -> str:
    return "–" if value is None else f"{100 * value:.1f}"


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join("---" for _ in header) + " |"]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])


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


# ---------------------------------------------------------------------------------------------------
# Round trips (Tab. 10)


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


# ---------------------------------------------------------------------------------------------------
# The paper's tables beside the measured ones (--reference paper)

REFERENCE_LEADS = (("method", "method"), ("modeling", "modeling"), ("via", "representation"),
                   ("modality", "modality"))  # fmt: skip
REFERENCE_EXTRAS = (("params_m", "Params (M)"), ("fps_net", "FPS_net"), ("fps", "FPS"), ("miou", "mIoU"))


def reference_table(table: ReferenceTable, rows: list[dict]) -> tuple[list[str], list[list[str]]]:
    """The paper's rows in the report's own column names and units (scores in %): the columns the table
    has, in Tab. 1's order; the first cell of a row names its source table, schedule and FPS GPU."""
    leads = [(key, title) for key, title in REFERENCE_LEADS if any(key in row for row in rows)]
    if table.field:
        leads.insert(0, ("value", FIELD_NAMES.get(table.field, table.field)))
    scores = [(mode, metric, stat) for mode in MODES for metric in METRICS for stat in STATS
              if any(SCORE_KEYS[mode, metric] in row for row in rows)]  # fmt: skip
    extras = [(key, title) for key, title in REFERENCE_EXTRAS if any(key in row for row in rows)]
    header = ["reference", *(title for _, title in leads)]
    header += [f"{SHORT[mode]} {SHORT[metric]} {SHORT[stat]}" for mode, metric, stat in scores]
    header += [title for _, title in extras]
    body = []
    for row in rows:
        cells = [table.row_label(row)] + [str(row.get(key, "–")) for key, _ in leads]
        for mode, metric, stat in scores:
            values = row.get(SCORE_KEYS[mode, metric])
            cells.append(percent(values[STATS.index(stat)]) if values else "–")
        cells += [f"{row[key]:.1f}" if key in row else "–" for key, _ in extras]
        body.append(cells)
    return header, body


def reference_section(table: ReferenceTable, rows: list[dict], dataset: str | None = None) -> list[str]:
    heading = f"#### Reference: {table.describe(dataset)}"
    return [heading, "", markdown_table(*reference_table(table, rows)), ""]


def console_reference(
    table: ReferenceTable, rows: list[dict], dataset: str
) -> tuple[str, list[str], list[list[str]]]:
    """(title, header, rows) of a reference table for a terminal: a label all rows share goes into the
    title instead of each row."""
    header, body = reference_table(table, rows)
    labels = {row[0] for row in body}
    title = f"Reference: {table.describe(dataset)}"
    if len(labels) == 1:
        label = labels.pop().replace(f"paper `{table.label}`", "paper")
        title = f"Reference ({label}): {table.describe(dataset)}"
        header, body = header[1:], [row[1:] for row in body]
    return title, header, body


def main_references(block: Block, refs: dict[str, ReferenceTable]) -> list[tuple[ReferenceTable, list[dict]]]:
    """The paper's tables that match a block's main table: Tab. 1 at its 30 x 60 m range on the
    dataset's own split, the 50 x 100 m table, the geographic split's table; only rows of its dataset."""
    bev_range, geographic = block.parameters.get("bev_range"), bool(block.parameters.get("split_files"))
    labels = ["tab:perception_range"] if bev_range == "50x100" else []
    labels += ["tab:newsplit"] if geographic else []
    labels += ["tab:modeling"] if bev_range == "30x60" and not geographic else []
    found = [(refs[label], refs[label].rows_of(block.dataset)) for label in labels if label in refs]
    return [(table, rows) for table, rows in found if rows]


def unplaced_references(refs: dict[str, ReferenceTable], placed: set[str]) -> list[str]:
    """A line for each paper table no measured table matched: where it would have been shown."""
    lines = []
    for label, table in refs.items():
        if label in placed:
            continue
        if table.field:
            where = f"beside an ablation of `{table.field}` (runs whose configs differ in that field alone)"
        else:
            where = REFERENCE_PLACES.get(label, "beside a matching measured table")
        lines.append(f"- `{label}`, {table.title}: shown {where}.")
    return lines


# ---------------------------------------------------------------------------------------------------
# Summary and the report


def paired_difference(first: Run, second: Run, draws: int) -> dict | str:
    """{mode: {metric: [low, high]}}: the 95 % interval of first's F1 minus second's from the paired
    bootstrap (same frames, same draws); or why there is none."""
    if draws == 0:
        return "no bootstrap (`--bootstrap 0`)"
    for run in (first, second):
        if run.counts is None:
            return f"{run.name}: {run.no_counts}"
    if first.frame_ids != second.frame_ids:
        return "the two were scored on other frames"
    return bootstrap.paired(first.counts, second.counts, draws)


def summary(blocks: list[Block], draws: int = bootstrap.DRAWS) -> str:
    """One paragraph in words, generated from the numbers. A run "leads" only where the paired interval
    of its difference to the next run excludes 0; where it holds 0 the two are "level"."""
    sentences = []
    for block in blocks:
        synthetic = "synthetic " if block.synthetic else ""
        scored, where = block.scored, f"On {synthetic}{block.dataset} ({block.split or '?'} split)"
        unscored = [run.name for run in block.runs if not run.scored]
        if not scored:
            sentences.append(
                f"{where} no run has scores yet ({', '.join(unscored)}: see the reasons in its table)."
            )
            continue
        if len(scored) == 1:
            run = scored[0]
            sentences.append(
                f"{where} the one scored run, {run.name} ({run.method}, {run.modality}), reaches directed "
                f"TOPO F1 {run.f1_text('directed', 'topo')} and directed Junction TOPO F1 "
                f"{run.f1_text('directed', 'junction_topo')}."
            )
        else:
            leads: dict[str, list[str]] = {}
            differences: dict[tuple[int, int], dict | str] = {}
            for mode, metric in F1_COLUMNS:
                ranked = sorted(scored, key=lambda r: -r.score(mode, metric))
                first, second = ranked[0], ranked[1]
                a, b = first.score(mode, metric), second.score(mode, metric)
                name = f"{mode} {'Junction TOPO' if metric == 'junction_topo' else 'TOPO'} F1"
                if a == b:
                    leads.setdefault(f"{first.name} and {second.name} tie", []).append(
                        f"{name} ({percent(a)} %)"
                    )
                    continue
                pair = (id(first), id(second))
                if pair not in differences:
                    differences[pair] = paired_difference(first, second, draws)
                lead, difference = f"{100 * (a - b):+.1f} points", differences[pair]
                if isinstance(difference, str):
                    text = f"{name} ({percent(a)} % vs {percent(b)} %, {lead}; not tested: {difference})"
                    leads.setdefault(f"{first.name} is ahead of {second.name}", []).append(text)
                    continue
                low, high = (100 * v for v in difference[mode][metric])
                interval = f"[{low:+.1f}, {high:+.1f}]"
                if low > 0:
                    text = (f"{name} ({percent(a)} % vs {percent(b)} % for {second.name}, {lead}, 95 % "
                            f"interval of the difference {interval})")  # fmt: skip
                    leads.setdefault(f"{first.name} leads", []).append(text)
                else:
                    text = (f"{name} ({percent(a)} % vs {percent(b)} %: the 95 % interval of the difference, "
                            f"{interval} points, holds 0)")  # fmt: skip
                    leads.setdefault(f"{first.name} is level with {second.name}", []).append(text)
            parts = [f"{who} on {', '.join(items)}" for who, items in leads.items()]
            sentences.append(f"{where} " + "; ".join(parts) + ".")
        for run in scored:
            floor = run.floor_f1("directed", "topo")
            if floor is not None:
                margin = run.score("directed", "topo") - floor
                side = "above" if margin > 0 else "below" if margin < 0 else "level with"
                sentences.append(
                    f"{run.name} is {abs(100 * margin):.1f} points {side} its sensor-blind floor on directed "
                    f"TOPO F1 ({percent(floor)} %)."
                )
        if unscored:
            sentences.append(f"{len(unscored)} run(s) have no scores: {', '.join(unscored)}.")
    return " ".join(sentences)


@dataclass
class Report:
    path: Path  # report.md
    blocks: list[Block]
    pictures: list[Path]
    grids: dict[str, tuple[int, int]]  # picture file name -> (rows, columns) of its panel grid
    # per block (in blocks' order): the paper's tables beside its main table, (heading, header, rows)
    references: list[list[tuple[str, list[str], list[list[str]]]]] = field(default_factory=list)


@dataclass
class Sections:
    """What the section builders share besides the lines they return: where the pictures go, the paper's
    tables (refs), and what they wrote and placed."""

    out: Path
    refs: dict[str, ReferenceTable]
    workers: int
    pictures: list[Path] = field(default_factory=list)
    grids: dict[str, tuple[int, int]] = field(default_factory=dict)
    placed: set[str] = field(default_factory=set)  # labels of the paper's tables shown
    shown_references: list[list[tuple[str, list[str], list[list[str]]]]] = field(default_factory=list)

    def picture(self, figure, name: str) -> None:
        self.pictures.append(figures.save_png(figure, self.out / name))


def introduction(blocks: list[Block], draws: int, doc: Sections) -> list[str]:
    """The title, the summary and how to read the tables."""
    md = ["# Lane-graph report", "", summary(blocks, draws), ""]
    md += [
        "Scores are in % (precision P, recall R, F1) of the TOPO and Junction TOPO metrics "
        "(docs/METRICS.md), directed (dir) and undirected (undir), as `cli eval` wrote them in each run's "
        "metrics.json. Params in millions, GFLOPs per frame (torch's FLOP counter), FPS_net: the network "
        "alone, FPS: with post-processing. Bold: the best F1 of a column among the runs of a block "
        "(none when all tie).",
        "",
    ]
    if any(run.external is not None for block in blocks for run in block.scored):
        md += [EXTERNAL_NOTE, ""]
    if draws:
        md += [
            "[low, high] beside a run's F1: its 95 % interval, a bootstrap over the block's frames "
            f"({draws} draws of the frames with replacement, seed {bootstrap.SEED}, the matched counts "
            "pooled again; benchmark/bootstrap.py). The summary's leads use the paired interval of two "
            "runs' difference (same frames, same draws).",
            "",
        ]
    if doc.refs:
        md += [REFERENCE_NOTE, ""]
    md += [
        f"Paths are relative to the folder `cli report` ran in (`{shown(doc.out)}` holds this report).",
        "",
    ]
    return md


def main_section(block: Block, beside: list[tuple[ReferenceTable, list[dict]]], doc: Sections) -> list[str]:
    """A block's heading, main table, the paper's tables beside it, the floor, its settings and data."""
    refs = doc.refs
    md = [f"## {block.title}", "", "### Main table (paper Tab. 1)", ""]
    md += [markdown_table(*main_table(block)), ""]
    md += [f"- {run.name}: no F1 intervals: {run.no_counts}." for run in block.scored if run.no_counts]
    md += [""] if any(run.no_counts for run in block.scored) else []
    md += [f"- {note}" for note in external_notes(block)]
    md += [""] if any(run.external is not None for run in block.scored) else []
    doc.shown_references.append([])
    if refs:
        if block.synthetic:
            md += [SYNTHETIC_NOTE, ""]
        elif block.synthetic is None:
            md += [UNKNOWN_ORIGIN_NOTE, ""]
        if not beside:
            where = f"{block.dataset} at range {block.parameters.get('bev_range', '?')}"
            where += ", prepared with --split-file" if block.parameters.get("split_files") else ""
            md += [f"No table of the paper matches this block ({where}).", ""]
    for table, rows in beside:
        md += reference_section(table, rows, block.dataset)
        doc.shown_references[-1].append(console_reference(table, rows, block.dataset))
        doc.placed.add(table.label)
    md += [FLOOR_NOTE, ""]
    md += [f"- {note}" for note in floor_notes(block)] + [""]
    md += [markdown_table(*settings_table(block)), ""]
    params_text = params_line(block.metric_params) if block.metric_params else "–"
    data_text = shown(block.data) if block.data else "not found"
    md += [
        f"Data: `{data_text}`, split {block.split}. Metric parameters (every run of it): {params_text}.",
        "",
    ]
    return md


def miou_section(block: Block, beside: list[tuple[ReferenceTable, list[dict]]], doc: Sections) -> list[str]:
    """mIoU (paper Tab. 9), with the paper's tab:iou where the main table has the modeling table beside."""
    refs = doc.refs
    md = ["### mIoU (paper Tab. 9)", "", markdown_table(*miou_table(block)), ""]
    if any(table.label == "tab:modeling" for table, _ in beside) and "tab:iou" in refs:
        md += reference_section(refs["tab:iou"], refs["tab:iou"].rows_of(block.dataset), block.dataset)
        doc.placed.add("tab:iou")
    return md


def ablation_sections(block: Block, doc: Sections) -> list[str]:
    """One table per config field that the block's runs differ in alone, the paper's beside."""
    md = []
    for name, members in ablations(block):
        md += [f"### Ablation: {FIELD_NAMES.get(name, name)} (`{name}`)", ""]
        md += ["Runs whose saved configs differ in this field alone.", ""]
        md += [markdown_table(*ablation_table(name, members)), ""]
        for table in doc.refs.values():
            if table.field == name:
                md += reference_section(table, table.rows)
                doc.placed.add(table.label)
    return md


def junction_sections(block: Block, slug: str, doc: Sections) -> list[str]:
    """Scores by junction count and the grid of frames, from the runs' predictions (none without)."""
    gt, predictions, notes = block_graphs(block)
    md = [f"- {note}" for note in notes]
    params = MetricParams(**block.metric_params)
    counts = {f: junction_count(g, params.step) for f, g in gt.items()}
    if predictions:
        md += ["### Scores by junction count", ""]
        md += ["Computed here, not read from metrics.json: each run's predictions.parquet scored with "
               "the project's metric (parameters above) on the frames of each bucket. "
               + JUNCTION_DEFINITION, ""]  # fmt: skip
        external = {
            run.name: run for run in block.scored if run.external is not None and run.name in predictions
        }
        table = junction_table(gt, predictions, counts, params, doc.workers, frozenset(external))
        md += [markdown_table(*table), ""]
        fewer = [(name, len(predictions[name])) for name in external if len(predictions[name]) < len(gt)]
        md += [f"- {name}: scored on the {n} frames of its result file alone (of the {len(gt)} here); a "
               "bucket's F1 of it is over those, and a frame not in its file is drawn empty in the grid."
               for name, n in fewer]  # fmt: skip
        md += [""] if fewer else []
        frames = grid_frames(counts, gt)
        columns = [("ground truth", gt)] + list(predictions.items())
        labels = [(f, f"{short_id(f)} ({counts[f]} junctions)") for f in frames]
        grid = f"grid_{slug}.png"
        doc.picture(figures.frame_grid(labels, columns, Range.parse(params.bev_range)), grid)
        doc.grids[grid] = (len(frames), len(columns))
        md += ["### Frames", "", f"![ground truth and predictions]({grid})", ""]
        rows_text = ", ".join(f"`{f}`" for f in frames)
        md += [f"Rows: {rows_text}. Columns: ground truth, {', '.join(predictions)}. " + GRID_NOTE, ""]
    return md


def f1_section(block: Block, slug: str, doc: Sections) -> list[str]:
    """Each run's F1 beside its floor, as bars."""
    names = [run.name for run in block.scored]
    values = np.array([[100 * run.score(m, k) for m, k in F1_COLUMNS] for run in block.scored])
    floors = np.array([[np.nan if run.floor_f1(m, k) is None else 100 * run.floor_f1(m, k)
                        for m, k in F1_COLUMNS] for run in block.scored])  # fmt: skip
    labels = [f"{SHORT[m]} {SHORT[k]} F1" for m, k in F1_COLUMNS]
    bars = f"f1_{slug}.png"
    doc.picture(figures.f1_bars(names, labels, values, floors), bars)
    return ["### F1 by run", "", f"![F1 by run]({bars})", ""]


def block_sections(index: int, block: Block, doc: Sections) -> list[str]:
    """Everything of one block (a dataset, range and split): its tables and pictures."""
    slug = f"{index}_{block.dataset}"
    beside = main_references(block, doc.refs) if doc.refs else []
    md = main_section(block, beside, doc)
    if not block.scored:
        return md
    md += miou_section(block, beside, doc)
    md += ablation_sections(block, doc)
    if block.data is None:
        return md + ["The data folder was not found: no scores by junction count and no frame grid.", ""]
    md += junction_sections(block, slug, doc)
    return md + f1_section(block, slug, doc)


def roundtrip_section(
    trip_tables: list[tuple[str, list[str], list[list[str]], dict]], doc: Sections
) -> list[str]:
    """Post-processing accuracy (paper Tab. 10): the round trips, the paper's beside."""
    if not trip_tables:
        return []
    md = ["## Post-processing accuracy (paper Tab. 10)", ""]
    md += [
        "The ground truth through each representation and back (`cli roundtrip`), scored against itself.",
        "",
    ]
    for title, header, rows, params in trip_tables:
        md += [
            f"### {title}",
            "",
            markdown_table(header, rows),
            "",
            f"Metric parameters: {params_line(params)}.",
            "",
        ]
    if "tab:postproc" in doc.refs:
        md += reference_section(doc.refs["tab:postproc"], doc.refs["tab:postproc"].rows)
        doc.placed.add("tab:postproc")
    return md


def unplaced_section(doc: Sections) -> list[str]:
    """The paper's tables that no measured table matched."""
    unplaced = unplaced_references(doc.refs, doc.placed)
    if not unplaced:
        return []
    note = "No measured table here matches these; each is shown when one does."
    return ["## The paper's tables not shown", "", note, "", *unplaced, ""]


def finite(value) -> bool:
    """A number that a curve can hold: not None, NaN or infinite."""
    return isinstance(value, int | float) and math.isfinite(value)


def loss_points(run: Run) -> tuple[np.ndarray, np.ndarray, int]:
    """(steps, losses) of a run's logged steps, and how many were left out: a step the non-finite guard
    skipped ("skipped") or any non-finite loss would cut the curve and spoil its scale."""
    logged = [e for e in run.log if "step" in e and e.get("loss") is not None]
    kept = [e for e in logged if "skipped" not in e and finite(e["loss"])]
    steps = np.array([e["step"] for e in kept], np.int64)
    return steps, np.array([e["loss"] for e in kept], np.float64), len(logged) - len(kept)


def loss_section(blocks: list[Block], doc: Sections) -> list[str]:
    """Every run's training loss by step, from its log.jsonl."""
    curves, left_out = {}, {}
    for block in blocks:
        for run in block.runs:
            steps, losses, skipped = loss_points(run)
            if len(steps):
                curves[run.name] = (steps, losses)
            if skipped:
                left_out[run.name] = skipped
    md = ["## Training loss", ""]
    if not curves:
        return md + ["No run has a log.jsonl with losses.", ""]
    doc.picture(figures.loss_curves(curves), "loss.png")
    md += ["![training loss](loss.png)", "", "From each run's log.jsonl (one point per logged step).", ""]
    if left_out:
        runs = ", ".join(f"{name} {count}" for name, count in left_out.items())
        md += [f"Left out: logged steps skipped by the non-finite guard or with a non-finite loss ({runs}).",
               ""]  # fmt: skip
    cut = [run.name for block in blocks for run in block.runs if "log.jsonl" in run.cut]
    if cut:
        md += [f"The last line of log.jsonl was cut short (a kill mid-write), left out: {', '.join(cut)}.",
               ""]  # fmt: skip
    return md


def validation_curve(run: Run) -> figures.ValidationCurve:
    """A run's val.jsonl as the picture draws it: each panel's key in % by step, the best constant in
    hindsight of its metrics.json, and its best checkpoint (run.json "best") where it is a panel's."""
    points, constants = {}, {}
    for key, mode, metric in VALIDATION_PANELS:
        kept = [r for r in run.validation or [] if "step" in r and finite(r.get(key))]
        if kept:
            points[key] = (np.array([r["step"] for r in kept]), 100 * np.array([r[key] for r in kept]))
        constant = ((run.metrics or {}).get("floor") or {}).get("best_constant")
        if constant:
            constants[key] = 100 * constant[mode][metric]["f1"]
    best = run.info.get("best")
    marked = None
    if best and best.get("metric") in points:
        marked = (best["metric"], best["step"], 100 * best["value"])
    return figures.ValidationCurve(run.name, points, constants, marked)


def validation_line(run: Run) -> str:
    """One line per run: what its val.jsonl holds, its best checkpoint and its best constant."""
    if run.validation is None:
        why = "an external run, not trained here" if run.external is not None else "no validation recorded"
        text = f"{run.name}: no {VALIDATION_FILE} ({why})"
    elif not run.validation:
        text = f"{run.name}: {VALIDATION_FILE} holds no complete line"
    else:
        steps = [r["step"] for r in run.validation if "step" in r]
        frames = sorted({r["frames"] for r in run.validation if "frames" in r})
        text = f"{run.name}: {len(run.validation)} validation(s)"
        if steps:
            text += f", step {steps[0]}" if min(steps) == max(steps) else f", steps {min(steps)}-{max(steps)}"
        if frames:
            text += f", on {frames[0] if len(frames) == 1 else f'{frames[0]}-{frames[-1]}'} frames"
    if VALIDATION_FILE in run.cut:
        text += "; its last line was cut short (a kill mid-write) and left out"
    best = run.info.get("best")
    if best:
        name = VALIDATION_NAMES.get(best.get("metric"), best.get("metric"))
        kept = "kept as best.pt" if (run.path / "best.pt").is_file() else "its best.pt is missing"
        text += (f"; best {name} {percent(best.get('value'))} % at step {best.get('step', '?')} "
                 f"(epoch {best.get('epoch', '?')}), {kept}")  # fmt: skip
    constant = ((run.metrics or {}).get("floor") or {}).get("best_constant")
    if constant and run.validation:
        known = [f"{VALIDATION_NAMES[key]} {percent(constant[mode][metric]['f1'])} %"
                 for key, mode, metric in VALIDATION_PANELS]  # fmt: skip
        text += f"; best constant (hindsight): {', '.join(known)}"
    return text + "."


def validation_section(blocks: list[Block], doc: Sections) -> list[str]:
    """Every run's validation F1 during training by step, from its val.jsonl, a line per run."""
    runs = [run for block in blocks for run in block.runs]
    curves = [validation_curve(run) for run in runs if run.validation]
    md = ["## Validation during training", ""]
    if any(curve.points for curve in curves):
        panels = [(key, VALIDATION_NAMES[key]) for key, _, _ in VALIDATION_PANELS]
        doc.picture(figures.validation_curves(panels, curves), "validation.png")
        md += ["![validation F1 during training](validation.png)", "", VALIDATION_NOTE, ""]
    return md + [f"- {validation_line(run)}" for run in runs] + [""]


def write_report(
    runs: list[Path], out: Path, roundtrips: list[Path] = (), workers: int = 1, reference: str | None = None,
    draws: int = bootstrap.DRAWS,
) -> Report:  # fmt: skip
    """Write out/report.md and the PNGs it links; returns what was written. `reference="paper"` places
    the paper's tables beside the measured ones; `draws`: bootstrap draws of the intervals (0: none)."""
    out = Path(out)
    bootstrap.check_draws(draws)
    refs = load_reference(reference) if reference else {}
    blocks = group_blocks(load_runs(runs))
    trip_tables = roundtrip_tables(load_roundtrips(list(roundtrips)))  # checked before anything is written
    for block in blocks:
        for run in block.scored:
            if draws and run.counts is not None:
                run.intervals = bootstrap.intervals(run.counts, draws)
    out.mkdir(parents=True, exist_ok=True)
    doc = Sections(out, refs, workers)
    md = introduction(blocks, draws, doc)
    for index, block in enumerate(blocks, 1):
        md += block_sections(index, block, doc)
    md += roundtrip_section(trip_tables, doc)
    md += unplaced_section(doc)
    md += loss_section(blocks, doc)
    md += validation_section(blocks, doc)
    text = "\n".join(md).rstrip() + "\n"
    path = out / "report.md"
    write_atomic(path, lambda tmp: tmp.write_text(text))
    return Report(path, blocks, doc.pictures, doc.grids, doc.shown_references)
