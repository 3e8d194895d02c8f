"""README.md's quoted leakage lines are what `cli prepare` prints on the data the README names: the test
suite's synthetic data (conftest's synth_raw, AV2 format), on its own split and by the geographic scheme."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from cli import app
from pipeline.manifest import read_manifest
from pipeline.splits.leakage import leakage_line

README = Path(__file__).resolve().parents[1] / "README.md"


def quoted_leakage_lines() -> list[str]:
    """The README's indented lines that quote a leakage line, in order."""
    return [
        line.strip()
        for line in README.read_text().splitlines()
        if line.startswith("    split scheme ") and "; leakage: " in line
    ]


def test_the_readmes_leakage_lines_are_what_prepare_prints(synth_raw, synth_prepared, tmp_path):
    # the default options: conftest's synth_prepared is that run (its manifest holds the summary's
    # leakage, from which `cli prepare` prints its line)
    own = leakage_line(read_manifest(synth_prepared["av2"])["leakage"], "original")
    root = synth_raw / "av2" / "sensor"
    args = ["prepare", "--dataset", "av2", "--root", str(root), "--out", str(tmp_path / "geo"),
            "--split-scheme", "geographic", "--geo-cell", "50", "--geo-seed", "3"]  # fmt: skip
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    (geographic,) = [line for line in result.output.splitlines() if line.startswith("split scheme ")]
    assert quoted_leakage_lines() == [own, geographic]
