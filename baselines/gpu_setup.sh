#!/usr/bin/env bash
# `make gpu-check` on a GPU machine that reaches no package index (its python3 holds CUDA torch and most
# of the project's packages):
#
#   here, with an index:  make wheelhouse   # wheelhouse/: wheels of the packages that machine lacks + ours
#   there, carried along: make gpu-check    # runs this script, since wheelhouse/ exists (or: bash this file)
#
# 1. $VENV (.venv-gpu) by `$PYTHON -m venv --system-site-packages`, so that it sees the machine's torch,
#    numpy, scipy, pyarrow, opencv... A venv made from a venv's python (the GPU image's python3 lives in
#    /opt/torch/.venv) sees only the base interpreter's site, so a .pth file adds $PYTHON's site-packages.
# 2. The wheelhouse, --no-index --no-deps: the machine's own torch and numpy stand in for the lock's
#    torch==2.13.0 and nuscenes-devkit's numpy<2, which pip's resolver would refuse. Then every module the
#    commands import, and the packages whose versions differ from requirements.lock (in the log).
# 3. torch.cuda.is_available() (it must be, unless --smoke), then `python -m baselines.bench_step --preset
#    gpu` and `python -m baselines.gpu_check --bench bench_step/bench_step.json` (epochs sized by it).
# 4. The key outputs into $OUT (the device tool's folder there) or gpu_check_out/: gpu_setup.log (all
#    output), environment.txt, bench_step.json, summary.json, report.md.
#
# Options: --smoke   `gpu_check --smoke` (tiny data, one epoch, any device), no bench_step
#          --system  no venv and no wheelhouse: run with $PYTHON as it is (make gpu-check with .venv)
# Environment: PYTHON (python3), WHEELHOUSE (wheelhouse), VENV (.venv-gpu), OUT (gpu_check_out),
#   GPU_CHECK_ARGS (more gpu_check options, e.g. --train-seconds 200 under a time limit), and, for
#   make gpu-dryrun alone, HIDE: distributions of $PYTHON's site-packages that $VENV must not see (the
#   lock's packages that the GPU image lacks), so that a CPU machine stands in for that image.
set -euo pipefail
script=$(cd "$(dirname "$0")" && pwd)/$(basename "$0")
cd "$(dirname "$script")/.."
out=${OUT:-gpu_check_out}
if [[ -z ${GPU_SETUP_LOG:-} ]]; then  # run again, everything into the log too
    mkdir -p "$out"
    export GPU_SETUP_LOG="$out/gpu_setup.log"
    bash "$script" "$@" 2>&1 | tee "$GPU_SETUP_LOG"
    exit "${PIPESTATUS[0]}"
fi

PYTHON=${PYTHON:-python3}
WHEELHOUSE=${WHEELHOUSE:-wheelhouse}
VENV=${VENV:-.venv-gpu}
smoke=0 system=0
for arg in "$@"; do
    case $arg in
        --smoke) smoke=1 ;;
        --system) system=1 ;;
        *) echo "usage: $0 [--smoke] [--system]" >&2; exit 2 ;;
    esac
done
export PYTHONUNBUFFERED=1
start=$SECONDS
step() { echo "== $* ($((SECONDS - start)) s)"; }

if ((system)); then
    py=$PYTHON
else
    step "venv $VENV from $WHEELHOUSE, no index"
    if ! compgen -G "$WHEELHOUSE/lanegraph-*.whl" >/dev/null; then
        echo "no $WHEELHOUSE/lanegraph-*.whl: run make wheelhouse where there is an index, carry $WHEELHOUSE/" >&2
        exit 1
    fi
    version=$("$PYTHON" -c 'import sys; print("%d.%d" % sys.version_info[:2])')
    if [[ $(cat "$WHEELHOUSE/python-version") != "$version" ]]; then
        echo "$WHEELHOUSE/ holds wheels for Python $(cat "$WHEELHOUSE/python-version"), $PYTHON is $version:" \
            "make wheelhouse WHEEL_PYTHON=$version" >&2
        exit 1
    fi
    rm -rf "$VENV"
    # --without-pip: the pip of $PYTHON's site serves (ensurepip may be missing from a distribution's python)
    "$PYTHON" -m venv --system-site-packages --without-pip "$VENV"
    py=$VENV/bin/python
    venv_site=$("$py" -c 'import sysconfig; print(sysconfig.get_path("purelib"))')
    # $PYTHON's own site-packages when it is a venv (none when it is a base interpreter)
    mapfile -t base_sites < <("$PYTHON" -c 'import site, sys
if sys.prefix != sys.base_prefix:
    print("\n".join(site.getsitepackages()))')
    if [[ -n ${HIDE:-} ]]; then  # make gpu-dryrun: a copy of that site, made of links, less $HIDE
        HIDE=$HIDE "$PYTHON" - "$VENV/base-site" "${base_sites[@]}" <<'EOF'
import importlib.metadata as md, os, re, sys
norm = lambda name: re.sub(r"[-_.]+", "-", name).lower()
hide = {norm(name) for name in os.environ["HIDE"].split()}
farm = sys.argv[1]
os.makedirs(farm, exist_ok=True)
for site in sys.argv[2:]:
    owners = {}  # top-level entry -> the distributions that own files in it
    for dist in md.distributions(path=[site]):
        for file in dist.files or []:
            if file.parts[0] != "..":
                owners.setdefault(file.parts[0], set()).add(norm(dist.metadata["Name"]))
    for entry in os.listdir(site):
        if not (entry in owners and owners[entry] <= hide) and not os.path.lexists(os.path.join(farm, entry)):
            os.symlink(os.path.join(os.path.abspath(site), entry), os.path.join(farm, entry))
EOF
        base_sites=("$(cd "$VENV/base-site" && pwd)")
    fi
    for site in "${base_sites[@]}"; do
        echo "import site; site.addsitedir('$site')"
    done >"$venv_site/_base_site.pth"
    "$py" -m pip install --quiet --no-index --find-links "$WHEELHOUSE" --no-deps --ignore-installed \
        -r "$WHEELHOUSE/requirements.txt" lanegraph
fi

step "environment"
"$py" - <<'EOF'
import importlib, importlib.metadata as md
for module in ("cli", "av2.map.map_api", "av2.utils.io", "av2.geometry.camera.pinhole_camera",
               "nuscenes.map_expansion.map_api", "shapely", "cv2", "numba", "skimage", "scipy", "pyarrow",
               "pandas", "matplotlib", "networkx", "typer", "rich", "torch"):
    importlib.import_module(module)  # fails here, before any GPU time, on a missing package
differ, absent = [], []
for line in open("requirements.lock"):
    if "==" not in line:
        continue
    name, pinned = line.strip().split("==")
    try:
        version = md.version(name)
    except md.PackageNotFoundError:
        absent.append(name)
        continue
    if version != pinned:
        differ.append(f"{name} {version} (lock {pinned})")
print("imports: ok")
print("versions other than requirements.lock's:", ", ".join(differ) or "none")
print("absent here from the lock (not imported by the code):", " ".join(absent) or "none")
EOF
{
    "$py" -c 'import sys; print("python", sys.version)'
    command -v nvidia-smi >/dev/null && nvidia-smi
    "$py" -m pip list --disable-pip-version-check 2>/dev/null
} >"$out/environment.txt" || true
cuda_ok=0
"$py" -c 'import sys, torch
ok = torch.cuda.is_available()
print(f"torch {torch.__version__} (CUDA {torch.version.cuda}):", torch.cuda.get_device_name(0) if ok else "no CUDA device")
sys.exit(0 if ok else 1)' && cuda_ok=1
if ((!smoke && !cuda_ok)); then
    echo "torch sees no CUDA device: make gpu-check needs one (--smoke runs on any device)" >&2
    exit 1
fi

rc=0
if ((smoke)); then
    step "gpu_check --smoke"
    "$py" -m baselines.gpu_check --smoke --out gpu_smoke || rc=$?
    results=(gpu_smoke/summary.json gpu_smoke/report/report.md)
else
    step "bench_step --preset gpu"
    bench=()
    if "$py" -m baselines.bench_step --preset gpu --out bench_step; then
        bench=(--bench bench_step/bench_step.json)
    else
        rc=$?
        echo "bench_step failed (exit $rc): gpu_check runs the gpu preset's epochs" >&2
    fi
    step "gpu_check ${bench[*]} ${GPU_CHECK_ARGS:-}"
    # shellcheck disable=SC2086  # GPU_CHECK_ARGS: more options, word by word
    "$py" -m baselines.gpu_check --out gpu_check "${bench[@]}" ${GPU_CHECK_ARGS:-} || rc=$?
    results=(bench_step/bench_step.json gpu_check/summary.json gpu_check/report/report.md)
fi
for file in "${results[@]}"; do
    if [[ -f $file ]]; then cp "$file" "$out/"; fi
done
step "done, exit $rc: $out/ holds $(cd "$out" && echo *)"
exit "$rc"
