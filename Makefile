# bumps_jax: every stage of the pipeline is a target. `make test` and `make demo` work from a
# fresh clone: they create .venv and install the package first.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# tiny: CPU-sized, minutes; paper: the paper's budgets, for a GPU.
PRESET ?= tiny

.PHONY: install test lint demo render bench-scene kick-prior train-experts bench-training meta-train filter clean

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

# The paper preset also publishes: assets/kick_prior.json, results/, benchmarks/results/, docs/.
kick-prior: $(STAMP)
	$(PY) -m bumps_jax kick-prior --preset $(PRESET) --run-dir runs/$(PRESET)/prior $(if $(filter paper,$(PRESET)),--publish,)

render: $(STAMP)
	$(PY) -m bumps_jax render --out docs/stance.png

bench-scene: $(STAMP)
	$(PY) benchmarks/scene_bench.py --out benchmarks/results/scene.json

# Single-task experts: BC of the kick prior, then PPO, all tasks in one vmapped program.
# PRESET=tiny runs on a CPU in minutes under runs/experts/tiny; PRESET=paper is the GPU run
# (23 tasks, 12M env steps each). A killed run resumes from its last checkpoint.
train-experts: $(STAMP)
	$(PY) -m bumps_jax.experts --preset $(PRESET) --run-dir runs/experts/$(PRESET)

bench-training: $(STAMP)
	$(PY) benchmarks/training_bench.py --preset $(PRESET) --out runs/bench/training_$(PRESET).json

# Meta-training (behaviour cloning of the experts) and policy filtering. PRESET=tiny runs on a
# CPU in minutes with synthetic prior-based experts; PRESET=paper is the GPU run
# (EXPERTS=module:function EXPERTS_PATH=... EXPERTS_JSON=... select the trained PPO experts).
EXPERTS ?= synthetic
META_ARGS = --preset $(PRESET) --out runs/meta/$(PRESET) --experts $(EXPERTS) \
	$(if $(EXPERTS_PATH),--experts-path $(EXPERTS_PATH)) $(if $(EXPERTS_JSON),--experts-json $(EXPERTS_JSON))
meta-train: $(STAMP)
	$(PY) -m bumps_jax.meta $(META_ARGS)

filter: $(STAMP)
	$(PY) -m bumps_jax.filtering --preset $(PRESET) --meta runs/meta/$(PRESET) --out runs/filter/$(PRESET)

clean:
	rm -rf $(VENV) runs
