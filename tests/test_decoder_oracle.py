"""The decoder oracle (tools/decoder_oracle.py): the ground-truth raster as a query model's BEV input,
pooled to the encoder's grid, and its training and scoring wired through the model's own record."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.io import decode_raster, read_table
from tools.decoder_oracle import oracle_bev, oracle_config, score_oracle, train_oracle


def test_oracle_bev_is_the_raster_pooled(synth_prepared):
    row = read_table(synth_prepared["av2"], "rasters").to_pylist()[5]
    mask, _ = decode_raster(row)
    full = oracle_bev(row, 1)
    assert torch.equal(full[0], torch.from_numpy(mask.astype(np.float32)))
    norms = full[1:].norm(dim=0)
    assert torch.allclose(norms[full[0] > 0], torch.ones(()), atol=1e-6)  # unit directions on the lanes
    assert torch.all(norms[full[0] == 0] == 0)
    pooled = oracle_bev(row, 10)
    assert pooled.shape[1:] == (mask.shape[0] // 10, mask.shape[1] // 10)
    inside = mask[: pooled.shape[1] * 10, : pooled.shape[2] * 10]
    assert pooled[0].sum().item() * 100 == pytest.approx(float(inside.sum()), rel=1e-5)


def test_the_oracle_takes_query_models_only():
    with pytest.raises(ValueError, match="hdmapnet"):
        oracle_config("hdmapnet", "tiny", [])
    assert oracle_config("lanegap", "tiny", []).decoder.aux_seg is False  # it would read its own input


@pytest.mark.parametrize("model", ["lanegap", "maptr", "stsu"])
def test_oracle_trains_and_scores_through_the_model(synth_prepared, model):
    config = oracle_config(model, "tiny", ["train.warmup_iters=1"])
    oracle, splits, _ = train_oracle(config, synth_prepared["av2"], steps=2)
    assert {split: len(items) for split, items in splits.items()} == {"train": 60, "val": 20}
    assert splits["val"][0][1].shape == (3, config.encoder.bev_h, config.encoder.bev_w)  # the encoder's grid
    rows = score_oracle(oracle, config, splits, synth_prepared["av2"], (0.0, 1.0))
    assert [(r["split"], r["threshold"]) for r in rows] == [
        ("train", 0.0),
        ("train", 1.0),
        ("val", 0.0),
        ("val", 1.0),
    ]
    # threshold 1.0 keeps nothing: no predicted graph, recall 0; threshold 0 keeps every query
    assert all(r["topo recall"] == 0.0 for r in rows if r["threshold"] == 1.0)
    assert all(r["topo recall"] > 0.0 for r in rows if r["threshold"] == 0.0)


def test_oracle_memorisation_subset(synth_prepared):
    config = oracle_config("lanegap", "tiny", ["train.warmup_iters=1"])
    _, splits, _ = train_oracle(config, synth_prepared["av2"], steps=1, train_frames=4)
    assert {split: len(items) for split, items in splits.items()} == {"train": 4, "val": 20}
    assert len({sample.frame_id for sample, _ in splits["train"]}) == 4
    _, again, _ = train_oracle(config, synth_prepared["av2"], steps=1, train_frames=4)  # seeded
    assert [s.frame_id for s, _ in again["train"]] == [s.frame_id for s, _ in splits["train"]]
    with pytest.raises(ValueError, match="train_frames must be 1 to 60"):
        train_oracle(config, synth_prepared["av2"], steps=1, train_frames=61)
