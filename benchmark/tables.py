"""The rich tables that the commands of cli.py print, one function per command, from the plain results
(dicts, the report) those commands get; with the notes that go under a table. Also how a command ends:
its result (finish), bad input's one line (reported_errors), and `cli --version`'s line."""

from __future__ import annotations

import json
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import typer
from rich.console import Console
from rich.table import Table
from rich.text import Text

from benchmark.metric.table import ALWAYS, console_tables

if TYPE_CHECKING:
    from pathlib import Path

    from benchmark.metric.table import Metric
    from benchmark.report.writer import Report


@dataclass
class Printout:
    """What a command prints above the paths it wrote: its tables, each under its heading, and the notes
    under them."""

    tables: list[tuple[str, Table]]
    notes: list[str] = field(default_factory=list)


MODES = ("directed", "undirected")
METRICS = (("TOPO", "topo"), ("Junction TOPO", "junction_topo"))  # (shown name, result key)


def number(value) -> str:
    """A float with two decimals, anything else as it is."""
    return f"{value:.2f}" if isinstance(value, float) else str(value)


def synth_tables(summary: dict) -> Printout:
    """`cli synth`'s logs under a heading naming the seed and each world's nuScenes map."""
    from pipeline.synth import summary_table

    worlds = ", ".join(f"{world['index']} {world['nuscenes_map']}" for world in summary["worlds"])
    return Printout([(f"synth, seed {summary['seed']}: worlds {worlds}", summary_table(summary))])


def prepare_tables(summary: dict, dataset: str, root: Path, split_scheme: str) -> Printout:
    """`cli prepare`'s tables: its summary, the geographic split's shares where it made one and the leakage
    where there are splits besides training; with the leakage's line under them."""
    from pipeline.splits.leakage import leakage_line

    tables = [(f"prepared {dataset} from {root}", prepare_table(summary))]
    leakage = summary["leakage"]
    if "split_shares" in summary:
        tables.append(("geographic split: shares of the kept frames (target)",
                       split_shares_table(summary["split_shares"])))  # fmt: skip
    if leakage["splits"]:
        tables.append(("leakage: each frame's distance to the nearest training frame of its city, and its "
                       "window's overlap with theirs", leakage_table(leakage)))  # fmt: skip
    return Printout(tables, [leakage_line(leakage, split_scheme)])


def prepare_table(summary: dict) -> Table:
    """`cli prepare`'s summary: frames, the per-frame counts, what the split files or the split scheme left
    out (where they did) and the speed."""
    table = Table("quantity", "value")
    keys = ("frames", "frames_skipped", "frames_without_images", "paths_per_frame", "pieces_per_frame",
            "junctions_per_frame", "path_cap_hits", "logs_already_done", "logs_in_no_split_file",
            "frames_in_no_split_file", "split_file_lines_naming_nothing_here", "split_file_lines_unmatched",
            "frames_in_buffer", "frames_per_second")  # fmt: skip
    for key in keys:
        if key in summary:
            value = summary[key]
            table.add_row(key.replace("_", " "), number(len(value) if isinstance(value, list) else value))
    return table


def leakage_table(leakage: dict) -> Table:
    """Each non-training split's distance from its frames to the nearest training frame of the same city,
    the share of its windows that overlap a training window and the mean share of a window they cover
    (pipeline/splits/leakage.py), per split and city."""
    range_m = leakage["range_m"]
    table = Table("split", "city", "frames", "within 5 m", f"within {range_m:g} m", "median m",
                  "windows overlapping", "area covered")  # fmt: skip
    for split, row in leakage["splits"].items():
        for city, values in [("all", row), *row["cities"].items()]:
            median = "-" if values["median_m"] is None else f"{values['median_m']:.1f}"
            shares = [f"{100 * values[key]:.1f} %" for key in ("within_5m", "within_range")]
            windows = [f"{100 * values[key]:.1f} %" for key in ("overlapping", "covered")]
            table.add_row(split, city, str(values["frames"]), *shares, median, *windows)
    return table


def split_shares_table(shares: dict) -> Table:
    """The geographic scheme's achieved shares (GeoSplit.achieved): per city and in all, the kept and
    left-out frames and each split's share of the kept ones, the target beside the whole's."""
    names = list(shares["targets"])
    table = Table("city", "frames kept", "left out", *names)
    cities = shares["cities"].values()
    kept, left_out = sum(c["frames"] for c in cities), sum(c["left_out"] for c in cities)
    whole = [f"{100 * shares['shares'][n]:.1f} % ({100 * shares['targets'][n]:.1f} %)" for n in names]
    table.add_row("all", str(kept), str(left_out), *whole)
    for city, values in shares["cities"].items():
        table.add_row(city, str(values["frames"]), str(values["left_out"]),
                      *(f"{100 * values['shares'][n]:.1f} %" for n in names))  # fmt: skip
    return table


def train_table(summary: dict) -> Table:
    """`cli train`'s summary: steps (and those skipped as not finite), final loss, speed, and the best
    validation (best.pt) where the run validated."""
    table = Table("steps", "skipped", "final loss", "train seconds", "samples/s")
    row = [str(summary["steps"]), str(summary.get("skipped_steps", 0)), f"{summary['final_loss']:.4f}",
           f"{summary['train_seconds']:.1f}", f"{summary['samples_per_s']:.2f}"]  # fmt: skip
    best = summary.get("best")
    if best:
        table.add_column("best (best.pt)")
        row.append(f"{best['metric']} {best['value']:.3f} at epoch {best['epoch']}")
    table.add_row(*row)
    return table


def train_tables(title: str, summary: dict) -> Printout:
    """`cli train`'s summary under the title of what was trained on what."""
    return Printout([(title, train_table(summary))])


def cell(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def eval_table(metrics: dict) -> tuple[Table, list[str]]:
    """`cli eval`'s metrics: each F1 (with its interval, and the sensor-blind floor and margin when
    scored), directed TOPO precision and recall, the model's size and speed; with the floor's notes."""
    blind, drawn = metrics.get("floor"), metrics.get("bootstrap")
    table = Table("metric", "model")
    if drawn:
        table.add_column("95 % interval")
    for title in ("other log's sensors", "constant prior", "floor", "margin") if blind else ():
        table.add_column(title)
    for mode in MODES:
        for name, metric in METRICS:
            row = [f"{mode} {name} F1", cell(metrics[mode][metric]["f1"])]
            row += ["{:.3f}-{:.3f}".format(*metrics[mode][metric]["f1_ci"])] if drawn else []
            if blind:
                baselines = (blind["other_log_sensors"], blind["constant_prior"])
                row += [cell(b[mode][metric]["f1"] if b else None) for b in baselines]
                row += [cell(blind[key][mode][metric] if blind[key] else None) for key in ("f1", "margin")]
            table.add_row(*row)
    for name in ("precision", "recall"):
        table.add_row(f"directed TOPO {name}", cell(metrics["directed"]["topo"][name]))
    for name in ("model", "modeling", "params", "gflops", "fps_net", "fps", "postprocess_ms", "device"):
        table.add_row(name, number(metrics[name]))
    notes = [
        f"fps: batch 1 on {metrics['device']} in {metrics.get('precision', 'fp32')} (the paper's FPS: fp32 "
        "on one RTX 3090)"
    ]
    if blind and blind["constant_prior"]:
        prior = blind["constant_prior"]
        notes.append(f"constant prior: the ground truth of {prior['frame_id']} ({prior['split']} split)")
    notes += [f"floor without {name}: {reason}" for name, reason in (blind or {}).get("absent", {}).items()]
    return table, notes


def eval_tables(run: Path, result: dict, metrics: tuple[Metric, ...]) -> Printout:
    """`cli eval`'s tables: its metrics under a heading naming the run, split, data and frames, then the
    other metrics' tables; with their notes (on OpenLane-V2 data, the submission written among them)."""
    table, notes = eval_table(result)
    if "submission" in result:  # OpenLane-V2 data: the predictions in its submission format too
        submission = result["submission"]
        notes.append(f"{submission['path']}: {submission['frames']} frames in OpenLane-V2's submission "
                     f"format; {submission['confidence']}")  # fmt: skip
    others, other_notes = console_tables(metrics, result)
    heading = f"{run} on {result['split']} of {result['data']}: {result['frames']} frames"
    return Printout([(heading, table), *others], notes + other_notes)


def score_table(result: dict) -> tuple[Table, list[str]]:
    """A score result (`cli score`, `cli roundtrip`) as P / R / F1 (and its bootstrap interval) and mIoU,
    with its notes."""
    drawn = result.get("bootstrap")
    table = Table(*(("metric", "precision", "recall", "F1") + (("F1 interval",) if drawn else ())))
    for mode in MODES:
        for name, metric in METRICS:
            values = result[mode][metric]
            cells = [f"{values[k]:.3f}" for k in ("precision", "recall", "f1")]
            cells += ["{:.3f}-{:.3f}".format(*values["f1_ci"])] if drawn else []
            table.add_row(f"{mode} {name}", *cells)
    table.add_row("mIoU", "", "", f"{result['miou']:.3f}")
    notes = [f"metric_version {result['metric_version']}"]
    if drawn:
        notes.append(f"F1 interval: the 95 % interval of a bootstrap of {drawn['draws']} draws over the "
                     f"frames (seed {drawn['seed']})")  # fmt: skip
    return table, notes


def score_tables(pred: Path, gt: Path, result: dict, metrics: tuple[Metric, ...]) -> Printout:
    """`cli score`'s tables: LaneGAP's metric (where chosen) under score_heading, the other metrics' tables
    and, with --sweep, the F1 by kept score; with their notes."""
    tables, notes = [], []
    source = result.get("external") or {}
    if all(always in metrics for always in ALWAYS):  # LaneGAP's metric: the main table
        table, notes = score_table(result)
        tables.append((score_heading(pred, gt, result), table))
    elif source.get("lanes_read") is not None:  # a submission's frames are said without the main table too
        notes.append(score_heading(pred, gt, result))
    others, other_notes = console_tables(metrics, result)
    tables, notes = tables + others, notes + other_notes
    said = any("not_computed" in metric.scores(result) for metric in metrics if metric.console is not None)
    if source.get("not_computed") and not said:  # a chosen metric's notes (OpenLane-V2's) say it already
        notes.append(f"not computed: {', '.join(source['not_computed'])} (the submission's traffic elements, "
                     "traffic_element and topology_lcte, are not read)")  # fmt: skip
    if result.get("sweep"):
        tables.append(sweep_table(result))
    return Printout(tables, notes)


def score_heading(pred: Path, gt: Path, result: dict) -> str:
    """cli score's heading: what was scored against what, and how many frames."""
    where = f", split {', '.join(result['splits'])}" if result["splits"] else ", every frame"
    source = result.get("external") or {}
    if source.get("lanes_read") is not None:  # an OpenLane-V2 submission
        method = f", method {source['method']}" if source.get("method") else ""
        ignored = source["frames_in_file"] - result["frames_predicted"]
        return (f"{pred} (OpenLane-V2 submission{method}) against {gt}{where}: {result['frames']} frames "
                f"scored, {result['frames_predicted']} in the submission ({source['lanes_read']} lanes), "
                f"{result['frames_missing']} missing (scored as empty)"
                + (f"; {ignored} of its frames, not of the split, ignored" if ignored else ""))  # fmt: skip
    if source.get("vectors_read") is None:  # our graph table
        return (f"{pred} against {gt}{where}: {result['frames']} frames scored, "
                f"{result['frames_predicted']} predicted, {result['frames_missing']} missing")  # fmt: skip
    kept = f"{source['class_name']} above {source['min_score']:g}"  # a result file of another codebase
    return (f"{pred} ({source['format']}, {kept}) against {gt}{where}: {result['frames']} frames scored "
            f"(those in the file), {source['frames_not_in_file']} of the split not in the file; "
            f"{source['vectors_kept']} vectors kept, {source['points_clipped']} points outside the range "
            "clipped")  # fmt: skip


def roundtrip_tables(data: Path, via: str, result: dict) -> Printout:
    """`cli roundtrip`'s scores under a heading naming the data, the representation and the frames."""
    table, notes = score_table(result)
    return Printout([(f"{data} through {via} and back: {result['frames']} frames", table)], notes)


def sweep_table(result: dict) -> tuple[str, Table]:
    """`cli score --sweep`: the F1 at each kept score of a result file, the one scored above marked."""
    table = Table(
        "kept score above", "vectors kept", *(f"{mode} {name} F1" for mode in MODES for name, _ in METRICS)
    )
    chosen = result["external"]["min_score"]
    for row in result["sweep"]:
        mark = " *" if row["min_score"] == chosen else ""
        table.add_row(f"{row['min_score']:g}{mark}", str(row["vectors_kept"]),
                      *(f"{row[mode][metric]:.3f}" for mode in MODES for _, metric in METRICS))  # fmt: skip
    return "F1 by kept score (--sweep; *: the one scored above; no intervals)", table


def viz_line(out: Path, result: dict) -> str:
    """`cli viz`'s line: the picture written, its frame and the frame's directed F1s."""
    directed = result["scores"]["directed"]
    return (f"wrote {out}: frame {result['frame_id']}, directed TOPO F1 {directed['topo']['f1']:.3f}, "
            f"Junction TOPO F1 {directed['junction_topo']['f1']:.3f}")  # fmt: skip


def plain(cell: str) -> str:
    """A markdown cell without its bold and code quotes."""
    return cell.replace("`", "").removeprefix("**").removesuffix("**")


def report_tables(result: Report) -> tuple[list[tuple[str, Table]], list[dict]]:
    """`cli report`'s main tables (each block's, and the paper's beside it) as (heading, table) pairs with
    the run, method, F1 and FPS columns (bold where report.md has it), and as plain dicts with every
    column for --json."""
    from benchmark.report.measured_tables import main_table

    shown, tables = [], []
    for block, references in zip(result.blocks, result.references):
        for title, header, rows in [(block.title, *main_table(block)), *references]:
            keep = [
                i for i, name in enumerate(header) if i < 2 or name.endswith("F1") or name.startswith("FPS")
            ]
            table = Table(*(header[i] for i in keep))
            for row in rows:
                table.add_row(*(f"[bold]{plain(row[i])}[/bold]" if row[i].startswith("**") else plain(row[i])
                                for i in keep))  # fmt: skip
            shown.append((plain(title), table))
            tables.append(
                {"title": plain(title), "header": header, "rows": [list(map(plain, r)) for r in rows]}
            )
    return shown, tables


def finish(result: dict, printout: Printout, wrote: list, as_json: bool) -> None:
    """A command's end: with --json its result as one JSON line on stdout (and what it wrote on stderr);
    else its printout (tables under their headings, notes) and the paths it wrote."""
    written = f"wrote {', '.join(str(path) for path in wrote)}" if wrote else ""
    if as_json:
        typer.echo(json.dumps(result))
        if written:
            typer.echo(written, err=True)
        return
    console = Console()
    one_line = not console.is_terminal  # a log keeps each line whole; a terminal wraps it between words
    for heading, table in printout.tables:
        console.print(Text(heading, style="bold"), soft_wrap=one_line)  # a table title wraps at its width
        console.print(table)
    for line in [*printout.notes, written]:
        if line:
            console.print(Text(line), soft_wrap=one_line)


@contextmanager
def reported_errors():
    """Bad input (DataError is a ValueError), or --executor ray without Ray installed (its install hint), ends
    the command with its message and exit code 1."""
    from pipeline.executor import RayMissing

    try:
        yield
    except (ValueError, FileNotFoundError, FileExistsError, RayMissing) as error:
        message = str(error)
        if "Original Traceback" in message:  # re-raised from a DataLoader worker: its last line says it
            message = message.strip().splitlines()[-1].partition(": ")[2]
        typer.secho(f"error: {message}", fg="red", err=True)
        raise typer.Exit(1) from error


def version_text() -> str:
    """The installed package's version, the metric's metric_version and the prepared data's schema_version
    (CHANGELOG.md says what each bump means for old files); imports neither torch nor the models."""
    from importlib.metadata import PackageNotFoundError, version

    from benchmark.metric.params import METRIC_VERSION
    from pipeline.io import SCHEMA_VERSION

    try:
        package = version("lanegraph")
    except PackageNotFoundError:  # a checkout on sys.path, never installed
        package = "(not installed)"
    versions = f"metric_version {METRIC_VERSION}, prepared-data schema_version {SCHEMA_VERSION}"
    return f"lanegraph {package} ({versions})"
