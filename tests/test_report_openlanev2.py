"""`cli report --reference paper`'s OpenLane-V2 section: the paper's `tab:toponet` (six rows of mIoU at
50 x 100 m, each with where its number comes from) in a section of its own, with the runs scored on
OpenLane-V2 data at that range beside it; runs at another range or on other data left out with a line
that says why, and OpenLane-V2 runs in no AV2 or nuScenes table.

The runs are `cli score --out` run folders (no training) on `cli synth`'s data: `wide`, a graph table on
its OpenLane-V2 layout prepared at 50 x 100 m (`cli prepare --dataset openlanev2 --range 50x100`), and
`submission`, an OpenLane-V2 submission on the same; `narrow`, a graph table on it prepared at 30 x 60 m;
`av2`, one on its AV2 logs prepared at 30 x 60 m.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from benchmark.report.paper_tables import (
    OPENLANEV2_BLOCK_NOTE,
    OPENLANEV2_NOTE,
    openlanev2_data,
    reference_table,
)
from benchmark.report.reference import load_reference
from benchmark.report.runs import Block

LATEX = Path(__file__).resolve().parents[1].parent / "shared" / "paper" / "lanegap.tex"
PAPER = {"HDMapNet": 18.3, "STSU": 31.1, "VectorMapNet": 25.0, "MapTR": 35.7, "TopoNet": 39.0,
         "LaneGAP": 40.6}  # fmt: skip
SECTION = "## OpenLane-V2 (the paper's `tab:toponet`)"


def section(text: str, start: str) -> str:
    """From the line that starts with `start` to the next heading of the same or a higher level."""
    at = text.index(start)
    level = len(start) - len(start.lstrip("#"))
    end = re.search(rf"^#{{1,{level}}} ", text[at + len(start) :], re.M)
    return text[at : at + len(start) + end.start()] if end else text[at:]


def first_table(text: str) -> tuple[list[str], list[list[str]]]:
    """The header and rows of the first markdown table in text."""
    lines = text[text.index("\n|") + 1 :].split("\n\n")[0].splitlines()
    cells = [[cell.strip() for cell in line.strip("|").split("|")] for line in lines]
    return cells[0], cells[2:]


def test_the_toml_holds_the_papers_six_rows_with_their_origin():
    table = load_reference()["tab:toponet"]
    assert (table.meta["dataset"], table.meta["range"]) == ("openlanev2", "50x100")
    assert {row["method"]: row["miou"] for row in table.rows} == PAPER
    assert [row["method"] for row in table.rows] == list(PAPER)  # the LaTeX's column order
    header, rows = reference_table(table, table.rows)
    assert header == ["reference", "method", "modeling", "mIoU"]
    assert [row[1:] for row in rows] == [
        ["HDMapNet", "pixel-wise", "18.3"], ["STSU", "piece-wise", "31.1"],
        ["VectorMapNet", "piece-wise", "25.0"], ["MapTR", "piece-wise", "35.7"],
        ["TopoNet", "piece-wise", "39.0"], ["LaneGAP", "path-wise", "40.6"],
    ]  # fmt: skip
    assert [row[0] for row in rows] == ["paper `tab:toponet`, from the TopoNet paper"] * 5 + [
        "paper `tab:toponet`, the paper's own: TopoNet learning paths, on TopoNet's recipe"
    ]
    assert table.describe() == "the paper's comparison on OpenLane-V2 (`tab:toponet`), on OpenLane-V2, " \
                               "50 x 100 m range"  # fmt: skip


def test_tab_toponet_matches_the_latex():
    """Every number and modeling against the LaTeX's table; a starred column (taken from the TopoNet
    paper, as its caption says) is one whose origin names TopoNet."""
    if not LATEX.is_file():
        pytest.skip(f"the paper's LaTeX source is not at {LATEX} (../shared/paper beside the repo)")
    tex = LATEX.read_text()
    at = tex.index(r"\label{tab:toponet}")
    body = tex[tex.rindex(r"\begin{tabular}", 0, at) : at]
    heads = re.search(r"Method\s*&(.*?)\\\\", body, re.S)[1].split("&")
    values = re.search(r"mIoU\s*&(.*?)\\\\", body, re.S)[1].split("&")
    caption = body[body.index(r"\caption") :]
    assert r"$^{*}$ means the results are directly taken from TopoNet paper" in caption
    table = load_reference()["tab:toponet"]
    assert len(heads) == len(values) == len(table.rows) == 6
    for head, value, row in zip(heads, values, table.rows):
        method = re.match(r"\s*(\w+)", head)[1]
        assert method == row["method"]
        assert float(re.sub(r"\\textbf\{([^}]*)\}", r"\1", value)) == row["miou"], method
        assert ("^{*}" in head) == ("TopoNet paper" in row["origin"]), method
        modeling = re.search(r"_\{\\text\{(\w+)\}\}", head)
        # LaneGAP's column has no subscript; the text names it LaneGAP^dagger_path
        expected = modeling[1] if modeling else "path"
        assert row["modeling"] == f"{expected}-wise", method
    assert r"$50m \times 100m$ perception range" in tex  # the range, from the text beside the table


def test_real_data_is_labelled_by_its_root_folder(tmp_path):
    root = tmp_path / "OpenLane-V2"
    root.mkdir()
    manifest = {"dataset": "openlanev2", "root": str(root)}
    assert openlanev2_data(Block("openlanev2", None, "val", [], manifest, synthetic=False)) == (
        "ours, OpenLane-V2 `OpenLane-V2`"
    )
    subset_a = {**manifest, "parameters": {"subset": "A"}}  # `cli prepare --subset A`
    assert openlanev2_data(Block("openlanev2", None, "val", [], subset_a, synthetic=False)) == (
        "ours, OpenLane-V2 `OpenLane-V2`, subset A"
    )
    assert openlanev2_data(Block("openlanev2", None, "val", [], manifest, synthetic=True)) == (
        "ours, synthetic OpenLane-V2 (`cli synth`)"
    )
    gone = {"dataset": "openlanev2", "root": str(tmp_path / "moved")}
    assert openlanev2_data(Block("openlanev2", None, "val", [], gone, synthetic=None)) == (
        "ours, OpenLane-V2 `moved` (its raw data is gone)"
    )


# ---------------------------------------------------------------------------------------------------
# The section in a report


def scored_run(data: Path, run: Path) -> None:
    """A run folder of `cli score --out`: the val frames' ground truth, each frame's last edge dropped."""
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


def submission_run(data: Path, run: Path) -> None:
    """A run folder of `cli score --out` of an OpenLane-V2 submission (write_submission, as `cli eval`
    writes one): the val frames' annotated lanes, every third lane and its links dropped."""
    import numpy as np

    from benchmark.formats.openlanev2_submission import write_submission
    from benchmark.score import score
    from pipeline import io
    from pipeline.records import AnnotatedLanes

    frames = io.read_table(data, "frames", columns=["frame_id", "split"]).to_pylist()
    val = [frame["frame_id"] for frame in frames if frame["split"] == "val"]
    keys, submitted = io.read_openlanev2_keys(data), {}
    for frame_id, lanes in io.read_annotated_lanes(data, val).items():
        keep = [i for i in range(len(lanes)) if i % 3 != 2]
        points, ids = [lanes.points[i] for i in keep], [lanes.ids[i] for i in keep]
        links, confidence = lanes.links[np.ix_(keep, keep)], np.linspace(1.0, 0.5, len(keep))
        submitted[keys[frame_id]] = AnnotatedLanes(points, links, ids, confidence)
    path = data.parent / f"{run.name}.pkl"
    write_submission(path, "two thirds of the lanes", submitted)
    score(path, data, out=run, split="val")


def prepare_openlanev2(raw: Path, out: Path, bev_range: str) -> None:
    """`cli prepare --dataset openlanev2` of `cli synth`'s OpenLane-V2 layout at a range."""
    from pipeline.geometry import Range
    from pipeline.prepare import prepare
    from pipeline.targets import TargetOptions

    prepare("openlanev2", raw / "openlanev2", out, TargetOptions(bev_range=Range.parse(bev_range)))


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> dict:
    from benchmark.report.writer import write_report
    from pipeline.prepare import prepare
    from pipeline.synth import synth
    from pipeline.targets import TargetOptions

    root = tmp_path_factory.mktemp("report_openlanev2")
    synth(root / "raw", logs=3, frames_per_log=2, seed=0, frame_period=1.0, worlds=1, val_frames_per_log=2)
    datas = {"wide": root / "ol_wide", "narrow": root / "ol_narrow", "av2": root / "av2"}
    prepare("av2", root / "raw" / "av2" / "sensor", datas["av2"], TargetOptions())
    for name, bev_range in (("wide", "50x100"), ("narrow", "30x60")):
        prepare_openlanev2(root / "raw", datas[name], bev_range)
    for name, data in datas.items():
        scored_run(data, root / "runs" / name)
    submission_run(datas["wide"], root / "runs" / "submission")
    report = write_report([root / "runs"], root / "report", reference="paper", draws=0)
    alone = write_report([root / "runs" / "av2"], root / "report_av2", reference="paper", draws=0)
    return {"root": root, "text": report.path.read_text(), "report": report,
            "av2_text": alone.path.read_text()}  # fmt: skip


def run_metrics(made: dict, name: str) -> dict:
    return json.loads((made["root"] / "runs" / name / "metrics.json").read_text())


def test_the_section_shows_the_papers_rows_and_our_run_at_its_range(made):
    part = section(made["text"], SECTION)
    assert OPENLANEV2_NOTE in part
    header, rows = first_table(section(part, "#### Reference:"))
    assert section(part, "#### Reference:").splitlines()[0] == (
        "#### Reference: the paper's comparison on OpenLane-V2 (`tab:toponet`), on OpenLane-V2, "
        "50 x 100 m range"
    )
    assert {row[1]: float(row[3]) for row in rows} == PAPER
    assert not any("**" in cell for row in rows for cell in row)  # never bolded
    header, rows = first_table(section(part, "#### Ours:"))
    assert header == ["data", "run", "method", "modality", "split", "frames", "mIoU"]
    wide, submission = run_metrics(made, "wide"), run_metrics(made, "submission")
    for metrics in (wide, submission):
        assert metrics["metric_params"]["bev_range"] == "50x100" and 0 < metrics["miou"] < 1
    synthetic = "ours, synthetic OpenLane-V2 (`cli synth`)"
    assert rows == [
        [synthetic, "submission", "OpenLane-V2 submission `two thirds of the lanes` (external)", "unknown",
         "val split", str(submission["frames"]), f"{100 * submission['miou']:.1f}"],
        [synthetic, "wide", "graph table (external)", "unknown", "val split", str(wide["frames"]),
         f"{100 * wide['miou']:.1f}"],
    ]  # fmt: skip
    assert "A run on synthetic OpenLane-V2 data (`cli synth`) is on worlds of its own" in part


def test_runs_at_another_range_or_on_other_data_are_left_out_with_a_line(made):
    part = section(made["text"], SECTION)
    assert run_metrics(made, "narrow")["metric_params"]["bev_range"] == "30x60"
    left_out = [line for line in part.splitlines() if line.startswith("- Left out")]
    assert left_out == [
        "- Left out: 1 run on OpenLane-V2 data measured at 30 x 60 m, not at the paper's 50 x 100 m "
        "(`cli prepare --dataset openlanev2 --range 50x100`).",
        "- Left out: 1 run on other data (AV2: 1): the paper's table is on OpenLane-V2.",
    ]
    assert "narrow" not in section(part, "#### Ours:").split("- Left out")[0]


def test_openlanev2_runs_stand_in_no_av2_table_and_the_av2_tables_beside_no_openlanev2_block(made):
    text, report = made["text"], made["report"]
    by_run = {run.name: block for block in report.blocks for run in block.runs}
    assert [by_run[name].dataset for name in ("wide", "submission", "narrow", "av2")] == \
        ["openlanev2"] * 3 + ["av2"]  # fmt: skip
    av2_block = section(text, f"## {by_run['av2'].title}")
    _, rows = first_table(section(av2_block, "### Main table"))
    assert [row[0] for row in rows if not row[0].startswith(("constant", "best constant"))] == ["av2"]
    assert "paper `tab:modeling`" in av2_block  # the AV2 block has the paper's AV2 rows beside it
    for names in (["submission", "wide"], ["narrow"]):
        part = section(text, f"## {by_run[names[0]].title}")
        assert OPENLANEV2_BLOCK_NOTE in part
        assert "#### Reference" not in part and "paper `" not in part
        _, rows = first_table(section(part, "### Main table"))
        assert [row[0] for row in rows] == names
    index = {block.title: i for i, block in enumerate(report.blocks)}
    assert [t for t, _, _ in report.references[index[by_run["wide"].title]]] == []
    assert "- `tab:toponet`" not in section(text, "## The paper's tables not shown")


def test_without_an_openlanev2_run_the_table_is_listed_as_not_shown(made):
    text = made["av2_text"]
    assert SECTION not in text
    assert "- `tab:toponet`, comparison on OpenLane-V2: shown in a section of its own when a run is on " \
           "OpenLane-V2 data (`cli prepare --dataset openlanev2`), beside those runs measured at " \
           "50 x 100 m." in section(text, "## The paper's tables not shown")  # fmt: skip


def test_each_reason_to_leave_a_run_out_is_one_line_with_its_count(tmp_path):
    """openlanev2_runs on runs as runs.py reads them: two other ranges, a run without scores, one whose
    data is not found (its dataset unknown), and the one kept."""
    from benchmark.report.paper_tables import openlanev2_runs
    from benchmark.report.runs import Run

    def run(name: str, dataset: str, bev_range: str | None) -> Run:
        metrics = None if bev_range is None else {"metric_params": {"bev_range": bev_range}, "miou": 0.25}
        return Run(tmp_path / name, name, metrics, None, None, dataset, "val", None)

    ours = [run("a", "openlanev2", "30x60"), run("b", "openlanev2", "20x40"), run("c", "openlanev2", "30x60"),
            run("crashed", "openlanev2", None), run("kept", "openlanev2", "50x100")]  # fmt: skip
    gone = Block("unknown", None, "val", [run("x", "unknown", "50x100")])  # its data not found
    blocks = [Block("openlanev2", tmp_path, "val", ours), gone]
    kept, lines = openlanev2_runs(blocks, "50x100")
    assert [(block.dataset, r.name) for block, r in kept] == [("openlanev2", "kept")]
    assert lines == [
        "Left out: 3 runs on OpenLane-V2 data measured at 30 x 60 m (2), 20 x 40 m (1), not at the paper's "
        "50 x 100 m (`cli prepare --dataset openlanev2 --range 50x100`).",
        "Left out: 1 run on other data (data not found: 1): the paper's table is on OpenLane-V2.",
        "Left out: 1 run on OpenLane-V2 data without scores (crashed).",
    ]
