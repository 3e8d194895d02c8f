"""The paper's published numbers (benchmark/report/paper_reference.toml): checked against the paper's LaTeX
when ../shared/paper is present, and read back from the reference tables the report renders."""

from __future__ import annotations

import hashlib
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
                           "tab:bezier", "tab:perception_range", "tab:newsplit", "tab:toponet",
                           "tab:modality", "tab:schedule"}  # fmt: skip
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


def test_the_range_and_split_tables_follow_the_manifest(tmp_path):
    refs = load_reference()

    def placed(dataset: str, parameters: dict) -> list[tuple[str, set]]:
        manifest = {"dataset": dataset, "parameters": parameters}
        block = Block(dataset, None, "val", [], manifest=manifest)
        return [
            (table.label, {table.dataset(row) for row in rows})
            for table, rows in main_references(block, refs)
        ]

    assert placed("nuscenes", {"bev_range": "30x60"}) == [("tab:modeling", {"nuscenes"})]
    assert placed("av2", {"bev_range": "30x60", "split_scheme": "original"}) == [("tab:modeling", {"av2"})]
    assert placed("nuscenes", {"bev_range": "50x100"}) == [("tab:perception_range", {"nuscenes"})]
    # the paper's tables are on the datasets' own splits: a geographic scheme's split stands beside none
    geographic = {"split_scheme": "geographic", "geo_cell": 100.0, "geo_buffer": 30.0, "geo_seed": 0}
    assert placed("nuscenes", {"bev_range": "30x60", **geographic}) == []
    assert placed("nuscenes", {"bev_range": "50x100", **geographic}) == []
    # nor do the user's own split files, which are not StreamMapNet's
    for split, names in (("train", ["scene-0061", "scene-0553"]), ("val", ["scene-0655"])):
        (tmp_path / f"{split}.txt").write_text("\n".join(names) + "\n")
    named = {split: str(tmp_path / f"{split}.txt") for split in ("train", "val")}
    files = {"split_scheme": "original", "split_files": named}
    assert placed("nuscenes", {"bev_range": "30x60", **files}) == []
    # the paper's range and split tables are nuScenes only; another range or dataset has no table
    assert placed("av2", {"bev_range": "50x100"}) == []
    assert placed("nuscenes", {"bev_range": "20x40"}) == []
    assert placed("unknown", {"bev_range": "30x60"}) == []


def test_streammapnets_split_files_are_told_by_their_names_and_get_tab_newsplit(tmp_path):
    """StreamMapNet's files (../shared/data/splits) in any order, with comments and blank lines, are the
    paper's new split; the same files less one name, or with train and val swapped, are the user's."""
    from benchmark.report.runs import DataSplit, SplitKind

    train, val = (require_split_file(f"nuscenes_geo_{split}.txt") for split in ("train", "val"))
    names = train.read_text().split()
    (tmp_path / "mine_train.txt").write_text("# StreamMapNet's\n\n" + "\n".join(reversed(names)) + "\n")
    (tmp_path / "fewer_train.txt").write_text("\n".join(names[1:]) + "\n")

    def split_of(dataset: str, files: dict[str, Path], sha256: dict[str, str] | None = None) -> DataSplit:
        parameters = {"bev_range": "30x60", "split_scheme": "original",
                      "split_files": {split: str(path) for split, path in files.items()}}  # fmt: skip
        if sha256 is not None:  # as `cli prepare` records them since it refuses changed split files
            parameters["split_file_sha256"] = sha256
        return DataSplit.of({"dataset": dataset, "parameters": parameters})

    refs = load_reference()
    for files in ({"train": train, "val": val}, {"train": tmp_path / "mine_train.txt", "val": val}):
        data_split = split_of("nuscenes", files)
        assert data_split.kind is SplitKind.STREAMMAPNET
        block = Block("nuscenes", None, "val", [], manifest={"dataset": "nuscenes", "parameters": {
            "bev_range": "30x60", "split_files": {s: str(p) for s, p in files.items()}}})  # fmt: skip
        assert [(t.label, len(rows)) for t, rows in main_references(block, refs)] == [("tab:newsplit", 4)]
    for files in ({"train": tmp_path / "fewer_train.txt", "val": val}, {"train": val, "val": train},
                  {"train": train}):  # fmt: skip
        data_split = split_of("nuscenes", files)
        assert data_split.kind is SplitKind.SPLIT_FILES
        assert data_split.describe().startswith("your split files (`--split-file` ")
    assert split_of("nuscenes", {"train": train, "val": val}).describe() == (
        "StreamMapNet's geographically disjoint split (`--split-file` train=nuscenes_geo_train.txt, "
        "val=nuscenes_geo_val.txt)"
    )
    # StreamMapNet's AV2 files are theirs too (the paper's tab:newsplit has nuScenes rows alone), but not
    # for nuScenes data; at 50 x 100 m the paper has no table on their split
    av2 = {split: require_split_file(f"av2_geo_{split}.txt") for split in ("train", "val")}
    assert split_of("av2", av2).kind is SplitKind.STREAMMAPNET
    assert split_of("nuscenes", av2).kind is SplitKind.SPLIT_FILES
    wide = Block("nuscenes", None, "val", [], manifest={"dataset": "nuscenes", "parameters": {
        "bev_range": "50x100", "split_files": {"train": str(train), "val": str(val)}}})  # fmt: skip
    assert wide.data_split.kind is SplitKind.STREAMMAPNET and main_references(wide, refs) == []
    # a file edited since `cli prepare` (its recorded sha256 differs): whose split the data is on is unknown
    mine = {"train": tmp_path / "mine_train.txt", "val": val}
    recorded = {split: hashlib.sha256(path.read_bytes()).hexdigest() for split, path in mine.items()}
    assert split_of("nuscenes", mine, recorded).kind is SplitKind.STREAMMAPNET
    # (even to the same names in another order: the file prepared from is not the one here); such a
    # manifest, from before the names' digest was recorded, cannot tell whose split it is
    (tmp_path / "mine_train.txt").write_text("\n".join(names) + "\n")
    edited = split_of("nuscenes", mine, recorded)
    assert edited.kind is SplitKind.UNSURE_FILES
    assert edited.describe() == (
        "split files of unknown provenance (`--split-file` train=mine_train.txt, val=nuscenes_geo_val.txt; "
        "mine_train.txt changed since `cli prepare`, and manifest.json, from an earlier version, records no "
        "digest of their names)"
    )
    # files gone since `cli prepare`: whose they were is unknown
    gone = split_of("nuscenes", {"train": tmp_path / "gone_train.txt", "val": val})
    assert gone.kind is SplitKind.UNSURE_FILES and "gone_train.txt not found" in gone.describe()


def test_the_split_is_told_from_the_manifest_where_the_split_files_are_gone(synth_raw, tmp_path):
    """cli prepare records the digest of each split file's names, so that a report made where the files
    are not (another machine) still tells StreamMapNet's split from the user's; a manifest without it
    (an earlier version) is never taken for StreamMapNet's when the files are gone."""
    from benchmark.report.runs import STREAMMAPNET_SPLITS, DataSplit, SplitKind
    from pipeline.manifest import read_manifest
    from pipeline.prepare import prepare
    from pipeline.targets import TargetOptions

    def prepared_then_gone(dataset: str, root: Path, files: dict[str, Path], **options) -> dict:
        copies = {split: tmp_path / f"{dataset}_{path.name}" for split, path in files.items()}
        for split, path in files.items():
            copies[split].write_text("# a copy\n" + path.read_text())
        prepare(dataset, root, tmp_path / dataset, TargetOptions(), frame_stride=10, split_files=copies,
                **options)  # fmt: skip
        for path in copies.values():
            path.unlink()
        return read_manifest(tmp_path / dataset)

    av2 = synth_raw / "av2" / "sensor"
    (tmp_path / "one_log.txt").write_text(sorted(p.name for p in (av2 / "train").iterdir())[0] + "\n")
    manifest = prepared_then_gone("av2", av2, {"train": tmp_path / "one_log.txt"})
    mine = DataSplit.of(manifest)
    assert mine.kind is SplitKind.SPLIT_FILES and mine.describe() == (
        "your split files (`--split-file` train=av2_one_log.txt)"
    )
    theirs = {split: require_split_file(f"nuscenes_geo_{split}.txt") for split in ("train", "val")}
    manifest = prepared_then_gone("nuscenes", synth_raw / "nuscenes", theirs, version="v1.0-mini")
    assert manifest["parameters"]["split_file_names_sha256"] == STREAMMAPNET_SPLITS["nuscenes"]
    split = DataSplit.of(manifest)
    assert split.kind is SplitKind.STREAMMAPNET and split.describe() == (
        "StreamMapNet's geographically disjoint split (`--split-file` train=nuscenes_nuscenes_geo_train.txt, "
        "val=nuscenes_nuscenes_geo_val.txt)"
    )
    # the same manifest as an earlier version wrote it: the files gone, whose split it is is unknown
    del manifest["parameters"]["split_file_names_sha256"]
    earlier = DataSplit.of(manifest)
    assert earlier.kind is SplitKind.UNSURE_FILES
    assert "nuscenes_nuscenes_geo_train.txt not found, nuscenes_nuscenes_geo_val.txt not found" in \
        earlier.describe()  # fmt: skip


def require_split_file(name: str) -> Path:
    path = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "splits" / name
    if not path.is_file():
        pytest.skip(f"StreamMapNet's split file is not at {path} (../shared/data/splits beside the repo)")
    return path


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


# ---------------------------------------------------------------------------------------------------
# Which split a block's data is on, end to end: runs scored by `cli score --out` (no training) on
# synthetic data prepared on its own split, by the geographic scheme, from the user's split files and
# from StreamMapNet's


def val_graphs_run(data: Path, run: Path) -> None:
    """A run folder of `cli score --out`: the val frames' ground truth, each frame's last edge dropped."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from benchmark.graph_table import graphs_from_table, read_graph_table
    from benchmark.score import score
    from pipeline import io

    frames = io.read_table(data, "frames", columns=["frame_id", "split"]).to_pylist()
    val = {frame["frame_id"] for frame in frames if frame["split"] == "val"}
    gt = graphs_from_table(read_graph_table(data), data)
    rows = [{"frame_id": f, "x": g.x.tolist(), "y": g.y.tolist(), "src": g.src[:-1].tolist(),
             "dst": g.dst[:-1].tolist()} for f, g in sorted(gt.items()) if f in val]  # fmt: skip
    predictions = data.parent / f"{run.name}_predictions.parquet"
    pq.write_table(pa.Table.from_pylist(rows, io.SCHEMAS["graphs"]), predictions)
    score(predictions, data, out=run, split="val")


@pytest.fixture(scope="module")
def split_report(synth_raw, tmp_path_factory) -> dict:
    from benchmark.report.writer import write_report
    from pipeline.prepare import prepare
    from pipeline.synth import synth
    from pipeline.targets import TargetOptions

    root = tmp_path_factory.mktemp("split_report")
    av2 = synth_raw / "av2" / "sensor"
    logs = {split: sorted(p.name for p in (av2 / split).iterdir()) for split in ("train", "val")}
    for split, names in logs.items():
        (root / f"my_{split}.txt").write_text("\n".join(names) + "\n")
    datas = {"own": root / "own", "geo": root / "geo", "files": root / "files"}
    prepare("av2", av2, datas["own"], TargetOptions())
    prepare("av2", av2, datas["geo"], TargetOptions(), split_scheme="geographic", geo_cell=50.0, geo_seed=3)
    prepare("av2", av2, datas["files"], TargetOptions(),
            split_files={split: root / f"my_{split}.txt" for split in ("train", "val")})  # fmt: skip
    splits = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "splits"
    if (splits / "nuscenes_geo_train.txt").is_file():
        # synth's scenes are v1.0-mini's; of its first five training scenes StreamMapNet's files put
        # scene-0757 and scene-0796 in val
        synth(root / "raw", logs=6, frames_per_log=2, frame_period=1.0, worlds=1, val_frames_per_log=2)
        datas["streammapnet"] = root / "streammapnet"
        theirs = {split: splits / f"nuscenes_geo_{split}.txt" for split in ("train", "val")}
        prepare("nuscenes", root / "raw" / "nuscenes", datas["streammapnet"], TargetOptions(),
                version="v1.0-mini", split_files=theirs)  # fmt: skip
    for name, data in datas.items():
        val_graphs_run(data, root / "runs" / name)
    report = write_report([root / "runs"], root / "report", reference="paper", draws=0)
    geo_buffer = json.loads((datas["geo"] / "manifest.json").read_text())["parameters"]["geo_buffer"]
    return {"report": report, "text": report.path.read_text(), "geo_buffer": geo_buffer}


def block_of(split_report: dict, run: str) -> tuple[str, list]:
    """The report.md section of the block that holds `run` (from its `## ` heading to the next), and the
    paper's tables shown beside it (Report.references)."""
    text, report = split_report["text"], split_report["report"]
    (index,) = [i for i, block in enumerate(report.blocks) if [r.name for r in block.runs] == [run]]
    sections = re.split(r"^(?=## )", text, flags=re.M)
    (part,) = [s for s in sections if s.startswith(f"## {report.blocks[index].title}\n")]
    return part, report.references[index]


def test_a_geographic_split_never_stands_beside_the_papers_rows(split_report):
    own, own_references = block_of(split_report, "own")
    assert "#### Reference: the paper's Tab. 1" in own and "paper `tab:modeling`" in own  # the contrast
    assert [title for title, _, _ in own_references][0].startswith("Reference (paper, 24 epochs")
    geo, geo_references = block_of(split_report, "geo")
    assert geo_references == [] and "#### Reference" not in geo and "paper `" not in geo
    heading, buffer = geo.splitlines()[0], split_report["geo_buffer"]  # the window's diagonal, 67.08 m
    assert f", val split of the geographic scheme (`--split-scheme geographic`, 50 m cells, {buffer:.1f} m " \
           "buffer, seed 3), " in heading  # fmt: skip
    assert "the paper measured no model on a split made so, so none of its rows stand beside" in geo
    assert "the paper's rows are context" not in geo  # the synthetic data's note is of rows not shown
    # its own section: after every block on a dataset's own split, in the summary by name
    titles = [block.title for block in split_report["report"].blocks]
    assert titles.index(heading[3:]) > titles.index(own.splitlines()[0][3:])
    summary = split_report["text"].split("\n\n")[1]
    assert "On synthetic av2 (val split of the geographic scheme) the one scored run, geo " in summary


def test_split_files_are_labelled_as_the_users_not_as_geographic(split_report):
    files, references = block_of(split_report, "files")
    heading = files.splitlines()[0]
    assert ", val split of your split files (`--split-file` train=my_train.txt, val=my_val.txt), " in heading
    assert "geographic" not in files.replace("geographically", "")
    assert references == [] and "#### Reference" not in files and "paper `" not in files
    assert "the paper has no table on them" in files


def test_streammapnets_split_stands_beside_tab_newsplit_alone(split_report):
    if "streammapnet" not in [run.name for block in split_report["report"].blocks for run in block.runs]:
        pytest.skip("StreamMapNet's split files are not in ../shared/data/splits")
    part, references = block_of(split_report, "streammapnet")
    assert "val split of StreamMapNet's geographically disjoint split (`--split-file` " \
           "train=nuscenes_geo_train.txt, val=nuscenes_geo_val.txt)" in part.splitlines()[0]  # fmt: skip
    assert re.findall(r"paper `(tab:\w+)`", part) == ["tab:newsplit"] * 4
    assert [title for title, _, _ in references] == [
        "Reference (paper, the recipe of tab:modeling): the paper's the four modelings on a geographic split "
        "of nuScenes (`tab:newsplit`), on nuScenes, camera input, 30 x 60 m range"
    ]
