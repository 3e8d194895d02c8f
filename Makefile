# Set-up is part of every target: a fresh clone needs only `make demo` or `make test`.
PY := .venv/bin/python
STAMP := .venv/.installed
DEMO := demo

.PHONY: demo test bench lint clean

$(STAMP): requirements.lock pyproject.toml
	test -x $(PY) || python3.11 -m venv .venv || python3 -m venv .venv
	$(PY) -m pip install --quiet -r requirements.lock
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $(STAMP)

demo: $(STAMP)
	.venv/bin/cli synth --out $(DEMO)/raw
	.venv/bin/cli prepare --dataset av2 --root $(DEMO)/raw/av2/sensor --out $(DEMO)/prepared/av2
	.venv/bin/cli prepare --dataset nuscenes --root $(DEMO)/raw/nuscenes --version v1.0-mini --out $(DEMO)/prepared/nuscenes

test: $(STAMP)
	$(PY) -m pytest -n 2 tests

bench: $(STAMP)
	$(PY) benchmark/bench_prepare.py

lint: $(STAMP)
	.venv/bin/ruff check .

clean:
	rm -rf .venv $(DEMO)
