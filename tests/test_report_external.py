"""`cli report` with external runs: run folders that `cli score --out RUN_DIR` writes for the result file
of another codebase (metrics.json with an "external" key, predictions.parquet, frame_counts.parquet; no
config, checkpoint or log), shown beside runs of ours.

On the session's small synthetic AV2 split (conftest's `synth_prepared`, 20 validation frames), written
by hand, nothing trained: `ours_1ep` and `ours_2ep`, runs of ours (config, run.json, an empty
checkpoint.pt) whose predictions are the ground truth shifted 0.2 m with edges dropped, saved as trained
for 1 and 2 epochs (an ablation of `train.epochs`); `maptrv2_ext`, a MapTRv2 result file's run whose 12
frames (the last 12 of the 20) are the ground truth; `graph_ext`, an external graph table holding 17 of
the 20 frames (the first 3 scored as empty predictions, as `cli score` does). And one external run that
`cli score --out` itself writes.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from test_report import first_table, number, section

from benchmark.graph_table import graphs_from_table, read_graph_table
from benchmark.metric import bootstrap
from benchmark.metric.params import MetricParams
from benchmark.report.measured_tables import settings_table
from benchmark.report.runs import find_runs, load_run
from benchmark.report.summary import paired_difference
from benchmark.report.writer import write_report
from benchmark.score import score_frames
from pipeline import io
from pipeline.lane_graph import LaneGraph

SHA = "0123456789abcdef" * 4
SUBSET = 12  # frames of maptrv2_ext's file
ABSENT = 3  # frames graph_ext's table lacks
PARAMS = MetricParams(bev_range="30x60")


def graph_table(graphs: dict[str, LaneGraph]) -> pa.Table:
    rows = [
        {"frame_id": f, "x": g.x.tolist(), "y": g.y.tolist(), "src": g.src.tolist(), "dst": g.dst.tolist()}
        for f, g in sorted(graphs.items())
    ]
    return pa.Table.from_pylist(rows, io.SCHEMAS["graphs"])


def scored_folder(folder: Path, graphs: dict[str, LaneGraph], gt: dict[str, LaneGraph], extra: dict) -> dict:
    """A run folder as `cli eval` / `cli score --out` leave it: predictions, per-frame counts in sorted
    frame order, and metrics.json (score_pairs' keys, intervals included, plus `extra`)."""
    folder.mkdir(parents=True)
    frames = sorted(graphs)
    scores, counts = score_frames([(graphs[f], gt[f]) for f in frames], PARAMS)
    bootstrap.add_intervals(scores, counts)
    pq.write_table(graph_table(graphs), folder / "predictions.parquet")
    bootstrap.write_frame_counts(folder / bootstrap.FRAME_COUNTS, frames, counts)
    metrics = {**scores, **extra}
    (folder / "metrics.json").write_text(json.dumps(metrics))
    return metrics


def external_metrics(data: Path, fmt: str, frames: int, not_in_file: int, **counts) -> dict:
    """What `cli score --out RUN_DIR` adds to score_pairs' result (docs of the task's spec)."""
    source = f"/elsewhere/{'nuscmap_results.json' if fmt != 'graph' else 'theirs.parquet'}"
    json_file = fmt != "graph"
    return {
        "pred": source, "gt": str(data), "data": str(data), "split": "val", "splits": ["val"],
        "frames_predicted": frames, "model": "external",
        "modeling": {"maptrv2": "path", "cgnet": "piece", "graph": "graph"}[fmt],
        "params": None, "gflops": None, "fps_net": None, "fps": None, "device": None, "precision": None,
        "external": {
            "format": fmt, "source": source, "sha256": SHA,
            "class_name": "centerline" if json_file else None, "min_score": 0.4 if json_file else None,
            "frames_in_file": frames, "frames_not_in_file": not_in_file,
            "points_clipped": counts.get("points_clipped") if json_file else None,
            "vectors_read": counts.get("vectors_read") if json_file else None,
            "vectors_kept": counts.get("vectors_kept") if json_file else None,
        },
    }  # fmt: skip


def our_extra(data: Path, epochs: int) -> tuple[dict, dict]:
    """(metrics.json's keys besides the scores, config.json) of a run of ours evaluated with --no-floor."""
    config = {"model": "lanegap", "preset": "tiny", "encoder": {"modality": "lidar"},
              "train": {"epochs": epochs, "batch_size": 2, "val_split": "val"}}  # fmt: skip
    extra = {"data": str(data), "split": "val", "model": "lanegap", "modeling": "path", "params": 1.5e6,
             "gflops": 4.2, "fps_net": 15.0, "fps": 12.5, "device": "cpu", "precision": "fp32",
             "config": config}  # fmt: skip
    return extra, config


@pytest.fixture(scope="module")
def made(synth_prepared, tmp_path_factory) -> dict:
    data = synth_prepared["av2"]
    frames_table = io.read_table(data, "frames", columns=["frame_id", "split"]).to_pylist()
    val = sorted(row["frame_id"] for row in frames_table if row["split"] == "val")
    gt_all = graphs_from_table(read_graph_table(data), data)
    gt = {f: gt_all[f] for f in val}
    root = tmp_path_factory.mktemp("report_external")
    runs = root / "runs"

    shifted = {}
    for i, f in enumerate(val):
        g, keep = gt[f], np.arange(len(gt[f].src)) % (2 + i % 3) != 0
        shifted[f] = LaneGraph(g.x + np.float32(0.2), g.y, g.src[keep], g.dst[keep])
    metrics = {}
    for name, epochs in (("ours_1ep", 1), ("ours_2ep", 2)):
        extra, config = our_extra(data, epochs)
        graphs = shifted if epochs == 1 else {f: gt[f] if i % 2 else shifted[f] for i, f in enumerate(val)}
        metrics[name] = scored_folder(runs / name, graphs, gt, extra)
        (runs / name / "config.json").write_text(json.dumps(config))
        (runs / name / "run.json").write_text(json.dumps({"data": str(data), "world_size": 1}))
        (runs / name / "checkpoint.pt").write_bytes(b"")

    subset = val[-SUBSET:]  # the last frames: the one with junctions among them
    extra = external_metrics(
        data, "maptrv2", SUBSET, len(val) - SUBSET, points_clipped=7, vectors_read=300, vectors_kept=120
    )
    metrics["maptrv2_ext"] = scored_folder(runs / "maptrv2_ext", {f: gt[f] for f in subset}, gt, extra)

    absent = set(val[:ABSENT])
    graphs = {f: LaneGraph.empty() if f in absent else gt[f] for f in val}  # as cli score writes them
    extra = external_metrics(data, "graph", len(val) - ABSENT, 0)
    extra["frames_missing"] = ABSENT
    metrics["graph_ext"] = scored_folder(runs / "graph_ext", graphs, gt, extra)

    out = root / "report"
    report = write_report([runs], out, draws=200)
    text = (out / "report.md").read_text()
    return {"data": data, "runs": runs, "val": val, "metrics": metrics, "report": report, "text": text}


def main_rows(made) -> tuple[list[str], dict[str, list[str]]]:
    header, rows = first_table(section(made["text"], "### Main table"))
    return header, {row[0]: row for row in rows}


def test_an_external_folder_is_a_scored_run_without_a_checkpoint_reason(made):
    assert {p.name for p in find_runs([made["runs"]])} == {"ours_1ep", "ours_2ep", "maptrv2_ext", "graph_ext"}
    assert find_runs([made["runs"] / "maptrv2_ext"]) == [made["runs"] / "maptrv2_ext"]
    (block,) = made["report"].blocks  # one block: same data folder and split as ours
    by_name = {run.name: run for run in block.runs}
    for name in ("maptrv2_ext", "graph_ext"):
        run = by_name[name]
        assert run.scored and run.reasons == [] and run.no_counts == "" and run.config is None
        assert len(run.frame_ids) == made["metrics"][name]["frames"]
    assert "no checkpoint.pt" not in made["text"]
    assert "not scored" not in made["text"]


def test_the_external_rows_hold_their_metrics_json_and_unknown_cells(made):
    header, rows = main_rows(made)
    assert header[16:] == ["Params (M)", "GFLOPs", "FPS_net", "FPS"]
    modes, metrics_ = (
        (("directed", "dir"), ("undirected", "undir")),
        (("topo", "TOPO"), ("junction_topo", "J-TOPO")),
    )
    f1_at = {(mode, metric): header.index(f"{m} {k} F1") for mode, m in modes for metric, k in metrics_}
    for name, method, modeling in (("maptrv2_ext", "MapTRv2 / LaneGAP JSON (external)", "path"),
                                   ("graph_ext", "graph table (external)", "graph")):  # fmt: skip
        row, metrics = rows[name], made["metrics"][name]
        assert row[1:4] == [method, modeling, "unknown"]
        assert row[16:] == ["unknown"] * 4
        for (mode, metric), at in f1_at.items():
            assert abs(number(row[at]) - 100 * metrics[mode][metric]["f1"]) <= 0.05 + 1e-9
            assert re.search(r"\[\S+, \S+\]", row[at])  # its interval, from its frame counts
    # the ground truth of its frames: 100 %, ranked and bolded like any run
    assert rows["maptrv2_ext"][f1_at["directed", "topo"]].startswith("**100.0")
    assert not rows["ours_1ep"][f1_at["directed", "topo"]].startswith("**")
    assert rows["ours_1ep"][1:4] == ["LaneGAP", "path", "lidar"] and rows["ours_1ep"][16:] == [
        "1.50", "4.20", "15.0", "12.5"
    ]  # fmt: skip
    # the title counts our runs' frames and names the one scored on fewer
    assert f"val split, 20 frames (maptrv2_ext: {SUBSET})" in made["text"]


def test_the_note_under_the_table_says_what_was_read(made):
    main = section(made["text"], "### Main table")
    (note,) = [line for line in main.splitlines() if line.startswith("- maptrv2_ext:")]
    assert note == (
        "- maptrv2_ext: external (MapTRv2 / LaneGAP JSON `nuscmap_results.json`, sha256 0123456789ab), "
        "scored by `cli score` with this report's metric on the same ground truth: class `centerline` above "
        f"score 0.4; {SUBSET} frames in its file scored; {20 - SUBSET} of the val split's frames not in its "
        "file (its F1 is over fewer frames, so no paired lead is tested between it and a run scored on other "
        "frames); 7 points outside the range clipped; 120 of 300 vectors kept. Its parameter count, GFLOPs, "
        "FPS and sensor-blind floor are unknown: its training and sensors are not ours."
    )
    (note,) = [line for line in main.splitlines() if line.startswith("- graph_ext:")]
    assert "graph table `theirs.parquet`, sha256 0123456789ab" in note
    assert f"20 of the val split's frames scored, {ABSENT} of them not in its file" in note
    assert "class" not in note and "vectors" not in note
    # the floor notes: ours evaluated without a floor, never an external run
    assert "- ours_1ep: no sensor-blind floor recorded" in made["text"]
    assert not re.search(r"_ext: no sensor-blind floor", made["text"])
    assert "A run whose method ends in *(external)*" in made["text"]


def test_settings_ablation_and_mIoU(made):
    (block,) = made["report"].blocks
    _, rows = settings_table(block)
    by_run = {row[0]: row for row in rows}
    assert by_run["maptrv2_ext"] == ["maptrv2_ext", "–", "–", "external (maptrv2)", "–", "–", "–", "–", "val"]
    assert by_run["graph_ext"][3] == "external (graph)"
    _, rows = first_table(section(made["text"], "### Ablation: epochs"))
    assert [(r[0], r[1]) for r in rows] == [("1", "ours_1ep"), ("2", "ours_2ep")]
    assert made["text"].count("### Ablation") == 1
    _, rows = first_table(section(made["text"], "### mIoU"))
    (row,) = [r for r in rows if r[0] == "maptrv2_ext"]
    assert row[1:3] == ["MapTRv2 / LaneGAP JSON (external)", "unknown"]
    assert abs(number(row[3]) - 100 * made["metrics"]["maptrv2_ext"]["miou"]) <= 0.05 + 1e-9


def test_the_summary_tests_no_lead_across_other_frames(made):
    summary = made["text"].split("\n\n")[1]
    leader, ext = made["metrics"]["maptrv2_ext"]["directed"]["topo"]["f1"], "maptrv2_ext"
    assert f"{ext} is ahead of " in summary and "not tested: the two were scored on other frames" in summary
    assert f"{ext} leads" not in summary and f"{ext} is level with" not in summary
    assert f"directed TOPO F1 ({100 * leader:.1f} % vs" in summary
    # where the frames are the same, an external run's lead is tested like any other
    by_name = {run.name: run for run in made["report"].blocks[0].runs}
    assert isinstance(paired_difference(by_name["graph_ext"], by_name["ours_1ep"], 200), dict)
    assert paired_difference(by_name[ext], by_name["ours_1ep"], 200) == "the two were scored on other frames"


def test_junction_table_and_grid_hold_the_external_predictions(made):
    header, rows = first_table(section(made["text"], "### Scores by junction count"))
    assert "maptrv2_ext dir TOPO F1" in header and "graph_ext dir J-TOPO F1" in header
    at = header.index("maptrv2_ext dir TOPO F1")
    for row in rows:  # its frames' ground truth, scored on its frames alone
        expected = ["–", "–"] if row[1] == "0" else ["100.0", "–" if row[0] == "0" else "100.0"]
        assert row[at : at + 2] == expected, row
    assert any(row[0] != "0" and row[1] != "0" for row in rows)  # a bucket with junctions is there
    assert (
        f"- maptrv2_ext: scored on the {SUBSET} frames of its result file alone (of the 20 here)"
        in (made["text"])
    )
    frames = section(made["text"], "### Frames")
    assert "Columns: ground truth, " in frames and "maptrv2_ext" in frames and "graph_ext" in frames
    grid = next(name for name in made["report"].grids if name.startswith("grid_"))
    assert made["report"].grids[grid][1] == 5  # ground truth and the four runs


def test_cgnet_name_and_a_non_external_run_with_null_sizes_is_refused(made, tmp_path):
    metrics = json.loads((made["runs"] / "maptrv2_ext" / "metrics.json").read_text())
    metrics["external"]["format"], metrics["modeling"] = "cgnet", "piece"
    (tmp_path / "cgnet").mkdir()
    (tmp_path / "cgnet" / "metrics.json").write_text(json.dumps(metrics))
    run = load_run(tmp_path / "cgnet", "cgnet")
    assert run.scored and run.reasons == [] and run.method == "CGNet JSON (external)"
    del metrics["external"]
    (tmp_path / "ours").mkdir()
    (tmp_path / "ours" / "metrics.json").write_text(json.dumps(metrics))
    (tmp_path / "ours" / "checkpoint.pt").write_bytes(b"")
    run = load_run(tmp_path / "ours", "ours")
    assert not run.scored
    (reason,) = run.reasons
    assert reason.endswith("metrics.json lacks params, fps_net, fps (re-run `cli eval`)")


def test_a_run_folder_written_by_cli_score_is_read(made, tmp_path):
    from benchmark.report.measured_tables import external_notes
    from benchmark.report.runs import group_blocks
    from benchmark.score import score

    pred = tmp_path / "theirs.parquet"
    gt = graphs_from_table(read_graph_table(made["data"]), made["data"])
    pq.write_table(graph_table({f: gt[f] for f in made["val"][2:]}), pred)
    score(pred, made["data"], tmp_path / "scored")
    run = load_run(tmp_path / "scored", "scored")
    assert run.scored and run.reasons == [] and run.no_counts == ""
    assert (run.method, run.modality, run.split) == ("graph table (external)", "unknown", "val")
    (block,) = group_blocks([run, load_run(made["runs"] / "ours_1ep", "ours_1ep")])  # one block with ours
    (note,) = external_notes(block)
    digest = run.metrics["external"]["sha256"]
    assert f"graph table `theirs.parquet`, sha256 {digest[:12]}" in note
    assert "20 of the val split's frames scored, 2 of them not in its file" in note
