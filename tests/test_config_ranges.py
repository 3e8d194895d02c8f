"""Config ranges (issue 59): every numeric field of every config section has its valid values beside it
(baselines/config.py `Range`), and a value outside them is one error naming the field, whichever way it
came: a preset or a model's head as written, a `cli train` option, `--set`, or config.json on --resume.
Before, `--set train.max_bad_steps=-1` started the run and stopped it at step 1."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import typing
from pathlib import Path

import pytest
from test_baselines_train import write_toy_dataset
from test_faults import cli, one_error_line

from baselines.config import PRESETS, Config, DataConfig, EncoderConfig, Range, TrainConfig, apply_overrides
from baselines.models import HEADS, load_config, resolve_config

# Numeric fields without a range, and why (none: camera_heights, any heights above the ground plane or below
# it, is finite).
UNRANGED: set[tuple[type, str]] = set()


def sections() -> list[type]:
    """Every config section's dataclass: the encoder, the data, the training and each model's head (and
    the head configs they build on)."""
    heads = {type(HEADS[model]("paper")) for model in HEADS}
    return [EncoderConfig, DataConfig, TrainConfig, *sorted(heads, key=lambda kind: kind.__name__)]


def is_numeric(kind: typing.Any) -> bool:
    if typing.get_origin(kind) is tuple:
        return all(is_numeric(item) for item in typing.get_args(kind) if item is not Ellipsis)
    return kind in (int, float)


def test_every_numeric_field_of_every_section_has_a_range():
    missing = []
    for section in sections():
        hints = typing.get_type_hints(section, include_extras=True)
        for item in dataclasses.fields(section):
            hint = hints[item.name]
            bare = typing.get_args(hint)[0] if typing.get_origin(hint) is typing.Annotated else hint
            ranges = [r for r in getattr(hint, "__metadata__", ()) if isinstance(r, Range)]
            if is_numeric(bare) and not ranges and (section, item.name) not in UNRANGED:
                missing.append(f"{section.__name__}.{item.name}")
    assert missing == []


@pytest.mark.parametrize("preset", sorted(PRESETS))
@pytest.mark.parametrize("model", sorted(HEADS))
def test_every_preset_and_head_is_in_range(preset, model):
    config = resolve_config(preset, model=model)
    config.check_ranges()  # what Config() checked as the preset was built, again on the whole
    assert config.train.max_bad_steps == 10


@pytest.mark.parametrize(
    "model, item, problem",
    [
        ("lanegap", "train.max_bad_steps=-1", "must be at least 0, not -1"),
        ("lanegap", "train.batch_size=0", "must be at least 1, not 0"),
        ("lanegap", "train.log_every=0", "must be at least 1, not 0"),
        ("lanegap", "train.lr=0", "must be greater than 0, not 0.0"),
        ("lanegap", "train.lr=nan", "must be greater than 0, not nan"),
        ("lanegap", "train.eps=inf", "must be greater than 0, not inf"),
        ("lanegap", "train.betas=0.9,1", "must be in [0, 1) each, not (0.9, 1.0)"),
        ("lanegap", "train.min_lr_ratio=1.5", "must be in [0, 1], not 1.5"),
        ("lanegap", "train.grad_clip=0", "must be in (0, inf], not 0.0"),
        ("lanegap", "train.seed=-1", "must be in [0, 2147483647], not -1"),
        ("lanegap", "encoder.x_range=15,-15", "must be increasing, not (15.0, -15.0)"),
        ("lanegap", "encoder.z_range=-5,inf", "must be finite each, not (-5.0, inf)"),
        # an unbounded end is no licence for infinity or NaN: a value is finite unless its range says
        ("lanegap", "encoder.x_range=-inf,15", "must be finite each, not (-inf, 15.0)"),
        ("lanegap", "encoder.y_range=nan,30", "must be finite each, not (nan, 30.0)"),
        ("lanegap", "encoder.camera_heights=nan,1", "must be finite each, not (nan, 1.0)"),
        ("lanegap", "encoder.camera_heights=0,-inf", "must be finite each, not (0.0, -inf)"),
        ("lanegap", "train.grad_clip=nan", "must be in (0, inf], not nan"),
        ("lanegap", "train.grad_clip=-inf", "must be in (0, inf], not -inf"),
        ("lanegap", "encoder.kernel_size=3,0", "must be at least 1 each, not (3, 0)"),
        ("lanegap", "encoder.backbone_frozen_stages=5", "must be in [-1, 4], not 5"),
        ("lanegap", "encoder.feature_stride=2", "must be in [4, 32], not 2"),
        ("lanegap", "data.image_crop_top=1", "must be in [0, 1), not 1.0"),
        ("lanegap", "data.num_workers=-2", "must be at least 0, not -2"),
        ("lanegap", "decoder.score_threshold=1.5", "must be in [0, 1], not 1.5"),
        ("lanegap", "decoder.path_points=1", "must be at least 2, not 1"),
        ("maptr", "decoder.dropout=-0.1", "must be in [0, 1), not -0.1"),
        ("maptr", "decoder.one_to_many_repeats=0", "must be at least 1, not 0"),
        ("stsu", "decoder.bezier_points=1", "must be at least 2, not 1"),
        ("hdmapnet", "decoder.resolution=0", "must be greater than 0, not 0.0"),
    ],
)
def test_a_value_out_of_range_from_set_is_refused_naming_the_field(model, item, problem):
    config = resolve_config("tiny", model=model)
    before = config.to_dict()
    with pytest.raises(ValueError) as refused:
        apply_overrides(config, [item])
    assert str(refused.value) == f"--set {item}: {item.partition('=')[0]} {problem}"
    assert config.to_dict() == before  # nothing set
    with pytest.raises(ValueError, match=f"^--set {re.escape(item)}: "):
        resolve_config("tiny", model=model, overrides=[item])


def test_the_ends_of_the_ranges_are_accepted():
    ends = ["train.max_bad_steps=0", "train.eval_every=0", "train.epochs=0", "train.grad_clip=inf",
            "train.warmup_ratio=1", "train.min_lr_ratio=0", "train.betas=0,0.999", "train.seed=2147483647",
            "train.backbone_lr_mult=0", "encoder.backbone_frozen_stages=-1", "encoder.dropout=0",
            "encoder.lidar_blocks=0", "data.image_crop_top=0.99", "decoder.score_threshold=1",
            "decoder.bezier_points=0"]  # fmt: skip
    config = resolve_config("paper", overrides=ends)
    assert config.train.grad_clip == math.inf and config.train.betas == (0.0, 0.999)
    assert config.encoder.backbone_frozen_stages == -1 and config.decoder.score_threshold == 1.0
    encoder = resolve_config("paper", overrides=["encoder.backbone_frozen_stages=4"]).encoder
    assert encoder.backbone_frozen_stages == 4


def test_the_options_of_cli_train_are_checked_by_name():
    with pytest.raises(ValueError, match=r"^--epochs: train\.epochs must be at least 0, not -1$"):
        resolve_config("tiny", epochs=-1)
    with pytest.raises(ValueError, match=r"^--path-points: decoder\.path_points must be at least 2, not 0$"):
        resolve_config("tiny", path_points=0)


def test_a_config_built_in_code_is_checked_too():
    with pytest.raises(ValueError, match=r"^train\.max_bad_steps must be at least 0, not -1$"):
        Config(train=TrainConfig(max_bad_steps=-1))
    config = resolve_config("tiny")
    with pytest.raises(ValueError, match=r"^encoder\.bev_h must be at least 1, not 0$"):
        dataclasses.replace(config, encoder=dataclasses.replace(config.encoder, bev_h=0))


def saved_config(folder: Path, section: str, name: str, value) -> Path:
    """A run folder's config.json (the tiny preset's) with `section.name` set to `value`, and its run.json."""
    folder.mkdir(parents=True, exist_ok=True)
    values = resolve_config("tiny").to_dict()
    values[section][name] = value
    (folder / "config.json").write_text(json.dumps(values))
    (folder / "run.json").write_text(json.dumps({"data": str(folder / "data")}))
    return folder / "config.json"


def test_a_saved_config_out_of_range_is_refused_naming_the_file(tmp_path):
    path = saved_config(tmp_path / "a", "train", "max_bad_steps", -1)
    with pytest.raises(ValueError) as refused:
        load_config(path)
    assert str(refused.value) == f"{path}: train.max_bad_steps must be at least 0, not -1"
    path = saved_config(tmp_path / "b", "encoder", "y_range", [30.0, -30.0])
    with pytest.raises(ValueError, match=r"encoder\.y_range must be increasing, not \(30\.0, -30\.0\)$"):
        load_config(path)
    assert load_config(saved_config(tmp_path / "c", "train", "max_bad_steps", 0)).train.max_bad_steps == 0


def test_cli_train_refuses_an_out_of_range_value_before_any_work(tmp_path):
    data = write_toy_dataset(tmp_path, frames=6)
    out = tmp_path / "run"
    args = ["train", "--data", data, "--out", out, "--preset", "tiny", "--modality", "lidar", "--epochs", 1]
    error = one_error_line(cli(*args, "--set", "train.max_bad_steps=-1"), "--set train.max_bad_steps=-1")
    assert error == "error: --set train.max_bad_steps=-1: train.max_bad_steps must be at least 0, not -1"
    assert not out.exists()
    one_error_line(cli(*args, "--set", "train.betas=0.9,1.5"), "train.betas must be in [0, 1) each")
    assert not out.exists()

    # --resume: the run's config.json, and the options that change it
    path = saved_config(out, "train", "max_bad_steps", -1)
    before = path.read_text()
    one_error_line(cli("train", "--out", out, "--resume"), f"{path}: train.max_bad_steps must be at least 0")
    (out / "config.json").write_text(json.dumps({**json.loads(before), "train": {"max_bad_steps": 2}}))
    one_error_line(
        cli("train", "--out", out, "--resume", "--set", "train.eval_frames=-5"),
        "--set train.eval_frames=-5: train.eval_frames must be at least 0, not -5",
    )
    assert sorted(p.name for p in out.iterdir()) == ["config.json", "run.json"]  # nothing written


@pytest.mark.parametrize("model", ["lanegap", "maptr", "stsu"])
def test_fields_that_the_build_needs_together_are_checked_where_the_config_is_built(model, tmp_path):
    # Before, --set decoder.heads=3 passed and build(config) ended in a bare AssertionError (torch's
    # MultiheadAttention): now one line naming both fields, by every way a config is built.
    heads = "encoder.channels 64 is not divisible by decoder.heads 3 (each attention head takes an equal"
    with pytest.raises(ValueError, match=f"^--set: {re.escape(heads)}"):
        resolve_config("tiny", model=model, overrides=["decoder.heads=3"])
    camera = "encoder.channels 64 is not divisible by encoder.camera_heads 3"
    with pytest.raises(ValueError, match=f"^--set: {camera}"):
        resolve_config("tiny", model=model, overrides=["encoder.camera_heads=3"])
    with pytest.raises(ValueError, match=r"^--set: encoder\.feature_stride must be 4, 8, 16 or 32 .* 12$"):
        resolve_config("tiny", model=model, overrides=["encoder.feature_stride=12"])
    with pytest.raises(ValueError, match=f"^{re.escape(heads)}"):  # a config built in code
        config = resolve_config("tiny", model=model)
        dataclasses.replace(config, decoder=dataclasses.replace(config.decoder, heads=3))
    values = resolve_config("tiny", model=model).to_dict()
    values["decoder"]["heads"] = 3
    path = tmp_path / "config.json"
    path.write_text(json.dumps(values))
    with pytest.raises(ValueError, match=f"^{re.escape(str(path))}: {re.escape(heads)}"):
        load_config(path)

    # checked once every --set is applied: a pair set one field at a time, in either order, is accepted
    for overrides in (["encoder.channels=48", "decoder.heads=6"], ["decoder.heads=6", "encoder.channels=48"]):
        config = resolve_config("tiny", model=model, overrides=overrides)
        assert (config.encoder.channels, config.decoder.heads) == (48, 6)
    # the camera branch's fields do not bind a LiDAR model, which has none
    lidar = resolve_config("tiny", model=model, modality="lidar", overrides=["encoder.camera_heads=3"])
    assert lidar.encoder.camera_heads == 3


def test_cli_train_refuses_fields_that_do_not_fit_together_before_any_work(tmp_path):
    data = write_toy_dataset(tmp_path, frames=6)
    out = tmp_path / "run"
    args = ["train", "--data", data, "--out", out, "--preset", "tiny", "--modality", "lidar", "--epochs", 1]
    error = one_error_line(cli(*args, "--set", "decoder.heads=3"), "encoder.channels 64", "decoder.heads 3")
    assert error.startswith("error: --set: encoder.channels 64 is not divisible by decoder.heads 3")
    assert not out.exists()
