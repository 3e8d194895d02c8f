"""Every command's --help follows the command line's conventions (issue 30): choices are typed and
listed, numbers carry their range, every option shows its effective default, the repeatable SPLIT=FILE
and section.field=value options say so, each help ends with examples and holds no implementation notes,
and --json means the same on every command that prints a result table."""

from __future__ import annotations

import subprocess
import sys
import typing
from pathlib import Path

import pytest
from typer._click import Context
from typer.main import get_command
from typer.testing import CliRunner

import cli
from cli import app

REPO = Path(__file__).resolve().parents[1]
COMMANDS = get_command(app).commands
CHOICES = {  # the options whose values are a closed set: typed, so that click lists and checks them
    "prepare": {"dataset", "executor", "on_error", "split_scheme", "subset"},
    "train": {"model", "preset", "modality", "path_points", "best_metric"},
    "eval": {"device", "checkpoint"},
    "score": {"matching", "format_"},
    "roundtrip": {"via"},
    "report": {"reference"},
}
TABLES = {"synth", "prepare", "train", "eval", "score", "roundtrip", "report"}  # print a result table
NOTES = ("import", "pytest", "tests/", "baselines/", "pipeline/", "benchmark/", ".py", "torch.", "numba")


def options(name: str):
    """(option, its help record: (flags and metavar, help with its [default: ...; range] part))."""
    command = COMMANDS[name]
    ctx = Context(command, info_name=name)
    found = [(p, p.get_help_record(ctx)) for p in command.params if p.param_type_name == "option"]
    assert found, name
    return found


def test_the_commands_are_all_here():
    assert list(COMMANDS) == ["synth", "prepare", "train", "eval", "score", "roundtrip", "report", "viz"]


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_option_has_help_its_default_and_its_range(name):
    for option, (flags, text) in options(name):
        assert option.help, (name, flags)
        flag = option.is_bool_flag and not option.secondary_opts  # --json: off unless given
        assert flag or "[default:" in text or "required]" in text, (name, flags, text)
        if option.type_descriptor.annotation in (int, float):
            assert any(r in text for r in ("x>=", "<=x", "x<=", "(x>0)")), (name, flags, text)
        typed = option.type_descriptor.choices is not None
        assert typed == (option.name in CHOICES.get(name, ())), (name, flags)
        if typed:  # click lists them
            assert "|".join(map(str, option.type_descriptor.choices)) in flags
        assert not any(note in option.help for note in NOTES), (name, flags, option.help)


def test_repeatable_options_show_what_to_repeat():
    flags = {(name, option.name): record[0] for name in COMMANDS for option, record in options(name)}
    assert flags["prepare", "split_file"] == "--split-file SPLIT=FILE"
    assert flags["train", "set_"] == "--set section.field=value"
    assert flags["report", "runs"] == "--runs RUN" and flags["report", "roundtrip"] == "--roundtrip JSON"


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_help_ends_with_examples_and_holds_no_implementation_notes(name):
    result = CliRunner().invoke(app, [name, "--help"])
    assert result.exit_code == 0, result.output
    description = result.output.split("Options:")[0]
    head, examples = description.split("Examples:")
    lines = [line.strip() for line in examples.strip().splitlines()]
    assert 1 <= len(lines) <= 2 and all(line.startswith(("cli ", "torchrun ")) for line in lines), lines
    assert all(f" {name} " in f"{line} " for line in lines), lines
    assert not any(note in head for note in NOTES), head


def test_json_is_the_same_option_on_every_command_with_a_result_table():
    for name in COMMANDS:
        flags = {record[0]: option.help for option, record in options(name)}
        assert ("--json" in flags) == (name in TABLES), name
        if name in TABLES:
            assert flags["--json"] == cli.JSON_HELP


def test_the_choices_and_preset_defaults_are_those_of_the_config():
    """`cli --help` does not import torch, so the train options' choices and preset defaults are written
    out in cli.py; they must be those of baselines/config.py and baselines/models."""
    from baselines.config import PAPER_EPOCHS, PRESETS, EncoderConfig
    from baselines.config import BestMetric as ConfigBestMetric
    from baselines.config import Modality as ConfigModality
    from baselines.models import HEADS, resolve_config

    assert typing.get_args(cli.Model) == tuple(HEADS)
    assert typing.get_args(cli.Preset) == tuple(PRESETS)
    assert typing.get_args(cli.Modality) == typing.get_args(ConfigModality)
    assert typing.get_args(cli.BestMetric) == typing.get_args(ConfigBestMetric)
    presets = {name: resolve_config(name) for name in PRESETS}  # LaneGAP, cli train's default model
    assert PAPER_EPOCHS == {"nuscenes": 110, "av2": 24, "openlanev2": 24}
    values = {
        # 0: the paper's schedule of the dataset's kind
        "epochs": {name: c.train.epochs or "110 on nuScenes, 24 on AV2 and OpenLane-V2"
                   for name, c in presets.items()},
        "batch_size": {name: c.train.batch_size for name, c in presets.items()},
        "modality": {name: c.encoder.modality for name, c in presets.items()},
        "path_points": {name: c.decoder.path_points for name, c in presets.items()},
    }
    for option, by_preset in values.items():
        expected = ", ".join(f"{name} {value}" for name, value in by_preset.items())
        assert cli.PRESET_DEFAULTS[option] == expected, option
    assert all(c.decoder.bezier_points == 0 and c.decoder.aux_seg for c in presets.values())
    assert EncoderConfig().modality == "camera"


def test_help_does_not_import_torch():
    code = (
        "import sys, cli; cli.app(['train', '--help'], standalone_mode=False); print('torch' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.strip().endswith("False"), done.stdout + done.stderr
