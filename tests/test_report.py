"""`cli report` and `cli viz` on small finished runs, read back.

The runs, made once for the module: `lanegap_lidar`, LaneGAP tiny (LiDAR, with a one-layer decoder of
8 queries: seconds on two loaded cores) trained for one epoch (3 steps) on a small synthetic AV2 split
and scored by `cli eval` (its floor included); `path_oracle`, the same run folder whose predictions are
the validation ground truth with edges dropped and shifted 0.2 m, scored with the project's metric and
saved as trained for 2 epochs (so the two differ in `train.epochs` alone, and have different, non-zero
scores); `lanegap_nusc`, the first checkpoint scored by `cli eval` on the nuScenes copy of the data;
`crashed`, a run whose training wrote its config and stopped.
"""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from PIL import Image
from typer.testing import CliRunner

from benchmark.graph_table import graphs_from_table, read_graph_table
from benchmark.metric import bootstrap
from benchmark.report.measured_tables import JUNCTION_BUCKETS, junction_count
from benchmark.report.paper_tables import REFERENCE_NOTE, SYNTHETIC_NOTE, UNKNOWN_ORIGIN_NOTE
from benchmark.report.reference import load_reference
from benchmark.report.writer import write_report
from benchmark.score import score_frames, score_pairs
from cli import app
from pipeline import io
from pipeline.lane_graph import LaneGraph

AV2, NUSC = "## av2 (synthetic, `cli synth`):", "## nuscenes (synthetic, `cli synth`):"  # block headings
SCORE_KEYS = [(mode, metric, stat) for mode in ("directed", "undirected")
              for metric in ("junction_topo", "topo") for stat in ("precision", "recall", "f1")]  # fmt: skip


def graph_rows(graphs: dict[str, LaneGraph]) -> pa.Table:
    rows = [
        {"frame_id": f, "x": g.x.tolist(), "y": g.y.tolist(), "src": g.src.tolist(), "dst": g.dst.tolist()}
        for f, g in sorted(graphs.items())
    ]
    return pa.Table.from_pylist(rows, io.SCHEMAS["graphs"])


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> dict:
    from baselines.evaluate import evaluate
    from baselines.models import resolve_config
    from baselines.train import train
    from benchmark.metric.params import MetricParams
    from benchmark.roundtrip import roundtrip
    from pipeline.prepare import prepare
    from pipeline.synth import synth
    from pipeline.targets import TargetOptions

    root = tmp_path_factory.mktemp("report")
    synth(root / "raw", logs=4, frames_per_log=4, seed=0, frame_period=1.0, worlds=1, val_frames_per_log=4)
    av2, nusc = root / "av2", root / "nusc"
    prepare("av2", root / "raw" / "av2" / "sensor", av2, TargetOptions())
    prepare("nuscenes", root / "raw" / "nuscenes", nusc, TargetOptions(), version="v1.0-mini")
    runs = root / "runs"
    model = runs / "lanegap_lidar"
    small = ["train.log_every=1", "decoder.layers=1", "decoder.num_paths=8", "decoder.ffn_channels=64"]
    train(resolve_config("tiny", "lidar", epochs=1, overrides=small), av2, model)
    evaluate(model, av2, "val", "cpu")

    oracle = runs / "path_oracle"
    shutil.copytree(model, oracle)
    gt = graphs_from_table(read_graph_table(av2), av2)
    frames = sorted(graphs_from_table(read_graph_table(model / "predictions.parquet"), model).keys())
    predicted = {}
    for i, f in enumerate(frames):
        g, keep = gt[f], np.arange(len(gt[f].src)) % (2 + i % 3) != 0
        predicted[f] = LaneGraph(g.x + np.float32(0.2), g.y, g.src[keep], g.dst[keep])
    pq.write_table(graph_rows(predicted), oracle / "predictions.parquet")
    metrics = json.loads((oracle / "metrics.json").read_text())
    pairs = [(predicted[f], gt[f]) for f in frames]
    scores, counts = score_frames(pairs, MetricParams(**metrics["metric_params"]))
    bootstrap.add_intervals(scores, counts)
    bootstrap.write_frame_counts(oracle / bootstrap.FRAME_COUNTS, frames, counts)
    metrics.update({k: scores[k] for k in ("directed", "undirected", "miou")}, fps=2 * metrics["fps"])
    metrics["config"]["train"]["epochs"] = 2
    (oracle / "metrics.json").write_text(json.dumps(metrics))
    (oracle / "config.json").write_text(json.dumps(metrics["config"]))

    nusc_run = root / "nusc_runs" / "lanegap_nusc"
    nusc_run.parent.mkdir()
    shutil.copytree(model, nusc_run)
    evaluate(nusc_run, nusc, "mini_val", "cpu", floor=False)

    crashed = runs / "crashed"
    crashed.mkdir()
    for name in ("config.json", "run.json"):
        shutil.copy(model / name, crashed / name)
    trips = [root / f"roundtrip_{via}.json" for via in ("path", "piece")]
    for via, path in zip(("path", "piece"), trips):
        roundtrip(av2, via, path)
    out = root / "report"
    report = write_report([runs, nusc_run], out, trips, reference="paper")
    return {"root": root, "av2": av2, "runs": runs, "out": out, "report": report, "trips": trips,
            "text": (out / "report.md").read_text()}  # fmt: skip


def section(text: str, start: str) -> str:
    """The text from the heading that starts with `start` to the next heading of its level or above."""
    lines = text.splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith(start))
    level = len(start) - len(start.lstrip("#"))
    end = next((i for i in range(at + 1, len(lines)) if re.match(rf"#{{1,{level}}} ", lines[i])), len(lines))
    return "\n".join(lines[at:end])


def first_table(text: str) -> tuple[list[str], list[list[str]]]:
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("|"))
    block = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        block.append([cell.strip() for cell in line.strip("|").split("|")])
    return block[0], block[2:]


def number(cell: str) -> float:
    """The score of a cell, without its bold and its interval."""
    return float(cell.strip("*").split(" [")[0])


def run_metrics(made, name: str) -> dict:
    folder = made["root"] / "nusc_runs" / name if name == "lanegap_nusc" else made["runs"] / name
    return json.loads((folder / "metrics.json").read_text())


def test_every_table_is_there(made):
    text = made["text"]
    for heading in (AV2, "### Main table", "### mIoU", "### Ablation: epochs (`train.epochs`)",
                    "### Scores by junction count", "### Frames", "### F1 by run", NUSC,
                    "## Post-processing accuracy", "## Training loss"):  # fmt: skip
        assert any(line.startswith(heading) for line in text.splitlines()), heading


def test_main_table_holds_each_runs_metrics_json(made):
    for block, names in ((AV2, ["lanegap_lidar", "path_oracle"]), (NUSC, ["lanegap_nusc"])):
        header, rows = first_table(section(section(made["text"], block), "### Main table"))
        by_run = {row[0]: row for row in rows}
        assert {n for n in by_run if not n.startswith(("constant", "best constant", "crashed"))} <= set(names)
        for name in names:
            metrics, row = run_metrics(made, name), by_run[name]
            for (mode, metric, stat), cell in zip(SCORE_KEYS, row[4:16]):
                assert abs(number(cell) - 100 * metrics[mode][metric][stat]) <= 0.05 + 1e-9, (
                    name,
                    mode,
                    metric,
                )
            assert header[16:] == ["Params (M)", "GFLOPs", "FPS_net", "FPS"]
            assert abs(float(row[16]) - metrics["params"] / 1e6) <= 0.005 + 1e-9
            assert abs(float(row[17]) - metrics["gflops"]) <= 0.005 + 1e-9
            assert abs(float(row[18]) - metrics["fps_net"]) <= 0.05 + 1e-9
            assert abs(float(row[19]) - metrics["fps"]) <= 0.05 + 1e-9
            assert row[1:4] == ["LaneGAP", metrics["modeling"], "lidar"]
    # runs of the other dataset never share the block
    assert "lanegap_nusc" not in section(made["text"], AV2)
    assert "path_oracle" not in section(made["text"], NUSC)


def test_floor_rows_and_settings(made):
    av2 = section(made["text"], AV2)
    _, rows = first_table(section(av2, "### Main table"))
    prior = run_metrics(made, "lanegap_lidar")["floor"]["constant_prior"]
    (row,) = [r for r in rows if r[0] == "constant prior"]
    assert prior["frame_id"] in row[1]
    for (mode, metric, stat), cell in zip(SCORE_KEYS, row[4:16]):
        assert abs(number(cell) - 100 * prior[mode][metric][stat]) <= 0.05 + 1e-9
    _, settings = first_table(av2.split("sensor-blind floor")[-1])
    schedule = "set (preset or --epochs)"
    row = ["lanegap_lidar", "cpu", "fp32", "tiny", "1 / 1", schedule, "2", "1 x 1 x 2", "val"]
    assert row in settings  # the preset's batch, one process, one micro-batch
    assert "evaluated with `--no-floor`" in section(made["text"], NUSC)


def test_bold_is_the_best_f1_of_each_column(made):
    header, rows = first_table(section(section(made["text"], AV2), "### Main table"))
    runs = [r for r in rows if r[0] in ("lanegap_lidar", "path_oracle")]
    f1_columns = [i for i, name in enumerate(header) if name.endswith("F1")]
    assert len(f1_columns) == 4
    for col in f1_columns:
        values = [number(r[col]) for r in runs]
        assert max(values) > 0
        for r, value in zip(runs, values):
            assert r[col].startswith("**") == (value == max(values)), (header[col], r[0])
    assert not any("**" in cell for r in rows if r not in runs for cell in r)


def test_incomplete_run_appears_with_its_reason(made):
    _, rows = first_table(section(section(made["text"], AV2), "### Main table"))
    (row,) = [r for r in rows if r[0] == "crashed"]
    assert row[1].startswith("not scored:") and "no checkpoint.pt" in row[1] and "no metrics.json" in row[1]
    assert "1 run(s) have no scores: crashed" in made["text"]


def test_summary_names_the_leader_with_its_numbers(made):
    oracle, model = run_metrics(made, "path_oracle"), run_metrics(made, "lanegap_lidar")
    a, b = oracle["directed"]["topo"]["f1"], model["directed"]["topo"]["f1"]
    assert a > b
    expected = f"path_oracle leads on directed TOPO F1 ({100 * a:.1f} % vs {100 * b:.1f} % for lanegap_lidar"
    assert expected in made["text"].split("\n\n")[1]


def test_miou_ablation_and_roundtrip_tables(made):
    av2 = section(made["text"], AV2)
    _, rows = first_table(section(av2, "### mIoU"))
    for row in rows:
        assert abs(number(row[3]) - 100 * run_metrics(made, row[0])["miou"]) <= 0.05 + 1e-9
    header, rows = first_table(section(av2, "### Ablation: epochs"))
    assert [(r[0], r[1]) for r in rows] == [("1", "lanegap_lidar"), ("2", "path_oracle")]
    assert abs(number(rows[1][2]) - 100 * run_metrics(made, "path_oracle")["directed"]["topo"]["f1"]) <= 0.05
    _, rows = first_table(section(made["text"], "## Post-processing accuracy"))
    for row, path in zip(rows, made["trips"]):
        result = json.loads(path.read_text())
        assert row[1] == path.name and int(row[2]) == result["frames"]
        for (mode, metric, stat), cell in zip(SCORE_KEYS, row[3:15]):
            assert abs(number(cell) - 100 * result[mode][metric][stat]) <= 0.05 + 1e-9


def test_a_roundtrip_file_that_names_its_thresholds_params_is_read(tmp_path):
    """`cli roundtrip` and `cli score` name the thresholds `metric_params`, as metrics.json does (where
    `params` is the parameter count); a round trip written when they were `params` gives the same table."""
    from benchmark.metric.totals import score_graphs
    from benchmark.report.measured_tables import load_roundtrips, roundtrip_tables

    lane = LaneGraph(np.zeros(2), np.array([0.0, 5.0]), np.array([0], np.int32), np.array([1], np.int32))
    result = {**score_graphs([(lane, lane)]), "via": "path", "data": str(tmp_path / "prepared")}
    old = {("params" if key == "metric_params" else key): value for key, value in result.items()}
    paths = [tmp_path / "new.json", tmp_path / "old.json"]
    for path, content in zip(paths, (result, old)):
        path.write_text(json.dumps(content))
    tables = [roundtrip_tables(load_roundtrips([path]))[0] for path in paths]
    (_, _, new_rows, new_params), (_, _, old_rows, old_params) = tables
    assert "params" not in result and old_params == new_params == result["metric_params"]
    assert [row[2:] for row in old_rows] == [row[2:] for row in new_rows] and new_rows[0][1] == "new.json"


def test_the_papers_rows_stand_beside_the_measured_tables(made):
    """Tab. 1 and tab:iou under each dataset's block, tab:schedule beside the ablation of epochs,
    tab:postproc beside the round trips; every number read back equals the data file's."""
    from test_report_reference import assert_row_equals, numbers_of

    refs, text = load_reference(), made["text"]

    def check(part: str, label: str, rows_expected: list[dict], lead: str | None = None) -> None:
        header, rows = first_table(section(part, "#### Reference:"))
        assert len(rows) == len(rows_expected) > 0
        for row, expected in zip(rows, rows_expected):
            assert row[0].startswith(f"paper `{label}`") and not any("**" in cell for cell in row)
            assert lead is None or row[1] == str(expected[lead])
            assert_row_equals(numbers_of(header, row), expected)

    for block, dataset, epochs in ((AV2, "av2", "24 epochs"), (NUSC, "nuscenes", "110 epochs")):
        main = section(section(text, block), "### Main table")
        assert SYNTHETIC_NOTE in main
        check(main, "tab:modeling", refs["tab:modeling"].rows_of(dataset), "method")
        header, rows = first_table(section(main, "#### Reference:"))
        assert all(f"{epochs}, FPS on one RTX 3090" in row[0] for row in rows)
        _, measured = first_table(main)
        assert not any(row[0].startswith("paper") for row in measured)  # never mixed with measured rows
        check(
            section(section(text, block), "### mIoU"), "tab:iou", refs["tab:iou"].rows_of(dataset), "method"
        )
    check(
        section(section(text, AV2), "### Ablation: epochs"),
        "tab:schedule",
        refs["tab:schedule"].rows,
        "value",
    )
    check(section(text, "## Post-processing accuracy"), "tab:postproc", refs["tab:postproc"].rows, "via")
    rest = section(text, "## The paper's tables not shown")
    for label in refs:
        placed = label in ("tab:modeling", "tab:iou", "tab:schedule", "tab:postproc")
        assert (f"- `{label}`" in rest) != placed, label
    assert REFERENCE_NOTE in text


def test_each_f1_has_its_interval_from_the_runs_frame_counts(made):
    header, rows = first_table(section(section(made["text"], AV2), "### Main table"))
    by_run = {row[0]: row for row in rows}
    oracle = bootstrap.read_frame_counts(made["runs"] / "path_oracle" / bootstrap.FRAME_COUNTS)[1]
    drawn = {"lanegap_lidar": run_metrics(made, "lanegap_lidar"), "path_oracle": None}
    for mode in ("directed", "undirected"):
        for metric, short in (("topo", "TOPO"), ("junction_topo", "J-TOPO")):
            at = header.index(f"{'dir' if mode == 'directed' else 'undir'} {short} F1")
            for name, metrics in drawn.items():
                low, high = map(float, re.search(r"\[(\S+), (\S+)\]", by_run[name][at]).groups())
                # cli eval's own interval (same draws) for the model; the oracle's from its counts
                expected = (
                    metrics[mode][metric]["f1_ci"] if metrics else bootstrap.intervals(oracle)[mode][metric]
                )
                assert (
                    abs(low - 100 * expected[0]) <= 0.05 + 1e-9
                    and abs(high - 100 * expected[1]) <= 0.05 + 1e-9
                )
                assert low <= number(by_run[name][at]) <= high
    assert "95 % interval of the difference [+" in made["text"].split("\n\n")[1]


def rescored(run: Path, av2: Path, change) -> None:
    """Rewrite a run folder's predictions with change(frame_id, graph), and its scores and counts."""
    from benchmark.metric.params import MetricParams

    gt = graphs_from_table(read_graph_table(av2), av2)
    predicted = graphs_from_table(read_graph_table(run / "predictions.parquet"), run)
    predicted = {f: change(f, g) for f, g in predicted.items()}
    pq.write_table(graph_rows(predicted), run / "predictions.parquet")
    metrics = json.loads((run / "metrics.json").read_text())
    frames = sorted(predicted)
    scores, counts = score_frames(
        [(predicted[f], gt[f]) for f in frames], MetricParams(**metrics["metric_params"])
    )
    bootstrap.write_frame_counts(run / bootstrap.FRAME_COUNTS, frames, counts)
    metrics.update({k: scores[k] for k in ("directed", "undirected", "miou")})
    (run / "metrics.json").write_text(json.dumps(metrics))


def test_a_lead_inside_the_noise_is_level_and_cli_report_prints_the_reference(made, tmp_path):
    runs = tmp_path / "runs"
    shutil.copytree(made["runs"] / "path_oracle", runs / "oracle_a")
    shutil.copytree(made["runs"] / "path_oracle", runs / "oracle_b")
    first = min(graphs_from_table(read_graph_table(runs / "oracle_b" / "predictions.parquet"), runs))
    # oracle_b loses the last edge of one frame out of four: a lower F1 that most draws cannot tell
    rescored(runs / "oracle_b", made["av2"],
             lambda f, g: LaneGraph(g.x, g.y, g.src[:-1], g.dst[:-1]) if f == first else g)  # fmt: skip
    args = ["report", "--runs", str(runs), "--out", str(tmp_path / "r"), "--reference", "paper"]
    result = CliRunner().invoke(app, args, env={"COLUMNS": "250"})
    assert result.exit_code == 0, result.output
    assert "Reference (paper, 24 epochs, FPS on one RTX 3090): the paper's Tab. 1" in result.output
    assert re.search(r"│ LaneGAP\s+│ path-wise\s+│ 61.6\s+│ 56.5\s+│", result.output)
    assert "wrote " in result.output
    summary = (tmp_path / "r" / "report.md").read_text().split("\n\n")[1]
    assert "oracle_a is level with oracle_b on directed TOPO F1" in summary and "leads" not in summary
    assert "points, holds 0)" in summary
    # without draws: no intervals, and no lead claimed
    result = CliRunner().invoke(app, args + ["--bootstrap", "0"])
    assert result.exit_code == 0, result.output
    text = (tmp_path / "r" / "report.md").read_text()
    assert "not tested: no bootstrap (`--bootstrap 0`)" in text.split("\n\n")[1]
    _, rows = first_table(section(text, "### Main table"))
    assert not any("[" in cell for row in rows for cell in row)
    # counts that do not pool to the run's scores give no interval, and say why
    shutil.copy(
        made["runs"] / "lanegap_lidar" / bootstrap.FRAME_COUNTS, runs / "oracle_b" / bootstrap.FRAME_COUNTS
    )
    assert CliRunner().invoke(app, args).exit_code == 0
    text = (tmp_path / "r" / "report.md").read_text()
    assert "oracle_b: no F1 intervals:" in text and "does not pool to the F1 of metrics.json" in text
    assert "oracle_a is ahead of oracle_b" in text.split("\n\n")[1]
    result = CliRunner().invoke(app, args[:-1] + ["book"])
    assert result.exit_code == 2 and "Invalid value for '--reference'" in result.output  # click's usage error


def test_the_report_writes_relative_paths(made, monkeypatch):
    text = made["text"]
    assert not re.search(r"(^|[\s`(])/[\w.-]+/", text, re.M)  # no absolute path anywhere
    data = re.search(r"^## av2 \(synthetic, `cli synth`\): `([^`]+)`", text, re.M)[1]
    assert not Path(data).is_absolute() and Path(data).resolve() == made["av2"].resolve()
    # the data's raw root is gone: the report says it cannot tell synthetic from real
    monkeypatch.chdir(made["root"])
    raw = made["root"] / "raw"
    raw.rename(made["root"] / "raw_moved")
    try:
        report = write_report([made["runs"] / "lanegap_lidar"], made["root"] / "moved", reference="paper")
    finally:
        (made["root"] / "raw_moved").rename(raw)
    text = report.path.read_text()
    assert UNKNOWN_ORIGIN_NOTE in text and "## av2: `av2`, val split" in text


def test_the_data_split_scheme_and_leakage_stand_under_the_main_table(made, tmp_path):
    from pipeline.geometry import Range
    from pipeline.splits.leakage import leakage_line, read_and_measure

    data, run = tmp_path / "av2", tmp_path / "runs" / "lanegap_lidar"
    shutil.copytree(made["av2"], data)
    shutil.copytree(made["runs"] / "lanegap_lidar", run)
    metrics = json.loads((run / "metrics.json").read_text())
    (run / "metrics.json").write_text(json.dumps({**metrics, "data": str(data)}))
    manifest = json.loads((data / "manifest.json").read_text())
    leakage = read_and_measure(data, Range())
    assert leakage["splits"]["val"]["within_5m"] == 0.0  # the validation log drives no training road
    parameters = {k: v for k, v in manifest["parameters"].items() if k != "split_scheme"}
    old = {k: v for k, v in manifest.items() if k != "leakage"} | {"parameters": parameters}  # before leakage
    new = old | {"parameters": parameters | {"split_scheme": "original"}, "leakage": leakage}
    unknown = "split scheme unknown; leakage not measured (prepared before leakage was recorded)"
    for written, line in [(new, leakage_line(leakage, "original")), (old, unknown)]:
        (data / "manifest.json").write_text(json.dumps(written))
        text = write_report([run], tmp_path / "r", draws=0).path.read_text()
        main = section(text, "### Main table").splitlines()
        start = next(i for i, row in enumerate(main) if row.startswith("|"))
        end = next(i for i in range(start, len(main)) if not main[i].startswith("|"))
        assert main[end : end + 3] == ["", line, ""]  # the line right under the main table
        assert text.count(line) == 1
    assert leakage_line(leakage, "original").startswith(
        "split scheme original; leakage: val 0.0 % of 4 frames within 5 m of a training frame (the same city)"
    )


def junctions_by_degree(graph: LaneGraph) -> int:
    """A plain reading of the report's definition: merge identical points, drop self-loops and repeated
    edges, count the vertices with in-degree >= 2 or out-degree >= 2."""
    xy = np.stack([graph.x, graph.y], axis=1).astype(np.float64)
    _, vertex = np.unique(xy, axis=0, return_inverse=True)
    edges = {(vertex[s], vertex[d]) for s, d in zip(graph.src, graph.dst) if vertex[s] != vertex[d]}
    out_degree, in_degree = {}, {}
    for s, d in edges:
        out_degree[s] = out_degree.get(s, 0) + 1
        in_degree[d] = in_degree.get(d, 0) + 1
    return sum(1 for v in set(vertex) if in_degree.get(v, 0) >= 2 or out_degree.get(v, 0) >= 2)


def test_junction_table_agrees_with_cli_score(made, tmp_path):
    av2 = made["av2"]
    gt = graphs_from_table(read_graph_table(av2), av2)
    header, rows = first_table(section(section(made["text"], AV2), "### Scores by junction count"))
    assert header[:2] == ["GT junctions", "frames"]
    oracle_file = made["runs"] / "path_oracle" / "predictions.parquet"
    predicted = graphs_from_table(read_graph_table(oracle_file), oracle_file)
    counts = {f: junctions_by_degree(gt[f]) for f in predicted}
    assert counts == {f: junction_count(gt[f], 0.15) for f in predicted}
    scored = 0
    for (low, high, label), row in zip(JUNCTION_BUCKETS, rows):
        frames = [f for f in predicted if low <= counts[f] <= high]
        assert row[:2] == [label, str(len(frames))]
        if not frames:
            continue
        pq.write_table(graph_rows({f: gt[f] for f in frames}), tmp_path / "gt.parquet")
        pq.write_table(graph_rows({f: predicted[f] for f in frames}), tmp_path / "pred.parquet")
        args = ["score", "--pred", str(tmp_path / "pred.parquet"), "--gt", str(tmp_path / "gt.parquet")]
        result = CliRunner().invoke(app, args + ["--out", str(tmp_path / "score.json")])
        assert result.exit_code == 0, result.output
        directed = json.loads((tmp_path / "score.json").read_text())["directed"]
        at = header.index("path_oracle dir TOPO F1")
        assert abs(number(row[at]) - 100 * directed["topo"]["f1"]) <= 0.05 + 1e-9
        if label != "0":
            assert abs(number(row[at + 1]) - 100 * directed["junction_topo"]["f1"]) <= 0.05 + 1e-9
        scored += 1
    assert scored >= 1


def panel_counts(path: Path) -> tuple[int, int]:
    """(rows, columns) of BEV panels in a grid PNG: runs of pixel rows / columns that hold the panels'
    background colour."""
    pixels = np.asarray(Image.open(path).convert("RGB")).astype(int)
    background = np.all(np.abs(pixels - 247) <= 1, axis=2)

    def runs(mask: np.ndarray) -> int:
        # a lane drawn along a whole panel leaves a line of a few pixels without background: runs
        # closer than the margin between two panels are one panel
        starts = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(int)])) == 1)
        ends = np.flatnonzero(np.diff(np.concatenate([mask.astype(int), [0]])) == -1)
        return 1 + int(np.count_nonzero(starts[1:] - ends[:-1] > 6)) if len(starts) else 0

    return runs(background.sum(axis=1) > 20), runs(background.sum(axis=0) > 20)


def test_pictures_exist_open_and_are_not_blank(made):
    out, report = made["out"], made["report"]
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", made["text"])
    assert sorted(links) == sorted(p.name for p in report.pictures)
    assert {"loss.png", "grid_1_av2.png", "f1_1_av2.png"} <= set(links)
    for link in links:
        image = np.asarray(Image.open(out / link).convert("L"), np.float64)
        assert image.shape[0] > 100 and image.shape[1] > 100
        assert image.std() > 10, link
    frames = len(
        graphs_from_table(read_graph_table(made["runs"] / "lanegap_lidar" / "predictions.parquet"), out)
    )
    assert report.grids["grid_1_av2.png"] == (min(frames, 5), 3)  # GT, lanegap_lidar, path_oracle
    assert panel_counts(out / "grid_1_av2.png") == report.grids["grid_1_av2.png"]


def test_runs_with_other_metric_parameters_are_refused(made, tmp_path):
    other = tmp_path / "strict"
    shutil.copytree(made["runs"] / "path_oracle", other)
    metrics = json.loads((other / "metrics.json").read_text())
    metrics["metric_params"]["match_radius"] = 0.3
    (other / "metrics.json").write_text(json.dumps(metrics))
    args = [
        "report",
        "--runs",
        str(made["runs"] / "lanegap_lidar"),
        "--runs",
        str(other),
        "--out",
        str(tmp_path / "r"),
    ]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 1
    assert "strict/metrics.json: scored with other metric parameters" in result.output
    assert "match_radius 0.3 vs 0.45" in result.output and "cannot share a table" in result.output
    assert not (tmp_path / "r" / "report.md").exists()


def test_viz_draws_the_frame_of_lowest_f1(made, tmp_path):
    from benchmark.metric.params import MetricParams

    av2, pred = made["av2"], made["runs"] / "path_oracle" / "predictions.parquet"
    gt = graphs_from_table(read_graph_table(av2), av2)
    predicted = graphs_from_table(read_graph_table(pred), pred)
    f1 = {
        f: score_pairs([(predicted[f], gt[f])], MetricParams())["directed"]["topo"]["f1"] for f in predicted
    }
    assert len(set(f1.values())) > 1
    worst = min(f1, key=lambda f: (f1[f], -len(gt[f].x), f))
    out = tmp_path / "viz.png"
    result = CliRunner().invoke(
        app, ["viz", "--pred", str(pred), "--gt", str(av2), "--camera", "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    assert worst in result.output and f"TOPO F1 {f1[worst]:.3f}" in result.output
    image = np.asarray(Image.open(out).convert("RGB"), np.float64)
    assert image.std() > 10
    # the matched (green) and unmatched (red) vertices are both drawn
    assert np.any(np.all(np.abs(image - [44, 160, 44]) < 8, axis=2))
    assert np.any(np.all(np.abs(image - [214, 39, 40]) < 8, axis=2))
    result = CliRunner().invoke(
        app, ["viz", "--pred", str(pred), "--gt", str(av2), "--frame", "nope", "--out", str(out)]
    )
    assert result.exit_code == 1 and "no frame 'nope' in the ground truth" in result.output


VALIDATION_KEYS = ("directed_topo_f1", "directed_junction_topo_f1", "undirected_topo_f1",
                   "undirected_junction_topo_f1", "miou")  # fmt: skip


def validated_copy(made, folder: Path, seed: int) -> list[dict]:
    """A copy of the trained run with a val.jsonl of seeded scores at its logged steps, run.json's
    "best" (the highest directed Junction TOPO F1) and its best.pt, as `cli train --eval-every` writes
    them."""
    shutil.copytree(made["runs"] / "lanegap_lidar", folder)
    log = [json.loads(line) for line in (folder / "log.jsonl").read_text().splitlines()]
    frames = json.loads((folder / "metrics.json").read_text())["frames"]
    rng = np.random.default_rng(seed)
    records = [{"step": e["step"], "epoch": e["epoch"], "split": "val", "frames": frames,
                "seconds": float(rng.uniform(1, 2)), **dict(zip(VALIDATION_KEYS, rng.uniform(0, 1, 5)))}
               for e in log]  # fmt: skip
    (folder / "val.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    best = max(records, key=lambda r: r["directed_junction_topo_f1"])
    info = json.loads((folder / "run.json").read_text())
    info["best"] = {"metric": "directed_junction_topo_f1", "value": best["directed_junction_topo_f1"],
                    "epoch": best["epoch"], "step": best["step"]}  # fmt: skip
    (folder / "run.json").write_text(json.dumps(info))
    shutil.copy(folder / "checkpoint.pt", folder / "best.pt")
    return records


def test_validation_curves_with_the_best_and_a_cut_last_line(made, tmp_path):
    from benchmark.report.runs import load_run
    from benchmark.report.sections import validation_curve

    runs = tmp_path / "runs"
    records = validated_copy(made, runs / "validated", seed=0)
    cut = validated_copy(made, runs / "cut", seed=1)[:-1]  # its last line is cut below
    # a kill mid-write: val.jsonl and log.jsonl end in the first half of their last line, no newline
    for name in ("val.jsonl", "log.jsonl"):
        text = (runs / "cut" / name).read_text().rstrip("\n")
        last = text.rsplit("\n", 1)[-1]
        (runs / "cut" / name).write_text(text[: len(text) - len(last) // 2])
    # a run trained before validation during training: no val.jsonl, best.pt or run.json "best"
    old = runs / "unvalidated"
    shutil.copytree(made["runs"] / "lanegap_lidar", old)
    for name in ("val.jsonl", "best.pt"):
        (old / name).unlink(missing_ok=True)
    info = json.loads((old / "run.json").read_text())
    (old / "run.json").write_text(json.dumps({k: v for k, v in info.items() if k != "best"}))

    drawn = validation_curve(load_run(runs / "cut", "cut"))
    for key in ("directed_topo_f1", "directed_junction_topo_f1"):
        steps, values = drawn.points[key]
        assert steps.tolist() == [r["step"] for r in cut] and values.tolist() == [100 * r[key] for r in cut]
    info = json.loads((runs / "cut" / "run.json").read_text())["best"]
    assert drawn.best == (info["metric"], info["step"], 100 * info["value"])

    report = write_report([runs], tmp_path / "r", draws=0)
    assert "validation.png" in [p.name for p in report.pictures]
    image = np.asarray(Image.open(tmp_path / "r" / "validation.png").convert("L"), np.float64)
    assert image.shape[0] > 100 and image.shape[1] > 100 and image.std() > 10
    text = section(report.path.read_text(), "## Validation during training")
    assert "![validation F1 during training](validation.png)" in text
    metrics = json.loads((runs / "validated" / "metrics.json").read_text())
    floor = metrics["floor"]["best_constant"]["directed"]
    constant = (f"best constant (hindsight): directed TOPO F1 {100 * floor['topo']['f1']:.1f} %, directed "
                f"Junction TOPO F1 {100 * floor['junction_topo']['f1']:.1f} %.")  # fmt: skip
    for name, held in (("validated", records), ("cut", cut)):
        best = json.loads((runs / name / "run.json").read_text())["best"]  # over every line, the cut one too
        steps = [r["step"] for r in held]
        line = f"- {name}: {len(held)} validation(s), steps {min(steps)}-{max(steps)}"
        line += f", on {metrics['frames']} frames"
        line += "; its last line was cut short (a kill mid-write) and left out" if name == "cut" else ""
        line += (f"; best directed Junction TOPO F1 {100 * best['value']:.1f} % at step {best['step']} "
                 f"(epoch {best['epoch']}), kept as best.pt; " + constant)  # fmt: skip
        assert line in text.splitlines(), (name, text)
    assert "- unvalidated: no val.jsonl (no validation recorded)." in text.splitlines()
    loss = section(report.path.read_text(), "## Training loss")
    assert "The last line of log.jsonl was cut short (a kill mid-write), left out: cut." in loss


def test_a_skipped_non_finite_step_is_left_out_of_the_loss_curve(made, tmp_path):
    from benchmark.report.runs import load_run
    from benchmark.report.sections import loss_points

    run = tmp_path / "runs" / "guarded"
    shutil.copytree(made["runs"] / "lanegap_lidar", run)
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    last = log[-1]
    # the guard's lines (json writes NaN and Infinity), and a logged step whose loss is infinite
    guard = {"epoch": last["epoch"], "skipped": "non-finite"}
    skipped = [{**guard, "step": last["step"] + 1, "loss": math.nan},
               {**guard, "step": last["step"] + 2, "loss": 2 * last["loss"]},
               {**last, "step": last["step"] + 3, "loss": math.inf}]  # fmt: skip
    with (run / "log.jsonl").open("a") as file:
        file.writelines(json.dumps(entry) + "\n" for entry in skipped)
    steps, losses, left_out = loss_points(load_run(run, "guarded"))
    assert steps.tolist() == [e["step"] for e in log] and losses.tolist() == [e["loss"] for e in log]
    assert left_out == len(skipped)
    report = write_report([tmp_path / "runs"], tmp_path / "r", draws=0)
    assert "loss.png" in [p.name for p in report.pictures]
    image = np.asarray(Image.open(tmp_path / "r" / "loss.png").convert("L"), np.float64)
    assert image.std() > 10
    text = section(report.path.read_text(), "## Training loss")
    assert f"non-finite loss (guarded {len(skipped)})." in text
