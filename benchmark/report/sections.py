"""The sections of report.md, each a list of markdown lines: the introduction, each block's tables and
pictures, the round trips, the paper's OpenLane-V2 table with the runs beside it, the paper's tables not
shown, the training loss and validation curves.

The section builders share a Sections: where the pictures go (benchmark/report/figures.py draws them), the
paper's tables, and which of those were placed; benchmark/report/writer.py puts the sections in order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from benchmark.metric import bootstrap
from benchmark.metric.params import MetricParams
from benchmark.report import figures
from benchmark.report.measured_tables import (
    F1_COLUMNS,
    FIELD_NAMES,
    JUNCTION_DEFINITION,
    SHORT,
    ablation_table,
    ablations,
    block_graphs,
    external_notes,
    floor_notes,
    grid_frames,
    junction_count,
    junction_table,
    main_table,
    markdown_table,
    miou_table,
    params_line,
    settings_table,
    short_id,
)
from benchmark.report.paper_tables import (
    OPENLANEV2,
    OPENLANEV2_BLOCK_NOTE,
    OPENLANEV2_NOTE,
    OPENLANEV2_SYNTHETIC_NOTE,
    OPENLANEV2_TABLE,
    REFERENCE_NOTE,
    SYNTHETIC_NOTE,
    UNKNOWN_ORIGIN_NOTE,
    ablation_references,
    console_reference,
    main_references,
    openlanev2_runs,
    openlanev2_table,
    range_words,
    reference_section,
    split_note,
    unplaced_references,
)
from benchmark.report.reference import ReferenceTable
from benchmark.report.runs import VALIDATION_FILE, Block, Run, percent, shown
from benchmark.report.summary import summary
from benchmark.report.variant_tables import variant_sections
from pipeline.geometry import Range
from pipeline.splits.geographic import draw_dataset_splits
from pipeline.splits.leakage import leakage_line

FLOOR_NOTE = (
    "Rows `constant prior` and `<run>: other log's sensors` are the sensor-blind floor (`cli eval`): what "
    "a model that ignores its frame's sensors scores on the same frames. Row `best constant (hindsight)`: "
    "of the constant prior's candidate graphs, the one that scores best on these frames themselves, an "
    "upper bound for any constant prediction (chosen on the evaluated frames, so not a blind model)."
)
EXTERNAL_NOTE = (
    "A run whose method ends in *(external)* is another codebase's result file, scored by `cli score --out "
    "RUN_DIR` with the same metric on the same ground truth (its metrics.json, not `cli eval`'s): ranked "
    "and bolded with the runs, but its size, speed, sensors and sensor-blind floor are unknown (the note "
    "under its table says what was read)."
)
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
SPLITS_NOTE = (
    "Every frame of the prepared data on its city's plane (world x, y), coloured by split: where a scored "
    "frame lies near a training frame, the model may recognise the place (the leakage line above)."
)


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
    metrics: tuple[str, ...] = ("lanegap",)  # `cli report --metric`: the other metrics' tables

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
            "pooled again; benchmark/metric/bootstrap.py). The summary's leads use the paired interval of "
            "two runs' difference (same frames, same draws).",
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
    # the data's split scheme and how near its evaluated frames lie to a training frame (`cli prepare`)
    md += [leakage_line(block.manifest.get("leakage"), block.parameters.get("split_scheme")), ""]
    doc.shown_references.append([])
    note = split_note(block) if refs else None  # on another split than the paper's: no paper rows
    if refs and note:
        md += [note, ""]
    elif refs and block.dataset == OPENLANEV2:
        md += [OPENLANEV2_BLOCK_NOTE, ""]
    elif refs:
        if block.synthetic:
            md += [SYNTHETIC_NOTE, ""]
        elif block.synthetic is None:
            md += [UNKNOWN_ORIGIN_NOTE, ""]
        if not beside:
            where = f"{block.dataset} at range {block.parameters.get('bev_range', '?')}"
            where += f", {block.data_split.describe()}" if block.data_split.files else ""
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
        for table in ablation_references(block, doc.refs, name):
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


def splits_section(block: Block, slug: str, doc: Sections) -> list[str]:
    """Where the block's data lies, every frame coloured by split, as `cli prepare` draws DATA/splits.png."""
    name = f"splits_{slug}.png"
    draw_dataset_splits(block.data, doc.out / name)
    doc.pictures.append(doc.out / name)
    return ["### Splits", "", f"![frames by split]({name})", "", SPLITS_NOTE, ""]


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
    md += variant_sections(block, doc.metrics, doc.workers)
    md += junction_sections(block, slug, doc)
    return md + f1_section(block, slug, doc) + splits_section(block, slug, doc)


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


def openlanev2_section(blocks: list[Block], doc: Sections) -> list[str]:
    """The paper's OpenLane-V2 table (`tab:toponet`) in a section of its own, with the runs measured on
    OpenLane-V2 data at its range beside it and a line for each reason others are left out; none without
    `--reference paper` or without a run on OpenLane-V2 data."""
    table = doc.refs.get(OPENLANEV2_TABLE)
    if table is None or not any(block.dataset == OPENLANEV2 for block in blocks):
        return []
    doc.placed.add(table.label)
    bev_range = table.meta["range"]
    md = ["## OpenLane-V2 (the paper's `tab:toponet`)", "", OPENLANEV2_NOTE, ""]
    md += reference_section(table, table.rows)
    kept, left_out = openlanev2_runs(blocks, bev_range)
    md += [f"#### Ours: runs on OpenLane-V2 data at {range_words(bev_range)} (`--range {bev_range}`)", ""]
    if kept:
        md += [markdown_table(*openlanev2_table(kept)), ""]
        if any(block.synthetic for block, _ in kept):
            md += [OPENLANEV2_SYNTHETIC_NOTE, ""]
    else:
        md += [f"No run here was scored on OpenLane-V2 data at {range_words(bev_range)}.", ""]
    return md + [f"- {line}" for line in left_out] + ([""] if left_out else [])


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
