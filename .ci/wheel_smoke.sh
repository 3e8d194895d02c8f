#!/usr/bin/env bash
# The installed package, away from the checkout (make wheel-smoke, in CI after the tests): lanegraph's wheel
# built from a copy of the sources git knows (tracked, or new and not ignored), a fresh venv holding
# requirements.lock (--no-deps: the lock is the whole closure, whose one OpenCV is opencv-python-headless)
# and that wheel, then, from a temporary folder outside the checkout: cli --help, cli --version, cli synth ->
# prepare (AV2 and nuScenes) -> score -> report --reference paper on a tiny dataset. tools/ (benchmarks, the
# GPU check) runs from a checkout and stays out of the wheel.
# A file the package needs but does not declare (package data) fails here, not on a user's machine.
#
# Environment: PYTHON (the interpreter the venv is made from: .venv/bin/python), KEEP=1 keeps the
# temporary folder (its path is printed).
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$(pwd)
PYTHON=${PYTHON:-.venv/bin/python}
tmp=$(mktemp -d "${TMPDIR:-/tmp}/lanegraph-wheel.XXXXXX")
if [[ ${KEEP:-0} == 1 ]]; then echo "keeping $tmp"; else trap 'rm -rf "$tmp"' EXIT; fi
start=$SECONDS
step() { echo "== $* ($((SECONDS - start)) s)"; }
fail() { echo "wheel smoke: $*" >&2; exit 1; }

step "wheel from the sources (copied to $tmp/src)"
git ls-files -z --cached --others --exclude-standard -- pyproject.toml cli.py pipeline baselines benchmark |
    while IFS= read -r -d '' file; do
        if [[ -f $file ]]; then mkdir -p "$tmp/src/$(dirname "$file")" && cp "$file" "$tmp/src/$file"; fi
    done
"$PYTHON" -m pip wheel --quiet --no-deps --no-build-isolation --wheel-dir "$tmp/dist" "$tmp/src"
wheel=$(echo "$tmp"/dist/lanegraph-*.whl)
[[ -f $wheel ]] || fail "no wheel in $tmp/dist"
"$PYTHON" - "$wheel" <<'EOF'
import sys, zipfile
names = zipfile.ZipFile(sys.argv[1]).namelist()
needed = ["cli.py", "benchmark/report/paper_reference.toml", "pipeline/io.py", "baselines/models/__init__.py",
          "benchmark/report/assets/browser.js", "benchmark/report/assets/style.css"]
missing = [name for name in needed if name not in names]
assert not missing, f"the wheel lacks {missing}"
assert not any(name.startswith(("tests/", "tools/")) for name in names), "the wheel holds tests/ or tools/"
print(f"{sys.argv[1].rsplit('/', 1)[-1]}: {len(names)} files")
EOF

step "fresh venv: requirements.lock and the wheel, --no-deps"
"$PYTHON" -m venv "$tmp/venv"
venv=$tmp/venv/bin
"$venv/python" -m pip install --quiet --quiet --no-deps -r requirements.lock "$wheel"  # errors only
# the lock must hold every requirement of what it installs; av2 alone asks for opencv-python (the GUI build),
# whose cv2 would overwrite the headless one's: the lock leaves it out on purpose
broken=$("$venv/python" -m pip check 2>&1 |
    grep -v "^av2 [^ ]* requires opencv-python, which is not installed" || true)
[[ -z $broken || $broken == "No broken requirements found." ]] || fail "pip check: $broken"

step "from $tmp/work, outside the checkout"
mkdir "$tmp/work"
cd "$tmp/work"
unset PYTHONPATH
"$venv/python" - "$repo" <<'EOF'
import importlib, sys
from pathlib import Path
repo = Path(sys.argv[1]).resolve()
for name in ("cli", "pipeline", "baselines", "benchmark", "cv2"):
    where = Path(importlib.import_module(name).__file__).resolve()
    assert repo not in where.parents, f"{name} imported from the checkout: {where}"
import importlib.metadata as md
import cv2
try:
    md.distribution("opencv-python")
    raise AssertionError("opencv-python (the GUI build) is installed beside opencv-python-headless")
except md.PackageNotFoundError:
    pass
gui = [line.strip() for line in cv2.getBuildInformation().splitlines() if line.strip().startswith("GUI:")]
print("cv2", cv2.__version__, "from opencv-python-headless,", *gui)
print("imports from", Path(importlib.import_module("pipeline").__file__).parent.parent)
EOF
"$venv/cli" --help >/dev/null
version=$("$venv/cli" --version)
echo "$version"
expected=$("$venv/python" -c 'import importlib.metadata as m; print(m.version("lanegraph"))')
[[ $version == *"lanegraph $expected"* && $version == *metric_version* && $version == *schema_version* ]] ||
    fail "cli --version printed '$version'"
"$venv/cli" synth --out raw --logs 2 --frames-per-log 2 --val-frames-per-log 2 --worlds 2 >/dev/null
"$venv/cli" prepare --dataset av2 --root raw/av2/sensor --out prepared/av2 >/dev/null
"$venv/cli" prepare --dataset nuscenes --root raw/nuscenes --version v1.0-mini \
    --out prepared/nuscenes >/dev/null
# the ground truth scored as a prediction: a run folder that cli report shows as external
"$venv/cli" score --pred prepared/av2/graphs --gt prepared/av2 --bootstrap 20 --out runs/gt_av2 >/dev/null
"$venv/cli" score --pred prepared/nuscenes/graphs --gt prepared/nuscenes --bootstrap 0 --json >score.json
"$venv/python" -c 'import json, sys; sys.exit(json.load(open("score.json"))["directed"]["topo"]["f1"] != 1)' ||
    fail "the nuScenes ground truth does not score F1 1 against itself"
"$venv/cli" report --runs runs --out report --reference paper --bootstrap 20 >report.log
grep -q "tab:modeling" report/report.md || fail "report.md holds no paper reference table"
ls report/*.png >/dev/null || fail "report/ holds no picture"
grep -q 'id="browser-data"' report/report.html || fail "report.html holds no frame browser"

step "done"
