#!/usr/bin/env bash
# `make gpu-check` on a GPU machine that reaches no package index (its python3 holds CUDA torch and most
# of the project's packages):
#
#   here, with an index:  make wheelhouse   # wheelhouse/: wheels of the packages that machine lacks + ours
#   there, copied along: make gpu-check    # runs this script, since wheelhouse/ exists (or: bash this file)
#
# 1. $VENV (.venv-gpu) by `$PYTHON -m venv --system-site-packages`, so that it sees the machine's torch,
#    numpy, scipy, pyarrow, opencv... PYTHON is the interpreter that holds CUDA torch (default: python3 on
#    the PATH; e.g. PYTHON=/path/to/venv/bin/python where an image keeps torch in a venv of its own). A
#    venv made from a venv's python sees only the base interpreter's site, so a .pth file adds $PYTHON's
#    site-packages.
# 2. The wheelhouse, --no-index --no-deps: the machine's own torch and numpy stand in for the lock's
#    torch==2.13.0 and nuscenes-devkit's numpy<2, which pip's resolver would refuse. Then every module the
#    commands import, and the packages whose versions differ from requirements.lock (in the log).
#    Then `cli --help` and the help of every command the check runs: typer builds them all, so an
#    incompatible typer fails here, before any GPU time.
# 3. torch.cuda.is_available() (it must be, unless --smoke), then `python -m tools.bench_step --preset
#    gpu` (at most BENCH_LIMIT s) and `python -m tools.gpu_check --bench bench_step/bench_step.json`
#    (every model the same epochs, the most that fit; without the bench a short fixed schedule), under
#    `timeout` so that the whole script ends within LIMIT s of its start. A model that fails does not stop
#    the others: summary.json records its failure with the last lines of its output, and the script exits
#    non-zero at the end.
# 4. Each result into the folder you choose, $GPU_CHECK_OUT (default gpu_check_out/: a handful of files,
#    quick to copy off the machine and read), as its stage ends: gpu_setup.log (all output, as it comes),
#    environment.txt, bench_step.json after the bench; runs.tar.gz (every finished run's metrics.json and
#    run.json) and summary.json so far after each model (gpu_check --results); report.md and the final
#    summary.json at the end. A timeout keeps what finished.
#
# Options: --smoke   `gpu_check --smoke` (tiny data, one epoch, any device), no bench_step
#          --system  no venv and no wheelhouse: run with $PYTHON as it is (make gpu-check with .venv)
# Environment: PYTHON (python3), WHEELHOUSE (wheelhouse), VENV (.venv-gpu), GPU_CHECK_OUT (gpu_check_out),
#   LIMIT (your time limit for the whole script, in seconds: 540 by default, the check's 10 minutes less
#   one, so that a hung or slow run stops by itself, results saved, inside them; raise it on a slower GPU;
#   3600 with --smoke, whose CPU run in CI took 527 s on a quiet machine, 1,277 s beside other jobs),
#   BENCH_LIMIT (120), GPU_CHECK_ARGS (more gpu_check options, e.g. --train-seconds 100), and, for make
#   gpu-dryrun alone, HIDE: distributions of $PYTHON's site-packages that $VENV must not see (the lock's
#   packages that a CUDA PyTorch image lacks), so that a CPU machine stands in for such an image.
#   GPU_CHECK_STARTED (set here: epoch seconds at the script's start) times the whole for gpu_check.
set -euo pipefail
script=$(cd "$(dirname "$0")" && pwd)/$(basename "$0")
cd "$(dirname "$script")/.."
out=${GPU_CHECK_OUT:-gpu_check_out}
if [[ -z ${GPU_SETUP_LOG:-} ]]; then  # run again, everything into the log too
    # the check's wall time and time limit count from here, set-up included
    GPU_CHECK_STARTED=$(date +%s.%N)
    export GPU_CHECK_STARTED
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
if ((smoke)); then limit=${LIMIT:-3600}; else limit=${LIMIT:-540}; fi
bench_limit=${BENCH_LIMIT:-120}
grace=15  # after gpu_check's limit: timeout's kill 5 s later, then this script's last lines
export PYTHONUNBUFFERED=1
: "${GPU_CHECK_STARTED:=$(date +%s.%N)}"  # set by the first pass above; this file run by hand otherwise
export GPU_CHECK_STARTED
elapsed() { echo $(($(date +%s) - ${GPU_CHECK_STARTED%.*})); }
step() { echo "== $* ($(elapsed) s)"; }

if ((system)); then
    py=$PYTHON
else
    step "venv $VENV from $WHEELHOUSE, no index"
    if ! compgen -G "$WHEELHOUSE/lanegraph-*.whl" >/dev/null; then
        echo "no $WHEELHOUSE/lanegraph-*.whl: run make wheelhouse where there is an index and copy $WHEELHOUSE/ here" >&2
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
# importing cli builds no command: typer does so for --help, as for a run
"$py" -m cli --help >/dev/null
for command in synth prepare train eval report; do
    "$py" -m cli "$command" --help >/dev/null
done
echo "cli --help and its commands' help: ok"
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

# `cmd...` under a time limit of its seconds, at most what is left of LIMIT less the grace: its exit
# status (124 when the limit stopped it; timeout signals its whole process group, cli's children too)
limited() {
    local seconds=$1 left rc=0
    shift
    left=$((limit - $(elapsed) - grace))
    if ((seconds > left)); then seconds=$left; fi
    if ((seconds <= 0)); then
        echo "no time left for $* (LIMIT $limit s)" >&2
        return 124
    fi
    timeout --kill-after=5 "$seconds" "$@" || rc=$?
    if ((rc == 124 || rc == 137)); then
        echo "stopped at its time limit of $seconds s (LIMIT $limit s from the script's start): $*" >&2
    fi
    return "$rc"
}

rc=0
if ((smoke)); then
    step "gpu_check --smoke"
    limited "$limit" "$py" -m tools.gpu_check --smoke --out gpu_smoke --results "$out" || rc=$?
else
    step "bench_step --preset gpu"
    bench=()
    bench_rc=0
    limited "$bench_limit" "$py" -m tools.bench_step --preset gpu --out bench_step || bench_rc=$?
    if ((bench_rc == 0)); then
        cp bench_step/bench_step.json "$out/"
        bench=(--bench bench_step/bench_step.json)
    else
        rc=$bench_rc
        echo "bench_step failed (exit $bench_rc, its error above): gpu_check trains its short fixed schedule" >&2
    fi
    step "gpu_check ${bench[*]} ${GPU_CHECK_ARGS:-}"
    # shellcheck disable=SC2086  # GPU_CHECK_ARGS: more options, word by word
    limited "$limit" "$py" -m tools.gpu_check --out gpu_check --results "$out" "${bench[@]}" \
        ${GPU_CHECK_ARGS:-} || rc=$?
fi
step "done, exit $rc: $out/ holds $(cd "$out" && echo *)"
exit "$rc"
