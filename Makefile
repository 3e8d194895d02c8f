# Set-up is part of every target: a fresh clone needs only `make demo` or `make test`.
PY := .venv/bin/python
STAMP := .venv/.installed
DEMO := demo
DEMO_ALL := demo_all
DEMO_SYNTH :=
DEMO_TRAIN :=
# The demo's trainings validate every DEMO_EVAL_EVERY epochs and after the last one (the tiny preset: every
# epoch): the validation curve keeps its points while the demo keeps within its promised time.
DEMO_EVAL_EVERY := 4
CLI := .venv/bin/cli
KERNELS := pipeline/_aot_kernels.json

.PHONY: demo demo-all kernels chromium test test-learning wheel-smoke gpu-check gpu-smoke gpu-dryrun wheelhouse bench \
	bench-train bench-step lint clean

# The lock is the whole closure, installed --no-deps: one OpenCV, the headless build (av2 declares the GUI
# build, opencv-python, whose cv2 overwrites the headless one's; a .venv made before drops it, and the
# headless files it shared are installed again).
$(STAMP): requirements.lock pyproject.toml
	test -x $(PY) || python3.11 -m venv .venv || python3 -m venv .venv
	$(PY) -m pip install --quiet --no-deps -r requirements.lock
	if $(PY) -m pip show --quiet opencv-python 2>/dev/null; then \
		$(PY) -m pip uninstall --quiet --yes opencv-python && $(PY) -m pip install --quiet --no-deps \
		--force-reinstall $$(grep -ix 'opencv-python-headless==[^ ]*' requirements.lock); fi
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $(STAMP)

# The demo's pipeline, one recipe for every model (tiny preset, fusion): $(1) the folder, $(2) the models,
# $(3) more `cli report` options, $(4) more `cli train` options. DEMO_SYNTH and DEMO_TRAIN add options to
# `cli synth` and to every `cli train`, e.g. a quick check of the steps: make demo-all DEMO_SYNTH="--logs 4" DEMO_TRAIN="--epochs 1"
# (the nuScenes version, v1.0-mini or v1.0-trainval by the number of logs, is read from synth.json).
# It ends with `cli report`, which prints the main table and the path of report.md.
define demo_pipeline
	rm -rf $(1)
	$(CLI) synth --out $(1)/raw $(DEMO_SYNTH)
	$(CLI) prepare --dataset av2 --root $(1)/raw/av2/sensor --out $(1)/prepared/av2
	$(CLI) prepare --dataset nuscenes --root $(1)/raw/nuscenes --out $(1)/prepared/nuscenes \
		--version $$($(PY) -c "import json; print(json.load(open('$(1)/raw/synth.json'))['nuscenes_version'])")
	$(CLI) roundtrip --data $(1)/prepared/av2 --via path --out $(1)/roundtrip_path.json
	$(CLI) roundtrip --data $(1)/prepared/av2 --via piece --out $(1)/roundtrip_piece.json
	$(CLI) roundtrip --data $(1)/prepared/av2 --via pixel --out $(1)/roundtrip_pixel.json
	for model in $(2); do \
		$(CLI) train --model $$model --data $(1)/prepared/av2 --out $(1)/runs/$${model}_fusion --preset tiny --eval-every $(DEMO_EVAL_EVERY) $(4) $(DEMO_TRAIN) \
		&& $(CLI) eval --run $(1)/runs/$${model}_fusion --data $(1)/prepared/av2 --split val || exit 1; \
	done
	$(CLI) report --runs $(1)/runs --roundtrip $(1)/roundtrip_path.json --roundtrip $(1)/roundtrip_piece.json --roundtrip $(1)/roundtrip_pixel.json --out $(1)/report $(3)
endef

# `make kernels`: the kernels that `cli score` calls, compiled ahead of time (pipeline/kernels.py; 40 s, 2
# minutes from a fresh clone), so that it starts without numba; `make test` and `make bench` build them first.
# Again whenever a module of pipeline/ or benchmark/ changed, since a build of other sources is not used. It
# needs a C compiler; without one the kernels run under numba's JIT (the same scores, a slower start). The
# demo does not wait for it: it would add about 2 minutes to the demo's 15 and save it a few seconds.
kernels: $(KERNELS)

$(KERNELS): $(STAMP) tools/build_kernels.py $(shell find pipeline benchmark -name '*.py')
	if command -v cc >/dev/null 2>&1; then $(PY) -m tools.build_kernels; else \
		echo "no C compiler (cc): the kernels are not built ahead of time and run under numba's JIT"; fi

# Two models, about 12 minutes on 2 cores from a fresh clone: 7 epochs (560 steps) where the tiny preset,
# demo-all and the learning checks train 11 (880 steps); docs/BENCHMARKS.md has its time and breakdown.
demo: $(STAMP)
	$(call demo_pipeline,$(DEMO),hdmapnet lanegap,--thumbnails,--epochs 7)

# All four models under the same recipe, then the report with the paper's tables beside it (about 30 minutes).
demo-all: $(STAMP)
	$(call demo_pipeline,$(DEMO_ALL),hdmapnet lanegap maptr stsu,--reference paper --thumbnails)

# `make chromium`: Debian's headless browser and its driver for report.html's tests (tests/test_report_html.py,
# selenium pointed at /usr/bin/chromium and /usr/bin/chromedriver; never a browser download). Installed with
# apt-get where it exists and they are missing; elsewhere (or without root) nothing is installed, the build
# goes on and those tests skip with one line (in CI, where .ci/run sets LANEGRAPH_BROWSER_REQUIRED=1, they fail).
# The first try is quiet (it fails where apt's lists are empty); the try after apt-get update shows its errors.
chromium:
	@if [ -x /usr/bin/chromium ] && [ -x /usr/bin/chromedriver ]; then :; \
	elif command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
		(DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null 2>&1 \
		|| (apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null)) \
		|| echo "chromium: apt-get could not install chromium chromium-driver (its errors above): report.html's browser tests skip"; \
	else echo "chromium: no apt-get (or not root): report.html's browser tests skip"; fi

# The learning contract (tests/test_baselines_learning.py) runs alone, not in `make test`: five trainings
# of the tiny preset's 880 steps take 20-30 minutes on 2 cores. LANEGRAPH_LEARNING_SEED=2 for another seed.
test: $(STAMP) $(KERNELS) chromium
	LANEGRAPH_AOT_REQUIRED=$$(test -f $(KERNELS) && echo 1) $(PY) -m pytest -n 2 tests

test-learning: $(STAMP)
	LANEGRAPH_LEARNING_CHECK=1 $(PY) -m pytest -s tests/test_baselines_learning.py

# The installed package away from the checkout (CI, after the tests; ~2 minutes on 2 cores, most of it pip
# installing the lock): our wheel and the lock in a fresh venv, then cli --help, --version and synth ->
# prepare -> score -> report --reference paper on a tiny dataset, from a temporary folder
# (.ci/wheel_smoke.sh).
wheel-smoke: $(STAMP)
	PYTHON=$(PY) bash .ci/wheel_smoke.sh

# make wheelhouse: the wheels for an offline GPU machine (WHEEL_PYTHON, default 3.12: set it to that machine's
# Python), binary ones only: requirements.lock's pins of GPU_WHEELS, then the project's own wheel.
# GPU_WHEELS (set it for your machine): the lock's packages that a CUDA PyTorch image (python3 with torch,
# numpy, scipy, pyarrow, opencv, numba...) lacks and that the code imports; the rest of GPU_IMAGE_LACKS is
# declared by av2, nuscenes-devkit or typer, or serves tests, ray or lint, and is never imported by the
# commands. Leaving those out keeps the wheelhouse at 18 MiB, quick to copy along with the tree: av, polars
# and opencv-python alone are 148 MiB of cp312 wheels (the lock less torch: 555 MiB).
WHEELHOUSE := wheelhouse
WHEEL_PYTHON := 3.12
WHEEL_PLATFORMS := manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 \
	manylinux1_x86_64
GPU_WHEELS := av2 nuscenes-devkit shapely cachetools descartes pyquaternion universal_pathlib pathlib_abc
GPU_IMAGE_LACKS := $(GPU_WHEELS) annotated-types argcomplete av colorlog dependency-groups distlib fire \
	jsonschema jsonschema-specifications kornia kornia_rs nox opencv-python parameterized platformdirs polars \
	polars-runtime-32 pycocotools pydantic pydantic_core pyproj python-discovery ray referencing rpds-py ruff \
	termcolor typing-inspection tzdata virtualenv
DRYRUN := gpu_dryrun

# GPU acceptance: the four models under the gpu preset on one CUDA GPU, within 10 minutes: that each
# runs, learns and fits, with its step time, memory and samples/s (the paper's ranking needs the paper's
# schedule). tools/gpu_setup.sh runs bench_step, then gpu_check with every model the same epochs, the
# most that fit by its step times, all under a time limit that you set, LIMIT (default 540 s from the
# script's start: the 10 minutes less one, so that a hung or slow run stops by itself inside them; e.g.
# make gpu-check LIMIT=900 on a slower GPU), and copies each result into the folder you choose,
# GPU_CHECK_OUT (default gpu_check_out/), as its stage ends, so that a timeout keeps what finished.
# Where wheelhouse/ holds our wheel (a GPU machine with no package index: `make wheelhouse` here, copy
# wheelhouse/ there), nothing comes from an index: .venv-gpu is made over that machine's python3 and its
# CUDA torch, from the wheelhouse alone. Else it runs in .venv, set up from the index as for every target.
# gpu-smoke runs gpu_check on tiny data on any device; gpu-dryrun (CI, after the tests) downloads the GPU
# machine's wheelhouse, then runs the offline path on this machine's CPUs: a wheelhouse for this Python,
# .venv less the packages that such an image lacks as that image, then gpu_setup.sh --smoke (its limit
# 3600 s; its results in gpu_dryrun/out, the same files a GPU run leaves in gpu_check_out/).
ifneq ($(wildcard $(WHEELHOUSE)/lanegraph-*.whl),)
gpu-check:
	bash tools/gpu_setup.sh
else
gpu-check: $(STAMP)
	PYTHON=$(PY) bash tools/gpu_setup.sh --system
endif

gpu-smoke: $(STAMP)
	$(PY) -m tools.gpu_check --smoke --out gpu_smoke

gpu-dryrun: $(STAMP)
	rm -rf $(DRYRUN)
	$(MAKE) --no-print-directory wheelhouse WHEELHOUSE=$(DRYRUN)/wheelhouse-gpu  # its wheels exist
	$(MAKE) --no-print-directory wheelhouse WHEELHOUSE=$(DRYRUN)/wheelhouse \
		WHEEL_PYTHON=$$($(PY) -c 'import sys; print("%d.%d" % sys.version_info[:2])')
	PYTHON=$(PY) WHEELHOUSE=$(DRYRUN)/wheelhouse VENV=$(DRYRUN)/venv GPU_CHECK_OUT=$(DRYRUN)/out \
		HIDE="$(GPU_IMAGE_LACKS) lanegraph" bash tools/gpu_setup.sh --smoke

wheelhouse: $(STAMP)
	rm -rf $(WHEELHOUSE) build && mkdir -p $(WHEELHOUSE)
	for name in $(GPU_WHEELS); do grep -ix "$$name==[^ ]*" requirements.lock || exit 1; done \
		>$(WHEELHOUSE)/requirements.txt
	$(PY) -m pip download --quiet --no-deps --only-binary=:all: --implementation cp \
		--python-version $(WHEEL_PYTHON) $(addprefix --platform ,$(WHEEL_PLATFORMS)) \
		-r $(WHEELHOUSE)/requirements.txt -d $(WHEELHOUSE)
	$(PY) -m pip wheel --quiet --no-deps --no-build-isolation --wheel-dir $(WHEELHOUSE) .
	rm -rf build
	echo $(WHEEL_PYTHON) >$(WHEELHOUSE)/python-version
	du -sh $(WHEELHOUSE)

bench: $(STAMP) $(KERNELS) chromium
	$(PY) -m tools.bench_prepare
	$(PY) -m tools.bench_metrics
	$(PY) -m tools.bench_external
	$(PY) -m tools.bench_loader
	$(PY) -m tools.bench_splits
	$(PY) -m tools.bench_openlanev2
	$(PY) -m tools.bench_cgnet
	$(PY) -m tools.bench_startup
	$(PY) -m tools.bench_report_html

bench-train: $(STAMP)
	$(PY) -m tools.bench_train

# what a long run's safety costs, per model: a validation frame against a training frame, a checkpoint's
# stall (its copy to the host) against its hash and write (docs/EXPERIMENTS.md, 2026-12-06)
bench-long-run: $(STAMP)
	$(PY) -m tools.bench_long_run --preset tiny --models lanegap,hdmapnet,maptr,stsu --frames 16

# each model's training step time under the gpu preset on this machine's device (before make gpu-check),
# under cli train's settings (bf16 autocast, cuDNN benchmark, TF32 on CUDA)
bench-step: $(STAMP)
	$(PY) -m tools.bench_step --preset gpu

lint: $(STAMP)
	.venv/bin/ruff check .

clean:
	rm -rf .venv $(DEMO) $(DEMO_ALL) gpu_check gpu_smoke bench_step bench_long_run .venv-gpu gpu_check_out $(DRYRUN)
