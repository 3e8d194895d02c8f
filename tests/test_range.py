"""The paper's 50 x 100 m range end to end: `cli prepare --range 50x100` -> `cli train` (the model's BEV
grid follows the manifest at the preset's cell size) -> `cli eval` -> `cli score`, on a small synthetic
split. The assertions are on shapes, coordinates and the grid the scores use, not on accuracy."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from cli import app
from pipeline.manifest import PreparedData


def invoke(*args) -> str:
    result = CliRunner().invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, result.output
    return result.output


@pytest.mark.parametrize("model", ["lanegap", "hdmapnet"])
def test_50x100_range_from_prepare_to_score(tmp_path_factory, model):
    from baselines.data import PreparedDataset
    from baselines.models import build, load_config
    from pipeline.synth import synth

    root = tmp_path_factory.getbasetemp() / "range_50x100"
    data = root / "prepared"
    if not (data / "manifest.json").is_file():
        synth(root / "raw", logs=3, frames_per_log=3, frame_period=1.0, worlds=2, val_frames_per_log=3)
        invoke("prepare", "--dataset", "av2", "--root", root / "raw/av2/sensor", "--out", data,
               "--range", "50x100")  # fmt: skip
    assert json.loads((data / "manifest.json").read_text())["range"] == {
        "x_min": -25.0, "x_max": 25.0, "y_min": -50.0, "y_max": 50.0
    }  # fmt: skip
    run = tmp_path_factory.mktemp(model)
    invoke("train", "--model", model, "--data", data, "--out", run, "--preset", "tiny", "--modality", "lidar",
           "--epochs", "1", "--batch-size", "2", "--set", "train.threads=1")  # fmt: skip
    config = load_config(run / "config.json")
    # the tiny preset's 1.5 m cells over 50 x 100 m
    assert (config.encoder.x_range, config.encoder.y_range) == ((-25.0, 25.0), (-50.0, 50.0))
    assert (config.encoder.bev_h, config.encoder.bev_w) == (67, 33)

    needs = build(config).needs
    sample = PreparedDataset(PreparedData.open(data), "train", config, needs)[0]
    assert sample.seg.shape == (67, 33)
    if "paths" in needs:  # unit coordinates of the 50 x 100 map
        assert len(sample.paths) and sample.paths.min() >= 0.0 and sample.paths.max() <= 1.0
    else:
        assert sample.raster[0].shape == (667, 333)

    invoke("eval", "--run", run, "--data", data, "--split", "val", "--no-floor", "--device", "cpu")
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["metric_params"]["bev_range"] == "50x100"
    predictions = pq.read_table(run / "predictions.parquet").to_pydict()
    x, y = np.concatenate(predictions["x"] or [[]]), np.concatenate(predictions["y"] or [[]])
    assert np.all(np.abs(x) <= 25.0) and np.all(np.abs(y) <= 50.0)

    score = run / "score.json"
    invoke("score", "--pred", run / "predictions.parquet", "--gt", data, "--out", score)
    scored = json.loads(score.read_text())  # the frames of the predicted split: the val log's 3 of 9
    assert scored["metric_params"]["bev_range"] == "50x100" and scored["splits"] == ["val"]
    assert (scored["frames"], scored["frames_predicted"], scored["frames_missing"]) == (3, 3, 0)
