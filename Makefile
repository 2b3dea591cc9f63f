# bumps_jax: every stage of the pipeline is a target. `make test` and `make demo` work from a
# fresh clone: they create .venv and install the package first.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install test lint demo render bench-scene clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

# pytest exits 5 when it collects nothing: that must fail, and it does (no `|| true`).
test: $(STAMP)
	$(PY) -m ruff check bumps_jax tests benchmarks experiments
	JAX_PLATFORMS=cpu $(PY) -m pytest -q tests

lint: $(STAMP)
	$(PY) -m ruff check bumps_jax tests benchmarks experiments
	$(PY) -m ruff format --check bumps_jax tests benchmarks experiments

# Until the later stages land, the demo is the scene showcase: a batch of noisy episodes.
demo: $(STAMP)
	JAX_PLATFORMS=cpu $(PY) -m bumps_jax showcase

render: $(STAMP)
	$(PY) -m bumps_jax render --out docs/stance.png

bench-scene: $(STAMP)
	$(PY) benchmarks/scene_bench.py --out benchmarks/results/scene.json

clean:
	rm -rf $(VENV) runs
