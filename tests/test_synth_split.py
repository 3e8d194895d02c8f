"""The default synthetic split demands perception: no fixed graph fits its validation frames."""

from __future__ import annotations

from baselines.floor import search_constant_prior
from benchmark.graph_table import default_range, graphs_from_table, read_graph_table
from benchmark.metric.params import MetricParams
from benchmark.score import score_pairs
from pipeline.io import read_table

PRIOR_CEILING = 0.35  # directed TOPO F1 of the best constant graph on the validation frames


def test_the_constant_prior_scores_low_on_the_default_validation_frames(tmp_path):
    from pipeline.prepare import prepare
    from pipeline.synth import synth
    from pipeline.targets import TargetOptions

    summary = synth(tmp_path / "raw", sensors=False)  # the defaults: the learning checks' data, no sensors
    data = tmp_path / "prepared"
    leakage = prepare("av2", tmp_path / "raw" / "av2" / "sensor", data, TargetOptions())["leakage"]
    # the validation world is a city of its own: no training window shares ground with a validation one
    val = leakage["splits"]["val"]
    assert (val["frames"], val["overlapping"], val["covered"], val["median_m"]) == (40, 0.0, 0.0, None)
    assert all(city["no_training_frames_in_city"] for city in val["cities"].values())
    frames = read_table(data, "frames").to_pylist()
    ids = {split: [f["frame_id"] for f in frames if f["split"] == split] for split in ("train", "val")}
    assert len(ids["train"]) == 160 and len(ids["val"]) == 40
    # 16 training logs take v1.0-trainval's scene names, so that the devkit's official splits hold them
    assert summary["nuscenes_version"] == "v1.0-trainval"
    nuscenes = tmp_path / "prepared_nuscenes"
    prepare("nuscenes", tmp_path / "raw" / "nuscenes", nuscenes, TargetOptions(), version="v1.0-trainval")
    splits = [f["split"] for f in read_table(nuscenes, "frames").to_pylist()]
    assert (splits.count("train"), splits.count("val")) == (160, 40)
    truth = graphs_from_table(read_graph_table(data), data)
    params = MetricParams(bev_range=default_range(data))
    prior = search_constant_prior(truth, ids["train"], "train", params, tmp_path / "cache")
    scores = score_pairs([(truth[prior["frame_id"]], truth[f]) for f in ids["val"]], params)
    print(f"constant prior {prior['frame_id']}: train F1 {prior['train_f1']:.3f}, val {scores['directed']}")
    assert scores["directed"]["topo"]["f1"] <= PRIOR_CEILING
    assert scores["directed"]["junction_topo"]["f1"] <= PRIOR_CEILING
