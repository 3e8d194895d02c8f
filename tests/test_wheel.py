"""The package as installed (issue 46): cli --version, package data declared, one OpenCV, scripts that need
the checkout saying so. The wheel itself, installed in a fresh venv and run outside the checkout, is
.ci/wheel_smoke.sh (make wheel-smoke, in CI after the tests): a minute or two, too long for make test."""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

import pipeline.checkout
from benchmark.metrics import METRIC_VERSION
from pipeline.io import SCHEMA_VERSION

REPO = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
PACKAGES = ("pipeline", "baselines", "benchmark")
# files in the packages that no installed module reads: they run from a checkout
CHECKOUT_ONLY = {"baselines/gpu_setup.sh"}


def test_version_names_the_package_metric_and_schema_without_torch():
    code = "import sys, cli; cli.app(['--version'], standalone_mode=False); print('torch' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    line, torch_imported = done.stdout.strip().splitlines()
    assert torch_imported == "False"
    versions = f"metric_version {METRIC_VERSION}, prepared-data schema_version {SCHEMA_VERSION}"
    assert re.fullmatch(rf"lanegraph \S+ \({versions}\)", line), line


def test_the_changelog_has_this_version():
    version = PYPROJECT["project"]["version"]
    assert re.search(rf"^## {re.escape(version)} ", (REPO / "CHANGELOG.md").read_text(), re.M), version


def test_every_data_file_of_the_packages_is_declared_package_data():
    """A file beside the modules that the installed package reads must be in the wheel: pyproject.toml's
    [tool.setuptools.package-data] (setuptools ships .py files only unless told)."""
    declared = PYPROJECT["tool"]["setuptools"]["package-data"]
    shipped = {f"{package}/{name}" for package, names in declared.items() for name in names}
    assert all((REPO / path).is_file() for path in shipped), shipped
    data = {
        path.relative_to(REPO).as_posix()
        for package in PACKAGES
        for path in (REPO / package).rglob("*")
        if path.is_file() and path.suffix not in (".py", ".pyc") and "__pycache__" not in path.parts
    }
    assert data - CHECKOUT_ONLY <= shipped, data - CHECKOUT_ONLY - shipped


def test_one_opencv_the_headless_build():
    lock = (REPO / "requirements.lock").read_text().lower().split()
    opencv = [line for line in lock if line.startswith("opencv")]
    assert [line.split("==")[0] for line in opencv] == ["opencv-python-headless"], opencv
    dependencies = [d.lower() for d in PYPROJECT["project"]["dependencies"] if d.lower().startswith("opencv")]
    assert [re.split("[<>=]", d)[0] for d in dependencies] == ["opencv-python-headless"], dependencies


def test_a_script_that_needs_the_checkout_says_so_from_an_install(tmp_path, monkeypatch, capsys):
    assert pipeline.checkout.is_checkout()
    monkeypatch.setattr(pipeline.checkout, "ROOT", tmp_path)  # as site-packages: no pyproject.toml there
    with pytest.raises(SystemExit) as stopped:
        pipeline.checkout.checkout_root("python -m baselines.gpu_check", "make gpu-check in a clone")
    assert stopped.value.code == 2
    said = capsys.readouterr().err
    assert said.count("\n") == 1 and "checkout" in said and "make gpu-check" in said, said
