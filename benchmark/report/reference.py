"""The LaneGAP paper's published tables, read from benchmark/report/paper_reference.toml, for `cli report
--reference paper`.

The numbers are the paper's, typed once from its LaTeX source, each table keyed by its \\label there.
They were measured on other data (the full nuScenes or AV2), with another schedule and other machines,
so the report shows them as reference tables of their own beside the measured ones: labelled with the
paper's schedule and hardware, never bolded, ranked or averaged with a measured row.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from importlib.resources import files
from importlib.resources.abc import Traversable
from pathlib import Path

# package data (pyproject.toml), found through the import system: in a checkout, an install or a zip alike
REFERENCE_FILE = files("benchmark.report") / "paper_reference.toml"
REFERENCES = ("paper",)  # the values of `cli report --reference`
# the data file's score keys, by (mode, metric)
SCORE_KEYS = {
    ("directed", "junction_topo"): "dir_jtopo",
    ("directed", "topo"): "dir_topo",
    ("undirected", "junction_topo"): "undir_jtopo",
    ("undirected", "topo"): "undir_topo",
}
DATASET_NAMES = {"nuscenes": "nuScenes", "av2": "AV2", "openlanev2": "OpenLane-V2"}


@dataclass
class ReferenceTable:
    label: str  # the LaTeX \label, e.g. "tab:modeling"
    title: str
    meta: dict  # dataset, modality, range, schedule, fps_on, field: where the paper states them
    rows: list[dict]

    @property
    def field(self) -> str | None:
        """The config field an ablation table varies (its rows' `value`)."""
        return self.meta.get("field")

    def rows_of(self, dataset: str | None = None) -> list[dict]:
        """The rows of one dataset (all rows when the table names none)."""
        return [row for row in self.rows if dataset is None or self.dataset(row) in (None, dataset)]

    def dataset(self, row: dict) -> str | None:
        return row.get("dataset", self.meta.get("dataset"))

    def row_label(self, row: dict) -> str:
        """Where the row comes from: the paper's table, schedule, the GPU of its FPS and its origin."""
        parts = [f"paper `{self.label}`"]
        schedule = self.meta.get("schedule")
        if isinstance(schedule, dict):
            schedule = schedule.get(self.dataset(row))
        if schedule:
            parts.append(schedule)
        if self.meta.get("fps_on") and ("fps" in row or "fps_net" in row):
            parts.append(f"FPS on {self.meta['fps_on']}")
        if row.get("origin"):  # a number the paper took from another paper, or a variant it measured
            parts.append(row["origin"])
        return ", ".join(parts)

    def describe(self, dataset: str | None = None) -> str:
        """One line: what the table is and under which conditions the paper measured it."""
        dataset = dataset or self.meta.get("dataset")
        where = [f"on {DATASET_NAMES.get(dataset, dataset)}" if dataset else "dataset not named"]
        if self.meta.get("modality"):
            where.append(f"{self.meta['modality']} input")
        if self.meta.get("range"):
            width, length = self.meta["range"].split("x")
            where.append(f"{width} x {length} m range")
        return f"the paper's {self.title} (`{self.label}`), " + ", ".join(where)


def load_reference(
    name: str = "paper", path: Path | Traversable = REFERENCE_FILE
) -> dict[str, ReferenceTable]:
    """{label: table} of a reference; ValueError for another name or a malformed file."""
    if name not in REFERENCES:
        raise ValueError(f"--reference must be {' or '.join(REFERENCES)}, not {name!r}")
    try:
        data = tomllib.loads((Path(path) if isinstance(path, str) else path).read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as error:
        raise ValueError(f"{path}: not valid TOML ({error})") from error
    tables = {}
    for label, body in data.items():
        if not label.startswith("tab:") or not isinstance(body.get("rows"), list) or "title" not in body:
            raise ValueError(
                f"{path}: [{label}] is not a table keyed by its LaTeX label, with title and rows"
            )
        meta = {k: v for k, v in body.items() if k not in ("title", "rows")}
        tables[label] = ReferenceTable(label, body["title"], meta, body["rows"])
    return tables
