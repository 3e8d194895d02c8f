"""The prediction formats of `cli score` (benchmark/formats/): each one's detection by content, `--format
auto` (the default) choosing one reader and refusing in one line a file that none recognises, the frames a
reader gives the metrics, and the old modules gone."""

from __future__ import annotations

import importlib.util
import json
import pickle
import re
import shutil
import typing
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from test_score_external import (
    CGNET_CENTERLINE,
    MAPTRV2_CENTERLINE,
    TRUNK,
    vector,
    write_prepared,
    write_results,
)
from typer.testing import CliRunner

import cli
from benchmark import formats
from benchmark.formats.base import FormatError, GroundTruth, Options, Source
from benchmark.graph_table import graph_row, graphs_from_table, read_graph_table
from benchmark.metric.frame import Frame
from benchmark.score import score
from pipeline.io import SCHEMAS
from pipeline.lane_graph import LaneGraph

REPO = Path(__file__).resolve().parents[1]
LANE = LaneGraph(TRUNK[:, 0].astype(np.float32), TRUNK[:, 1].astype(np.float32), np.array([0, 1], np.int32),
                 np.array([1, 2], np.int32))  # fmt: skip


@pytest.fixture
def files(tmp_path) -> dict[str, Path]:
    """One file of each kind, each under a name that says another kind: detection reads the content."""
    out = {}
    table = pa.Table.from_pylist([graph_row("f/a", LANE)], SCHEMAS["graphs"])
    pq.write_table(table, out.setdefault("graph table", tmp_path / "graphs.json"))
    (tmp_path / "shards").mkdir()
    pq.write_table(table, out.setdefault("folder of shards", tmp_path / "shards") / "part-0.parquet")
    one = [{"sample_token": "t", "vectors": [vector(TRUNK, 0.9, MAPTRV2_CENTERLINE)]}]
    out["maptrv2"] = write_results(tmp_path / "maptrv2.parquet", one)
    divider = [{"sample_token": "t", "vectors": [vector(TRUNK, 0.9, {"cls_name": "divider", "type": 0})]}]
    out["maptrv2 divider"] = write_results(tmp_path / "divider.pkl.txt", divider)
    one = [{"sample_token": "t", "vectors": [vector(TRUNK, 0.9, CGNET_CENTERLINE)]}]
    out["cgnet"] = write_results(tmp_path / "cgnet.parquet", one)
    lane = [{"sample_token": "t", "vectors": [vector(TRUNK, 0.9, {"cls_name": "lane", "type": 7})]}]
    out["unknown classes"] = write_results(tmp_path / "lane.json", lane)
    out["no vectors"] = write_results(tmp_path / "empty.json", [{"sample_token": "t", "vectors": []}])
    out["no samples"] = write_results(tmp_path / "none.json", [])
    (out.setdefault("text", tmp_path / "notes.parquet")).write_text("not a prediction file")
    (out.setdefault("broken JSON", tmp_path / "broken.json")).write_text('{"results": [')
    (out.setdefault("no results", tmp_path / "meta.json")).write_text('{"meta": {}}')
    (out.setdefault("pickle", tmp_path / "results.json")).write_bytes(pickle.dumps({"results": []}))
    submission = {("val", "s", "1"): {"predictions": {"lane_centerline": [], "topology_lclc": np.zeros(0)}}}
    (out.setdefault("openlanev2", tmp_path / "sub.json")).write_bytes(pickle.dumps({"results": submission}))
    records = [{"split": "val", "segment_id": "s", "timestamp": "1", "predictions": {}}]
    out["openlanev2 JSON"] = write_results(tmp_path / "sub.pkl", records)
    return out


DETECTED = {
    "graph table": ["graph"], "folder of shards": ["graph"], "maptrv2": ["maptrv2"],
    "maptrv2 divider": ["maptrv2"], "cgnet": ["cgnet"], "unknown classes": [], "no vectors": [],
    "no samples": [], "text": [], "broken JSON": [], "no results": [], "pickle": [],
    "openlanev2": ["openlanev2"], "openlanev2 JSON": ["openlanev2"],
}  # fmt: skip


def test_each_format_detects_its_own_files_by_content_alone(files):
    detected = {kind: [fmt.name for fmt in formats.FORMATS if fmt.detect(Source.of(path))]
                for kind, path in files.items()}  # fmt: skip
    assert detected == DETECTED


def test_auto_picks_one_reader_and_refuses_a_file_none_recognises_in_one_line(files, tmp_path):
    for kind, path in files.items():
        if DETECTED[kind]:
            assert formats.choose(Source.of(path)).name == DETECTED[kind][0]
    for kind in ("unknown classes", "text", "broken JSON", "no results"):
        with pytest.raises(FormatError) as refused:
            formats.choose(Source.of(files[kind]))
        assert str(refused.value) == (
            f"{files[kind]}: no format recognises its content (tried graph, maptrv2, cgnet, openlanev2); "
            "pass --format NAME to hear why that one does not read it"
        )
    # a result file without vectors is either codebase's: told apart by nothing, named by the user
    with pytest.raises(FormatError) as refused:
        formats.choose(Source.of(files["no vectors"]))
    assert str(refused.value) == (
        f"{files['no vectors']}: no vectors to tell MapTRv2 from CGNet: pass --format maptrv2 or cgnet"
    )
    with pytest.raises(FormatError) as refused:  # what either reader says of it
        formats.choose(Source.of(files["no samples"]))
    assert str(refused.value) == f"{files['no samples']}: no sample in its results list"
    with pytest.raises(FormatError, match=r'^\S*results.json: not an OpenLane-V2 submission: no "results"'):
        formats.choose(Source.of(files["pickle"]))  # the one pickle format's reader says why not
    with pytest.raises(FormatError, match=r"^\S*gone.json: no such file or folder$"):
        formats.choose(Source.of(tmp_path / "gone.json"))
    # a named format is taken as named, its content unlooked at (its reader says what is wrong)
    assert formats.choose(Source.of(files["text"]), "cgnet").name == "cgnet"
    expected = "graph, maptrv2, cgnet, openlanev2, auto"
    with pytest.raises(FormatError, match=f"^--format bogus: expected one of {expected}$"):
        formats.choose(Source.of(files["text"]), "bogus")


def test_the_json_is_parsed_once_whichever_format_asks(files, monkeypatch):
    source, loads = Source.of(files["cgnet"]), []
    original = json.load
    monkeypatch.setattr(json, "load", lambda file: loads.append(1) or original(file))
    assert formats.choose(source).name == "cgnet" and source.json()["results"][0]["sample_token"] == "t"
    assert len(loads) == 1
    # the reader takes it last and lets it go: the parsed file is not held while the frames are scored
    assert source.json(keep=False) is not None and len(loads) == 1 and source._parsed is None


def test_auto_is_the_default_and_scores_as_the_named_format(tmp_path):
    data, token = write_prepared(tmp_path / "data", "nuscenes", LANE)
    noisy = TRUNK + [[0.25, 0.0], [0.0, 0.0], [-0.25, 0.0]]  # exact in the graph table's float32
    wrong = vector(TRUNK[::-1], 0.35, MAPTRV2_CENTERLINE)  # under MapTRv2's kept score
    records = [{"sample_token": token, "vectors": [vector(noisy, 0.9, MAPTRV2_CENTERLINE), wrong]}]
    path = write_results(tmp_path / "nuscmap_results.json", records)
    by_default, named = score(path, data, bootstrap=0), score(path, data, fmt="maptrv2", bootstrap=0)
    assert by_default == named and by_default["external"]["format"] == "maptrv2"
    run = CliRunner().invoke(cli.app, ["score", "--pred", str(path), "--gt", str(data), "--bootstrap", "0",
                                       "--out", str(tmp_path / "run")])  # fmt: skip
    assert run.exit_code == 0, run.output
    assert f"{path} (maptrv2, centerline above 0.4) against {data}" in run.output
    # the graph table it wrote, under a JSON name: read as the graph table its content is
    table = tmp_path / "graphs.json"
    shutil.copy(tmp_path / "run" / "predictions.parquet", table)
    from_table = score(table, data, bootstrap=0)
    assert "external" not in from_table
    f1 = by_default["directed"]["topo"]["f1"]
    assert 0 < f1 < 1 and from_table["directed"]["topo"]["f1"] == pytest.approx(f1, abs=1e-6)
    refused = CliRunner().invoke(cli.app, ["score", "--pred", str(tmp_path / "data" / "manifest.json"),
                                           "--gt", str(data)])  # fmt: skip
    error = [line for line in refused.output.splitlines() if line.strip()]
    assert refused.exit_code == 1 and len(error) == 1 and "manifest.json: no format recognises" in error[0]


def test_a_reader_gives_each_frame_as_the_metrics_take_it(tmp_path):
    data, token = write_prepared(tmp_path / "data", "nuscenes", LANE)
    gt = GroundTruth(data, graphs_from_table(read_graph_table(data), data), None, 1)
    records = [{"sample_token": token, "vectors": [vector(TRUNK[:2], 0.9, MAPTRV2_CENTERLINE),
                                                   vector(TRUNK[1:], 0.6, MAPTRV2_CENTERLINE)]}]  # fmt: skip
    fmt, source = formats.checked(write_results(tmp_path / "r.json", records))
    (prediction,) = fmt.read(source, Options(), gt)
    assert prediction.frame_id == "nuscenes/scene-0001/1000" and len(prediction.graph.src) > 0
    assert prediction.edge_scores.shape == prediction.graph.src.shape
    assert set(prediction.edge_scores.tolist()) == {0.9, 0.6}
    frame = prediction.frame(gt.graphs[prediction.frame_id])
    assert isinstance(frame, Frame) and frame.pred_scores is prediction.edge_scores
    assert frame.pred is prediction.graph and frame.gt is gt.graphs[prediction.frame_id]
    fmt, source = formats.checked(data / "graphs")
    (prediction,) = fmt.read(source, Options(), gt)
    assert fmt.name == "graph" and prediction.edge_scores is None
    assert np.array_equal(prediction.graph.x, LANE.x) and prediction.frame(LANE).pred_scores is None


def test_options_a_format_does_not_take_are_refused_before_any_work(files):
    with pytest.raises(FormatError, match="^--min-score, --sweep: only for a result file of another"):
        formats.checked(files["graph table"], options=Options(min_score=0.5, sweep=True))
    with pytest.raises(FormatError, match=r"^--class-name divider: not a cgnet class \(centerline\)$"):
        formats.checked(files["cgnet"], options=Options(class_name="divider"))
    assert formats.checked(files["maptrv2"], options=Options(class_name="divider"))[0].name == "maptrv2"


def test_cli_format_choices_are_the_formats_and_auto():
    hints = typing.get_type_hints(cli.score)
    assert typing.get_args(hints["format_"]) == (formats.AUTO, *(fmt.name for fmt in formats.FORMATS))


# what issue 60 removed: the modules, and tables.py's variant_tables (benchmark/report/variant_tables.py,
# report.md's tables of the other metrics, stays)
OLD_MODULES = ("benchmark.predictions", "benchmark.external", "benchmark.metric.variants")
OLD_NAMES = re.compile(
    r"\bbenchmark[./](predictions|external|metric[./]variants)\b(?!_)"
    r"|\bfrom benchmark import [^\n]*\b(predictions|external)\b(?!_)"
    r"|\bfrom benchmark\.metric import [^\n]*\bvariants\b(?!_)"
    r"|\b(benchmark[./])?tables\.variant_tables\b|\bfrom benchmark\.tables import [^\n]*\bvariant_tables\b"
)
# where the code, its tools, docs and build name modules; CHANGELOG.md is history and may
NAMING_PLACES = (*(f"{d}/**/*.py" for d in ("benchmark", "baselines", "pipeline", "tools", "tests")),
                 "docs/**/*.md", ".ci/*", "cli.py", "README.md", "Makefile", "pyproject.toml")  # fmt: skip


def old_names_in(root: Path) -> list[str]:
    """'path: the old name' for each place under `root` that names a removed module or function, imports
    of several names and parenthesised ones included."""
    found = []
    for path in sorted({p for place in NAMING_PLACES for p in root.glob(place) if p.is_file()}):
        text = path.read_text(errors="replace")
        # a parenthesised import on one line, for the patterns that read one line
        imports = re.sub(r"import \(([^()]*)\)", lambda m: "import " + " ".join(m.group(1).split()), text)
        found += [f"{path.relative_to(root)}: {m.group(0)}" for m in OLD_NAMES.finditer(imports)]
    return found


def test_the_old_modules_are_gone_and_named_nowhere():
    import benchmark.tables

    for old in OLD_MODULES:
        assert importlib.util.find_spec(old) is None, old
    assert not hasattr(benchmark.tables, "variant_tables")
    naming = [place for place in old_names_in(REPO) if not place.startswith("tests/test_formats.py")]
    assert not naming, naming


def test_the_old_names_check_sees_each_way_of_naming_them(tmp_path):
    named = {
        "pipeline/a.py": "from benchmark.metric import (\n    table,\n    variants,\n)\n",
        "tools/b.py": "import benchmark.metric.variants as v\n",
        "docs/guide/c.md": "see `benchmark/external.py`\n",
        ".ci/run": "python -c 'from benchmark import frames, predictions'\n",
        "Makefile": "\tpython -m benchmark.predictions\n",
        "pyproject.toml": '"benchmark/metric/variants.py" = ["E501"]\n',
        "cli.py": "from benchmark.tables import finish, variant_tables\n",
        "baselines/d.py": "rows = benchmark.tables.variant_tables(result)\n",
    }
    for name, text in named.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    assert sorted(place.split(":")[0] for place in old_names_in(tmp_path)) == sorted(named)
    fine = (
        "from benchmark.report.variant_tables import variant_sections\nfrom benchmark.tables import finish\n"
        "from benchmark.report.measured_tables import external_notes\nbenchmark/report/variant_tables.py\n"
        "from benchmark.formats import graph  # external\n"
    )
    for name in named:
        (tmp_path / name).write_text(fine)
    assert old_names_in(tmp_path) == []
    (tmp_path / "CHANGELOG.md").write_text("`benchmark/predictions.py` is gone\n")  # history
    assert old_names_in(tmp_path) == []
