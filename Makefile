# Set-up is part of every target: a fresh clone needs only `make demo` or `make test`.
PY := .venv/bin/python
STAMP := .venv/.installed
DEMO := demo

.PHONY: demo test test-learning gpu-check gpu-smoke bench bench-train lint clean

$(STAMP): requirements.lock pyproject.toml
	test -x $(PY) || python3.11 -m venv .venv || python3 -m venv .venv
	$(PY) -m pip install --quiet -r requirements.lock
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $(STAMP)

demo: $(STAMP)
	rm -rf $(DEMO)
	.venv/bin/cli synth --out $(DEMO)/raw
	.venv/bin/cli prepare --dataset av2 --root $(DEMO)/raw/av2/sensor --out $(DEMO)/prepared/av2
	.venv/bin/cli prepare --dataset nuscenes --root $(DEMO)/raw/nuscenes --version v1.0-mini --out $(DEMO)/prepared/nuscenes
	.venv/bin/cli roundtrip --data $(DEMO)/prepared/av2 --via path --out $(DEMO)/roundtrip_path.json
	.venv/bin/cli roundtrip --data $(DEMO)/prepared/av2 --via piece --out $(DEMO)/roundtrip_piece.json
	.venv/bin/cli roundtrip --data $(DEMO)/prepared/av2 --via pixel --out $(DEMO)/roundtrip_pixel.json
	.venv/bin/cli train --model hdmapnet --data $(DEMO)/prepared/av2 --out $(DEMO)/runs/hdmapnet_fusion --preset tiny
	.venv/bin/cli eval --run $(DEMO)/runs/hdmapnet_fusion --data $(DEMO)/prepared/av2 --split val
	.venv/bin/cli train --model lanegap --data $(DEMO)/prepared/av2 --out $(DEMO)/runs/lanegap_fusion --preset tiny
	.venv/bin/cli eval --run $(DEMO)/runs/lanegap_fusion --data $(DEMO)/prepared/av2 --split val
	.venv/bin/cli report --runs $(DEMO)/runs --roundtrip $(DEMO)/roundtrip_path.json --roundtrip $(DEMO)/roundtrip_piece.json --roundtrip $(DEMO)/roundtrip_pixel.json --out $(DEMO)/report

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
	$(PY) benchmark/bench_loader.py

bench-train: $(STAMP)
	$(PY) baselines/bench_train.py

lint: $(STAMP)
	.venv/bin/ruff check .

clean:
	rm -rf .venv $(DEMO) gpu_check gpu_smoke
