"""The package as installed (issue 46): cli --version, package data declared, one OpenCV, the tools left
out. The wheel itself, installed in a fresh venv and run outside the checkout, is
.ci/wheel_smoke.sh (make wheel-smoke, in CI after the tests): a minute or two, too long for make test."""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from pathlib import Path

from benchmark.metric.params import METRIC_VERSION
from pipeline.io import SCHEMA_VERSION
from pipeline.kernels import AOT_NAME

REPO = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
PACKAGES = ("pipeline", "baselines", "benchmark")


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
    shipped = {f"{package.replace('.', '/')}/{name}" for package, names in declared.items() for name in names}
    assert all((REPO / path).is_file() for path in shipped), shipped
    data = {
        path.relative_to(REPO).as_posix()
        for package in PACKAGES
        for path in (REPO / package).rglob("*")
        if path.is_file()
        and path.suffix not in (".py", ".pyc")
        and "__pycache__" not in path.parts
        and not path.name.startswith(AOT_NAME)  # the kernels' build: made where it runs, never shipped
    }
    assert data <= shipped, data - shipped


def test_one_opencv_the_headless_build():
    lock = (REPO / "requirements.lock").read_text().lower().split()
    opencv = [line for line in lock if line.startswith("opencv")]
    assert [line.split("==")[0] for line in opencv] == ["opencv-python-headless"], opencv
    dependencies = [d.lower() for d in PYPROJECT["project"]["dependencies"] if d.lower().startswith("opencv")]
    assert [re.split("[<>=]", d)[0] for d in dependencies] == ["opencv-python-headless"], dependencies


def test_the_tools_run_from_a_checkout_and_stay_out_of_the_wheel():
    included = PYPROJECT["tool"]["setuptools"]["packages"]["find"]["include"]
    assert sorted(included) == sorted(f"{package}*" for package in PACKAGES), included
    assert (REPO / "tools" / "__init__.py").is_file()
