"""The paper's published tables beside the measured ones (`cli report --reference paper`): which of them
match a block, their rows in the report's own columns and units, and the notes report.md says of them.

The numbers come from benchmark/report/reference.py (paper_reference.toml); they stand as reference tables
of their own, never bolded, ranked or averaged with measured rows. The paper's OpenLane-V2 table
(`tab:toponet`) stands in a section of its own, beside the runs on OpenLane-V2 data at its range
(openlanev2_runs, openlanev2_table); OpenLane-V2 blocks get none of its nuScenes and AV2 tables.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from benchmark.report.measured_tables import FIELD_NAMES, METRICS, MODES, SHORT, STATS, markdown_table
from benchmark.report.reference import DATASET_NAMES, SCORE_KEYS, ReferenceTable
from benchmark.report.runs import Block, Run, SplitKind, percent

REFERENCE_NOTE = (
    "Tables headed *Reference* hold the paper's published numbers (benchmark/report/paper_reference.toml, "
    "each from the LaTeX table named in its rows), not numbers measured here: the paper trained on the full "
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
OPENLANEV2 = "openlanev2"  # the manifest's dataset of OpenLane-V2 data (`cli prepare --dataset openlanev2`)
OPENLANEV2_TABLE = "tab:toponet"  # the paper's OpenLane-V2 table, shown in a section of its own
OPENLANEV2_NOTE = (
    "The paper compares on OpenLane-V2 by mIoU alone, at OpenLane-V2's 50 x 100 m range: its starred rows "
    "are the TopoNet paper's numbers, its LaneGAP row a variant of TopoNet that learns paths. Beside them, "
    "the runs here that were scored on OpenLane-V2 data (`cli prepare --dataset openlanev2`) at that range, "
    "their mIoU as the block's mIoU table reads it from metrics.json: this project's mIoU (docs/METRICS.md, "
    "both graphs drawn on the BEV grid), the paper's rows TopoNet's, so alike in kind, not proven equal. "
    "OpenLane-V2 runs stand in no nuScenes or AV2 table, and the paper's nuScenes and AV2 tables beside no "
    "OpenLane-V2 block."
)
OPENLANEV2_SYNTHETIC_NOTE = (
    "A run on synthetic OpenLane-V2 data (`cli synth`) is on worlds of its own: the paper's rows are context "
    "for it, not a like-for-like comparison."
)
OPENLANEV2_BLOCK_NOTE = (
    "The paper's nuScenes and AV2 tables stand beside no OpenLane-V2 block: its OpenLane-V2 table "
    "(`tab:toponet`, mIoU at 50 x 100 m) is in the section *OpenLane-V2* below, with the runs here measured "
    "at that range."
)
# where each paper table is shown, for the list of those no measured table matched
REFERENCE_PLACES = {
    "tab:modeling": "under a dataset block of nuScenes or AV2 at 30 x 60 m on its own split",
    "tab:iou": "beside the mIoU table of a nuScenes or AV2 block at 30 x 60 m on its own split",
    "tab:postproc": "beside the post-processing accuracy of `--roundtrip` results",
    "tab:perception_range": "under a dataset block of nuScenes prepared at 50 x 100 m on its own split",
    OPENLANEV2_TABLE: "in a section of its own when a run is on OpenLane-V2 data (`cli prepare --dataset "
    "openlanev2`), beside those runs measured at 50 x 100 m",
    "tab:newsplit": "under a dataset block of nuScenes at 30 x 60 m prepared with StreamMapNet's split files "
    "(`--split-file train=... --split-file val=...`)",
}
# why a block whose data is not on the dataset's own split has no paper table beside it, by its split
OTHER_SPLIT_NOTES = {
    SplitKind.GEOGRAPHIC: "the paper measured no model on a split made so, so none of its rows stand beside "
    "this block (its tables are on the datasets' own splits, `tab:newsplit` on StreamMapNet's).",
    SplitKind.SPLIT_FILES: "they are not StreamMapNet's split (the paper's `tab:newsplit`) and the paper "
    "has no table on them, so none of its rows stand beside this block.",
}
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
    """The paper's tables that match a block's main table, only rows of its dataset: on the dataset's own
    split, Tab. 1 at its 30 x 60 m range or the 50 x 100 m table; on StreamMapNet's split, its table at
    30 x 60 m; on any other split (the geographic scheme's, the user's split files) none."""
    bev_range, kind = block.parameters.get("bev_range"), block.data_split.kind
    labels = []
    if block.dataset == OPENLANEV2:  # the paper's OpenLane-V2 table has its own section
        return []
    if kind is SplitKind.ORIGINAL:
        labels = ["tab:perception_range"] if bev_range == "50x100" else []
        labels += ["tab:modeling"] if bev_range == "30x60" else []
    elif kind is SplitKind.STREAMMAPNET and bev_range == "30x60":
        labels = ["tab:newsplit"]
    found = [(refs[label], refs[label].rows_of(block.dataset)) for label in labels if label in refs]
    return [(table, rows) for table, rows in found if rows]


def ablation_references(block: Block, refs: dict[str, ReferenceTable], name: str) -> list[ReferenceTable]:
    """The paper's ablations of config field `name` (each on a dataset's own split), for a block whose
    data is on its own split; none for another split or OpenLane-V2 data (the paper's are on nuScenes)."""
    if block.data_split.kind is not SplitKind.ORIGINAL or block.dataset == OPENLANEV2:
        return []
    return [table for table in refs.values() if table.field == name]


def split_note(block: Block) -> str | None:
    """Why no paper table stands beside a block whose data is not on the dataset's own split (None for
    the dataset's own split and StreamMapNet's)."""
    data_split = block.data_split
    why = OTHER_SPLIT_NOTES.get(data_split.kind)
    return None if why is None else f"This data is split by {data_split.describe()}: {why}"


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


def openlanev2_runs(blocks: list[Block], bev_range: str) -> tuple[list[tuple[Block, Run]], list[str]]:
    """The runs beside the paper's OpenLane-V2 table: those scored on OpenLane-V2 data at its range
    (`bev_range`) with an mIoU, with their blocks; and a line for each reason the others are left out,
    with how many."""
    kept: list[tuple[Block, Run]] = []
    other_data, ranges = Counter(), Counter()
    unscored, no_miou = [], []
    for block in blocks:
        for run in block.runs:
            if block.dataset != OPENLANEV2:
                name = DATASET_NAMES.get(block.dataset, block.dataset)
                other_data[name if block.data is not None else "data not found"] += 1
            elif not run.scored:
                unscored.append(run.name)
            elif run.bev_range != bev_range:
                ranges[range_words(run.bev_range)] += 1
            elif run.metrics.get("miou") is None:
                no_miou.append(run.name)
            else:
                kept.append((block, run))
    paper = range_words(bev_range)
    lines = []
    if ranges:
        at = [*ranges][0] if len(ranges) == 1 else ", ".join(f"{r} ({n})" for r, n in ranges.items())
        redo = f"`cli prepare --dataset openlanev2 --range {bev_range}`"
        lines.append(f"Left out: {runs_count(ranges.total())} on OpenLane-V2 data measured at {at}, not at "
                     f"the paper's {paper} ({redo}).")  # fmt: skip
    if other_data:
        on = ", ".join(f"{name}: {count}" for name, count in other_data.items())
        lines.append(f"Left out: {runs_count(other_data.total())} on other data ({on}): the paper's table "
                     "is on OpenLane-V2.")  # fmt: skip
    if unscored:
        lines.append(f"Left out: {runs_count(len(unscored))} on OpenLane-V2 data without scores "
                     f"({', '.join(unscored)}).")  # fmt: skip
    if no_miou:
        lines.append(f"Left out: {runs_count(len(no_miou))} on OpenLane-V2 data whose metrics.json holds no "
                     f"mIoU ({', '.join(no_miou)}).")  # fmt: skip
    return kept, lines


def runs_count(count: int) -> str:
    return f"{count} run" if count == 1 else f"{count} runs"


def range_words(bev_range: str | None) -> str:
    """A range as the report writes it: "50 x 100 m"; "an unknown range" for None."""
    if not bev_range:
        return "an unknown range"
    width, length = bev_range.split("x")
    return f"{width} x {length} m"


def openlanev2_data(block: Block) -> str:
    """Which OpenLane-V2 data a block's runs ran on: "ours, synthetic OpenLane-V2 (`cli synth`)", or
    the raw root's folder name and the subset read (`--subset`), as its manifest names them."""
    if block.synthetic:
        return "ours, synthetic OpenLane-V2 (`cli synth`)"
    root, subset = block.manifest.get("root"), block.parameters.get("subset")
    name = f"OpenLane-V2 `{Path(root).name}`" if root else "OpenLane-V2 (root not recorded)"
    name += f", subset {subset}" if subset else ""
    return f"ours, {name}" + (" (its raw data is gone)" if block.synthetic is None and root else "")


def openlanev2_table(kept: list[tuple[Block, Run]]) -> tuple[list[str], list[list[str]]]:
    """Our runs beside the paper's OpenLane-V2 table: the data each ran on, and its mIoU in %."""
    rows = [
        [openlanev2_data(block), run.name, run.method, run.modality, block.split_words,
         str(run.metrics["frames"]), percent(run.metrics["miou"])]
        for block, run in kept
    ]  # fmt: skip
    return ["data", "run", "method", "modality", "split", "frames", "mIoU"], rows
