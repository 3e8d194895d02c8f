"""The paper's published tables beside the measured ones (`cli report --reference paper`): which of them
match a block, their rows in the report's own columns and units, and the notes report.md says of them.

The numbers come from benchmark/report/reference.py (paper_reference.toml); they stand as reference tables
of their own, never bolded, ranked or averaged with measured rows.
"""

from __future__ import annotations

from benchmark.report.measured_tables import FIELD_NAMES, METRICS, MODES, SHORT, STATS, markdown_table
from benchmark.report.reference import SCORE_KEYS, ReferenceTable
from benchmark.report.runs import Block, SplitKind, percent

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
# where each paper table is shown, for the list of those no measured table matched
REFERENCE_PLACES = {
    "tab:modeling": "under a dataset block of nuScenes or AV2 at 30 x 60 m on its own split",
    "tab:iou": "beside the mIoU table of a nuScenes or AV2 block at 30 x 60 m on its own split",
    "tab:postproc": "beside the post-processing accuracy of `--roundtrip` results",
    "tab:perception_range": "under a dataset block of nuScenes prepared at 50 x 100 m on its own split",
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
    if kind is SplitKind.ORIGINAL:
        labels = ["tab:perception_range"] if bev_range == "50x100" else []
        labels += ["tab:modeling"] if bev_range == "30x60" else []
    elif kind is SplitKind.STREAMMAPNET and bev_range == "30x60":
        labels = ["tab:newsplit"]
    found = [(refs[label], refs[label].rows_of(block.dataset)) for label in labels if label in refs]
    return [(table, rows) for table, rows in found if rows]


def ablation_references(block: Block, refs: dict[str, ReferenceTable], name: str) -> list[ReferenceTable]:
    """The paper's ablations of config field `name` (each on a dataset's own split), for a block whose
    data is on its own split; none for another split."""
    if block.data_split.kind is not SplitKind.ORIGINAL:
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
