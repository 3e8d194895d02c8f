"""The paper's published numbers (benchmark/report/paper_reference.toml): checked against the paper's LaTeX
when ../shared/paper is present, and read back from the reference tables the report renders."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from benchmark.report.paper_tables import main_references, reference_table
from benchmark.report.reference import REFERENCE_FILE, SCORE_KEYS, load_reference
from benchmark.report.runs import Block, is_synthetic

LATEX = Path(__file__).resolve().parents[1].parent / "shared" / "paper" / "lanegap.tex"
STAT_INDEX = {"P": 0, "R": 1, "F1": 2}
MODE_NAMES, METRIC_NAMES = (
    {"directed": "dir", "undirected": "undir"},
    {"junction_topo": "J-TOPO", "topo": "TOPO"},
)
COLUMN_KEYS = {
    f"{MODE_NAMES[mode]} {METRIC_NAMES[metric]}": key for (mode, metric), key in SCORE_KEYS.items()
}
EXTRAS = {"Params (M)": "params_m", "FPS_net": "fps_net", "FPS": "fps", "mIoU": "miou"}


def numbers_of(header: list[str], row: list[str]) -> dict:
    """The numbers of one rendered reference row, in the data file's keys and units: {key: [P, R, F1]}
    for scores (cells in %), {key: value} for the others; "–" cells left out."""
    out: dict = {}
    for name, cell in zip(header, row):
        cell = cell.strip()
        if cell == "–":
            continue
        scores = re.fullmatch(r"(dir|undir) (J-TOPO|TOPO) (P|R|F1)", name)
        if scores:
            key = COLUMN_KEYS[f"{scores[1]} {scores[2]}"]
            out.setdefault(key, [None, None, None])[STAT_INDEX[scores[3]]] = float(cell) / 100
        elif name in EXTRAS:
            out[EXTRAS[name]] = float(cell)
    return out


def assert_row_equals(parsed: dict, row: dict) -> None:
    """Every number of the data file's row, and nothing else, read back from the rendered row."""
    expected = {key: row[key] for key in (*SCORE_KEYS.values(), *EXTRAS.values()) if key in row}
    assert parsed.keys() == expected.keys()
    for key, value in expected.items():
        assert parsed[key] == pytest.approx(value, abs=1e-9), key


def test_every_table_renders_and_reads_back_to_the_data_file():
    tables = load_reference()
    assert set(tables) == {"tab:modeling", "tab:iou", "tab:postproc", "tab:bevseg", "tab:polyline",
                           "tab:bezier", "tab:perception_range", "tab:newsplit", "tab:modality",
                           "tab:schedule"}  # fmt: skip
    for label, table in tables.items():
        header, rows = reference_table(table, table.rows)
        assert header[0] == "reference" and len(rows) == len(table.rows)
        for rendered, row in zip(rows, table.rows):
            assert rendered[0].startswith(f"paper `{label}`")
            assert not any("**" in cell for cell in rendered)  # never bolded
            assert_row_equals(numbers_of(header, rendered), row)


def test_row_labels_name_the_papers_schedule_and_fps_gpu():
    tables = load_reference()
    header, rows = reference_table(tables["tab:modeling"], tables["tab:modeling"].rows_of("nuscenes"))
    assert [row[1] for row in rows] == ["HDMapNet", "STSU", "MapTR", "LaneGAP"]
    assert all(row[0] == "paper `tab:modeling`, 110 epochs, FPS on one RTX 3090" for row in rows)
    _, rows = reference_table(tables["tab:modeling"], tables["tab:modeling"].rows_of("av2"))
    assert all(row[0] == "paper `tab:modeling`, 24 epochs, FPS on one RTX 3090" for row in rows)
    header, rows = reference_table(tables["tab:polyline"], tables["tab:polyline"].rows)
    assert header[1] == "points per path" and [row[1] for row in rows] == ["10", "30", "40"]
    assert rows[0][0] == "paper `tab:polyline`, 24 epochs, FPS on one RTX 3090"


def test_an_unknown_reference_or_a_malformed_file_is_refused(tmp_path):
    with pytest.raises(ValueError, match="--reference must be paper, not 'book'"):
        load_reference("book")
    bad = tmp_path / "bad.toml"
    bad.write_text('["tab:x"]\ntitle = "x"\n')
    with pytest.raises(ValueError, match=r"bad.toml: \[tab:x\] is not a table"):
        load_reference("paper", bad)


# ---------------------------------------------------------------------------------------------------
# The data file against the paper's LaTeX


def latex_rows(tex: str, label: str) -> list[list[str]]:
    """The body rows of the tabular just before \\label{label}: cells without colour, bold or multirow."""
    at = tex.index(rf"\label{{{label}}}")
    start = tex.rindex(r"\begin{tabular}", 0, at)
    body = tex[start : tex.index(r"\end{tabular}", start)]
    body = re.sub(r"\\(midrule|bottomrule)", "", body[body.index(r"\midrule") + len(r"\midrule") :])
    rows = []
    for line in body.split(r"\\"):
        cells = [re.sub(r"\\cellcolor\{[^}]*\}", "", cell) for cell in line.split("&")]
        cells = [
            re.sub(r"\\(?:textbf|multirow\{[^}]*\}\{[^}]*\})\{([^}]*)\}", r"\1", c).strip() for c in cells
        ]
        if any(cells):
            rows.append(cells)
    return rows


@pytest.fixture(scope="module")
def tex() -> str:
    if not LATEX.is_file():
        pytest.skip(f"the paper's LaTeX source is not at {LATEX} (../shared/paper beside the repo)")
    return LATEX.read_text()


def test_tab_modeling_matches_the_latex(tex):
    rows, table = latex_rows(tex, "tab:modeling"), load_reference()["tab:modeling"]
    assert len(rows) == len(table.rows) == 8
    dataset = None
    for cells, row in zip(rows, table.rows):
        dataset = {"nusc": "nuscenes", "av2": "av2"}.get(cells[0], dataset)  # a multirow's first row
        assert (dataset, cells[1], cells[2].lower()) == (row["dataset"], row["method"], row["modeling"])
        numbers = [float(cell.rstrip("M")) for cell in cells[3:]]
        expected = [v for key in ("dir_jtopo", "dir_topo", "undir_jtopo", "undir_topo") for v in row[key]]
        assert numbers == expected + [row["params_m"], row["fps_net"], row["fps"]], row["method"]


def test_tab_iou_matches_the_latex(tex):
    rows, table = latex_rows(tex, "tab:iou"), load_reference()["tab:iou"]
    header = re.findall(r"&\s*(\w+)", tex[tex.rindex(r"\begin{tabular}", 0, tex.index(r"\label{tab:iou}")) :])
    methods = header[:4]
    assert methods == ["HDMapNet", "STSU", "MapTR", "LaneGAP"]
    published = {
        ({"nusc": "nuscenes", "av2": "av2"}[cells[0].split()[-1]], method): float(value)
        for cells in rows for method, value in zip(methods, cells[1:])
    }  # fmt: skip
    assert published == {(row["dataset"], row["method"]): row["miou"] for row in table.rows}


def test_tab_postproc_matches_the_latex(tex):
    rows, table = latex_rows(tex, "tab:postproc"), load_reference()["tab:postproc"]
    assert [cells[0].lower() for cells in rows] == [row["via"] for row in table.rows]
    for cells, row in zip(rows, table.rows):
        assert [float(c) for c in cells[1:] if c] == row["dir_jtopo"] + row["dir_topo"]


def test_the_data_file_names_its_source():
    text = REFERENCE_FILE.read_text()
    assert "lanegap.tex" in text
    # every table is keyed by a LaTeX label, and the LaTeX (when present) has each of them
    labels = re.findall(r'^\["(tab:[a-z_]+)"\]', text, re.M)
    assert labels == list(load_reference())
    if LATEX.is_file():
        source = LATEX.read_text()
        assert all(rf"\label{{{label}}}" in source for label in labels)


# ---------------------------------------------------------------------------------------------------
# Which tables a dataset block gets, and how its data is named


def test_the_range_and_split_tables_follow_the_manifest():
    refs = load_reference()

    def placed(dataset: str, parameters: dict) -> list[tuple[str, set]]:
        block = Block(dataset, None, "val", [], manifest={"parameters": parameters})
        return [
            (table.label, {table.dataset(row) for row in rows})
            for table, rows in main_references(block, refs)
        ]

    geographic = {"train": "train.txt", "val": "val.txt"}
    assert placed("nuscenes", {"bev_range": "30x60"}) == [("tab:modeling", {"nuscenes"})]
    assert placed("av2", {"bev_range": "30x60"}) == [("tab:modeling", {"av2"})]
    assert placed("nuscenes", {"bev_range": "50x100"}) == [("tab:perception_range", {"nuscenes"})]
    assert placed("nuscenes", {"bev_range": "30x60", "split_files": geographic}) == [
        ("tab:newsplit", {"nuscenes"})
    ]
    assert placed("nuscenes", {"bev_range": "50x100", "split_files": geographic}) == [
        ("tab:perception_range", {"nuscenes"}), ("tab:newsplit", {"nuscenes"})
    ]  # fmt: skip
    # the paper's range and split tables are nuScenes only; another range or dataset has no table
    assert placed("av2", {"bev_range": "50x100"}) == []
    assert placed("nuscenes", {"bev_range": "20x40"}) == []
    assert placed("unknown", {"bev_range": "30x60"}) == []


def test_synthetic_data_is_told_by_the_synth_marker_above_the_raw_root(tmp_path):
    raw = tmp_path / "raw"
    (raw / "av2" / "sensor").mkdir(parents=True)
    (raw / "nuscenes").mkdir()
    (raw / "synth.json").write_text(json.dumps({"av2_root": "av2/sensor", "nuscenes_root": "nuscenes"}))
    assert is_synthetic({"root": str(raw / "av2" / "sensor")}) is True
    assert is_synthetic({"root": str(raw / "nuscenes")}) is True
    real = tmp_path / "real" / "sensor"
    real.mkdir(parents=True)
    assert is_synthetic({"root": str(real)}) is False
    (tmp_path / "other").mkdir()  # a marker that names other roots says nothing about this one
    (tmp_path / "other" / "synth.json").write_text(json.dumps({"av2_root": "x", "nuscenes_root": "y"}))
    (tmp_path / "other" / "data").mkdir()
    assert is_synthetic({"root": str(tmp_path / "other" / "data")}) is False
    assert is_synthetic({"root": str(tmp_path / "gone")}) is None
    assert is_synthetic({}) is None
