"""A range typed another way (`cli score --range 50.0X100`) is the same range: cli score records it as
cli prepare does (Range.text, "50x100"), and cli report reads an earlier run's spelling so, which compares
runs' ranges as text (the OpenLane-V2 section's runs at the paper's 50 x 100 m)."""

from __future__ import annotations

import json
from pathlib import Path

from test_openlanev2_prepare import segment

from benchmark.formats.openlanev2_submission import write_submission
from benchmark.report.writer import write_report
from benchmark.score import score
from pipeline.geometry import Range
from pipeline.io import read_annotated_lanes, read_openlanev2_keys
from pipeline.prepare import prepare
from pipeline.records import AnnotatedLanes
from pipeline.targets import TargetOptions


def prepared_with_submission(tmp_path: Path, bev_range: str) -> Path:
    """One OpenLane-V2 segment prepared at `bev_range` into tmp_path/data, and tmp_path/submission.pkl
    holding its annotated lanes."""
    root, data = tmp_path / "olv2", tmp_path / "data"
    segment(root, "seg-b", 2, "val")
    prepare("openlanev2", root, data, TargetOptions(Range.parse(bev_range)))
    keys, annotated = read_openlanev2_keys(data), read_annotated_lanes(data)
    frames = {keys[f]: AnnotatedLanes(lanes.points, lanes.links, lanes.ids, [0.9] * len(lanes))
              for f, lanes in annotated.items()}  # fmt: skip
    write_submission(tmp_path / "submission.pkl", "mine", frames)
    return data


def test_a_range_spelt_otherwise_is_recorded_and_reported_as_the_same(tmp_path):
    data = prepared_with_submission(tmp_path, "50x100")
    run = tmp_path / "runs" / "typed"
    score(tmp_path / "submission.pkl", data, out=run, bev_range="50.0X100")
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["metric_params"]["bev_range"] == "50x100"
    # a run folder an earlier cli score wrote with the range as typed: the same range to the report
    metrics["metric_params"]["bev_range"] = "50.0X100"
    (run / "metrics.json").write_text(json.dumps(metrics))
    report = write_report([tmp_path / "runs"], tmp_path / "report", reference="paper", draws=0)
    text = Path(report.path).read_text()
    assert "Left out" not in text and "| ours, OpenLane-V2 `olv2` | typed |" in text


def test_a_range_wider_than_the_prepared_crop_is_refused(tmp_path):
    """Beyond the crop `cli prepare` cut the ground truth to there is no ground truth: a wider --range would
    count a perfect prediction's lanes there as false (the ground truth's own lanes scored TOPO F1 0.74)."""
    import pytest

    data = prepared_with_submission(tmp_path, "30x60")
    with pytest.raises(ValueError, match=r"--range 50x100: wider than the ground truth .* prepared at 30x60"):
        score(tmp_path / "submission.pkl", data, bev_range="50x100", bootstrap=0)
    narrower = score(tmp_path / "submission.pkl", data, bev_range="20x40", bootstrap=0)
    assert narrower["metric_params"]["bev_range"] == "20x40"
