# Set-up is part of every target: a fresh clone needs only `make demo` or `make test`.
PY := .venv/bin/python
STAMP := .venv/.installed
DEMO := demo
DEMO_ALL := demo_all
DEMO_SYNTH :=
DEMO_TRAIN :=
CLI := .venv/bin/cli

.PHONY: demo demo-all test test-learning gpu-check gpu-smoke bench bench-train bench-step lint clean

$(STAMP): requirements.lock pyproject.toml
	test -x $(PY) || python3.11 -m venv .venv || python3 -m venv .venv
	$(PY) -m pip install --quiet -r requirements.lock
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $(STAMP)

# The demo's pipeline, one recipe for every model (tiny preset, fusion): $(1) the folder, $(2) the models,
# $(3) more `cli report` options. DEMO_SYNTH and DEMO_TRAIN add options to `cli synth` and to every
# `cli train`, e.g. a quick check of the steps: make demo-all DEMO_SYNTH="--logs 4" DEMO_TRAIN="--epochs 1"
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
		$(CLI) train --model $$model --data $(1)/prepared/av2 --out $(1)/runs/$${model}_fusion --preset tiny $(DEMO_TRAIN) \
		&& $(CLI) eval --run $(1)/runs/$${model}_fusion --data $(1)/prepared/av2 --split val || exit 1; \
	done
	$(CLI) report --runs $(1)/runs --roundtrip $(1)/roundtrip_path.json --roundtrip $(1)/roundtrip_piece.json --roundtrip $(1)/roundtrip_pixel.json --out $(1)/report $(3)
endef

# Two models, under 15 minutes on 2 cores.
demo: $(STAMP)
	$(call demo_pipeline,$(DEMO),hdmapnet lanegap,)

# All four models under the same recipe, then the report with the paper's tables beside it.
demo-all: $(STAMP)
	$(call demo_pipeline,$(DEMO_ALL),hdmapnet lanegap maptr stsu,--reference paper)

# The learning contract (tests/test_baselines_learning.py) runs alone, not in `make test`: five trainings
# of the tiny preset's 880 steps take 20-30 minutes on 2 cores. LANEGRAPH_LEARNING_SEED=2 for another seed.
test: $(STAMP)
	$(PY) -m pytest -n 2 tests

test-learning: $(STAMP)
	LANEGRAPH_LEARNING_CHECK=1 $(PY) -m pytest -s tests/test_baselines_learning.py

# GPU acceptance: the four models under the gpu preset on one CUDA GPU, within 10 minutes, against the
# paper's claims. gpu-smoke runs the same script on tiny data on any device (CI runs it after the tests).
gpu-check: $(STAMP)
	$(PY) -m baselines.gpu_check --out gpu_check

gpu-smoke: $(STAMP)
	$(PY) -m baselines.gpu_check --smoke --out gpu_smoke

bench: $(STAMP)
	$(PY) benchmark/bench_prepare.py
	$(PY) benchmark/bench_metrics.py
	$(PY) baselines/bench_loader.py

bench-train: $(STAMP)
	$(PY) baselines/bench_train.py

# each model's training step time under the gpu preset on this machine's device (before make gpu-check)
bench-step: $(STAMP)
	$(PY) -m baselines.bench_step --preset gpu

lint: $(STAMP)
	.venv/bin/ruff check .

clean:
	rm -rf .venv $(DEMO) $(DEMO_ALL) gpu_check gpu_smoke bench_step
