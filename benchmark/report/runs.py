"""The runs `cli report` reads: run folders (metrics.json, config.json, run.json, log.jsonl, val.jsonl and
frame_counts.parquet) as typed rows (Run), grouped in blocks of one prepared dataset and split (Block), each
with the split its data was prepared on (DataSplit, read from the data's manifest.json).

A missing or unusable file becomes a reason why a run has no scores, never an exception; a run's per-frame
counts are checked against its metrics.json before they give intervals. Paths are shown relative to the
working directory (`shown`).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from enum import Enum
from functools import cached_property
from pathlib import Path

import numpy as np

from benchmark.metric import bootstrap
from pipeline.geometry import Range
from pipeline.splits.plan import split_file_digests, split_names_digest

METHOD_NAMES = {"lanegap": "LaneGAP", "maptr": "MapTR", "stsu": "STSU", "hdmapnet": "HDMapNet"}
# files that mark a folder as one run folder (else it is a folder of runs); a run folder holds more
RUN_MARKERS = ("metrics.json", "config.json", "run.json", "checkpoint.pt", "log.jsonl", "predictions.parquet")
REQUIRED = ("frames", "directed", "undirected", "metric_params", "params", "fps_net", "fps", "split", "data")
MEASURED = ("params", "fps_net", "fps")  # null only in an external run's metrics.json (not measured here)
# an external run (`cli score --out RUN_DIR`: another codebase's result file, metrics.json's "external")
EXTERNAL_NAMES = {"maptrv2": "MapTRv2 / LaneGAP JSON", "cgnet": "CGNet JSON", "graph": "graph table",
                  "openlanev2": "OpenLane-V2 submission"}  # fmt: skip
VALIDATION_FILE = "val.jsonl"
# the raw roots that `cli synth` writes, as its marker (pipeline.synth.MARKER) names them
SYNTH_ROOTS = ("av2_root", "nuscenes_root", "openlanev2_root")
# StreamMapNet's geographically disjoint splits (Yuan et al., WACV 2024), the paper's new split: sha256 of
# each file's names, sorted and joined by newlines (`split_names_digest`), so that a copy in another order
# or with comments is told as theirs; from nusc_split.py and av2_{train,val}_split.txt of their repository
STREAMMAPNET_SPLITS = {
    "nuscenes": {"train": "65debcbfbdd34790cb94124df5d4e4c84740c77fee4c7db01d90dcf206f0f604",
                 "val": "e78fa0fa52cd1f26dd6924d83d276d46c90c8b79ca4ee8dd4f1624e7ba61421a"},
    "av2": {"train": "d8082f9cc2bd861da8307eedda002db5e4919e513578625defe62c0fd1ca993b",
            "val": "0f77c8be5baf5349a2521bda1e0926f7ff538b888838b9663e9bf9a514bcf681"},
}  # fmt: skip


class SplitKind(Enum):
    """Which split a prepared dataset's frames are in (`cli prepare`), in the order the report shows
    blocks: the paper's tables beside a block depend on it (benchmark/report/paper_tables.py)."""

    ORIGINAL = "the dataset's own split"
    STREAMMAPNET = "StreamMapNet's geographically disjoint split"  # the paper's new split (tab:newsplit)
    GEOGRAPHIC = "the geographic scheme"  # --split-scheme geographic
    SPLIT_FILES = "your split files"  # --split-file naming other splits than StreamMapNet's
    # --split-file, in a manifest from before the names' digest was recorded, whose files are gone or
    # changed: whose split it is cannot be told
    UNSURE_FILES = "split files of unknown provenance"
    UNKNOWN = "an unknown split"  # the data (its manifest.json) is not found


@dataclass(frozen=True)
class DataSplit:
    """The split a prepared dataset was made with, as its manifest.json records it: the kind, the split
    files (split -> file, as `cli prepare` resolved them) and the geographic scheme's cell, buffer, seed."""

    kind: SplitKind
    files: dict[str, Path] = field(default_factory=dict)
    # UNSURE_FILES: the split files gone or changed since `cli prepare`, in words
    unsure: tuple[str, ...] = ()
    geographic: tuple[float, float, int] | None = None  # cell and buffer in metres, seed

    @classmethod
    def of(cls, manifest: dict) -> DataSplit:
        """Read from a manifest (`cli prepare`'s parameters); {} (data not found) gives UNKNOWN. A manifest
        written before the split scheme was recorded is on the original scheme, as `cli prepare` reads it.
        Split files are told by the digest of their names that `cli prepare` recorded
        (split_file_names_sha256), wherever the files are now; a manifest from before that has only the
        files themselves, read if they are here as prepared, and is UNSURE_FILES if not."""
        if not manifest:
            return cls(SplitKind.UNKNOWN)
        parameters = manifest.get("parameters", {})
        if parameters.get("split_scheme", "original") == "geographic":
            scheme = (parameters.get("geo_cell"), parameters.get("geo_buffer"), parameters.get("geo_seed"))
            return cls(SplitKind.GEOGRAPHIC, geographic=scheme)
        files = {split: Path(path) for split, path in (parameters.get("split_files") or {}).items()}
        if not files:
            return cls(SplitKind.ORIGINAL)
        theirs = STREAMMAPNET_SPLITS.get(manifest.get("dataset"), {})
        names = parameters.get("split_file_names_sha256")
        if names is None:  # an earlier manifest: the files, if they are those it was prepared from
            unsure = unsure_files(files, parameters.get("split_file_sha256") or {})
            if unsure:
                return cls(SplitKind.UNSURE_FILES, files, unsure)
            names = {split: split_names_digest(path) for split, path in files.items()}
        kind = SplitKind.STREAMMAPNET if names == theirs else SplitKind.SPLIT_FILES
        return cls(kind, files)

    def describe(self) -> str:
        """The split in words, with the option that made it: "the geographic scheme (`--split-scheme
        geographic`, 100 m cells, 30 m buffer, seed 0)", "your split files (`--split-file` train=a.txt)"."""
        if self.kind is SplitKind.GEOGRAPHIC:
            cell, buffer, seed = self.geographic
            return (f"{self.kind.value} (`--split-scheme geographic`, {metres(cell)} cells, "
                    f"{metres(buffer)} buffer, seed {seed if seed is not None else '?'})")  # fmt: skip
        if self.files:
            named = ", ".join(f"{split}={path.name}" for split, path in self.files.items())
            unsure = (
                f"; {', '.join(self.unsure)}, and manifest.json, from an earlier version, records no digest "
                "of their names"
                if self.unsure
                else ""
            )
            return f"{self.kind.value} (`--split-file` {named}{unsure})"
        return self.kind.value


def unsure_files(files: dict[str, Path], recorded: dict[str, str]) -> tuple[str, ...]:
    """The split files gone or changed since `cli prepare` recorded their sha256 (`recorded`, {split:
    sha256}; a manifest from before those has none, and its files are taken as they are), in words."""
    unsure = []
    for split, path in files.items():
        if not path.is_file():
            unsure.append(f"{path.name} not found")
        elif split in recorded and split_file_digests({split: path})[split] != recorded[split]:
            unsure.append(f"{path.name} changed since `cli prepare`")
    return tuple(unsure)


def metres(value: float | None) -> str:
    """A length as a heading names it: "100 m", "67.1 m"."""
    return "? m" if value is None else f"{round(value, 1):g} m"


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
            named = f" `{self.external['method']}`" if self.external.get("method") else ""  # a submission's
            return f"{EXTERNAL_NAMES.get(fmt, fmt)}{named} (external)"
        model = (self.metrics or {}).get("model") or (self.config or {}).get("model") or "?"
        return METHOD_NAMES.get(model, model)

    @property
    def modality(self) -> str:
        if self.external is not None:
            return "unknown"
        return (self.config or {}).get("encoder", {}).get("modality", "-")

    @property
    def bev_range(self) -> str | None:
        """The range its scores were measured at (metrics.json's metric parameters, WIDTHxLENGTH m); None
        without scores; spelt as Range.text, as cli prepare writes it (cli score kept --range as typed)."""
        text = ((self.metrics or {}).get("metric_params") or {}).get("bev_range")
        try:
            return None if text is None else Range.parse(text).text
        except ValueError:
            return text

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
    def key(self) -> tuple[str, str, str]:
        return self.dataset, str(self.data or ""), self.split or ""

    @cached_property
    def data_split(self) -> DataSplit:
        """The split its data was prepared on (read once its manifest is): where the report shows the
        block, and the paper's tables beside it."""
        return DataSplit.of(self.manifest)

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
        return f"{self.name}: `{data}`, {self.split_words}{frames}"

    @property
    def split_words(self) -> str:
        """The block's split in words: "val split", or "val split of the geographic scheme (...)" where the
        data is not on the dataset's own split."""
        of = self.data_split.kind not in (SplitKind.ORIGINAL, SplitKind.UNKNOWN)
        return f"{self.split or '?'} split" + (f" of {self.data_split.describe()}" if of else "")


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
        if any((path / name).exists() for name in RUN_MARKERS):
            found.append(path)
            continue
        inner = sorted(p for p in path.iterdir() if p.is_dir() and not p.name.startswith("."))
        if not inner:
            raise ValueError(
                f"{path}: neither a run folder (no {', '.join(RUN_MARKERS[:3])}) nor a folder of runs"
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
            roots = [marker.get(key) for key in SYNTH_ROOTS]
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
    """One block per (dataset, data folder, split); each block's runs must share the metric parameters.
    Blocks on the datasets' own splits come first, then those of each other split (SplitKind's order)."""
    blocks: dict[tuple, Block] = {}
    for run in runs:
        key = (run.dataset, str(run.data or ""), run.split or "")  # Block.key
        blocks.setdefault(key, Block(run.dataset, run.data, run.split, [])).runs.append(run)
    for block in blocks.values():
        check_metric_params(block.scored)
        if block.data is not None:
            block.manifest = read_json(block.data / "manifest.json")
            block.synthetic = is_synthetic(block.manifest)
    kinds = list(SplitKind)
    return sorted(blocks.values(), key=lambda block: (kinds.index(block.data_split.kind), block.key))


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


def percent(value: float | None) -> str:
    return "–" if value is None else f"{100 * value:.1f}"
