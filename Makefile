# bumps_jax: every stage of the pipeline is a target. `make test` and `make demo` work from a
# fresh clone: they create .venv and install the package first.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# tiny: CPU-sized, minutes; paper: the paper's budgets, for a GPU.
PRESET ?= tiny

.PHONY: install test lint demo reproduce report baseline render video publish bench-scene kick-prior train-experts bench bench-scaling meta-train filter clean

# --no-compile: modules are byte-compiled when first imported, not every installed one up front.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q --no-compile -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

# pytest exits 5 when it collects nothing: that must fail, and it does (no `|| true`).
# Two workers (one core each); every test file runs whole on one worker, the slowest files first
# (tests/conftest.py: SLOWEST_FIRST).
test: lint
	JAX_PLATFORMS=cpu $(PY) -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder tests

lint: $(STAMP)
	$(PY) -m ruff check bumps_jax tests benchmarks experiments
	$(PY) -m ruff format --check bumps_jax tests benchmarks experiments

# The whole pipeline at CPU size (prior from assets/, 3 experts, short BC, a few test tasks),
# ending with runs/demo/report.md.
demo: $(STAMP)
	JAX_PLATFORMS=cpu $(PY) -m bumps_jax demo

# The paper preset end to end on a GPU: runs/paper/report.md; finished stages are skipped. A run
# of the preset as it is then publishes itself (see `publish`); a run with overrides does not.
# Overrides are dotted keys of the config tree: make reproduce SET="experts.ppo.total_env_steps=2880000"
# TASK=cheetah_vel runs HalfCheetah-Vel instead of the kick (runs/cheetah_vel/paper, results/cheetah_vel/).
reproduce: $(STAMP)
	$(PY) -m bumps_jax reproduce --preset paper $(if $(TASK),--task $(TASK),) $(if $(SET),--set $(SET),)
	$(if $(SET),@echo "not published: a run with overrides (SET) is an experiment",$(PY) -m bumps_jax publish $(if $(TASK),--task $(TASK) --run-dir runs/$(TASK)/paper,--run-dir runs/paper))

# Copy a finished paper run's results and figures into results/ and docs/ (docs/results.md), its prior into assets/.
publish: $(STAMP)
	$(PY) -m bumps_jax publish --run-dir runs/paper

report: $(STAMP)
	$(PY) -m bumps_jax report --preset $(PRESET)

# Stages write only into runs/$(PRESET)/<stage>/; `make publish` copies a paper run into the repository.
kick-prior: $(STAMP)
	$(PY) -m bumps_jax kick-prior --preset $(PRESET)

# Offscreen rendering: the command picks EGL (else OSMesa) unless MUJOCO_GL names a backend.
render: $(STAMP)
	$(PY) -m bumps_jax render --out docs/stance.png

# A GIF of filtered kicks at three distances from a finished run (runs/$(PRESET)/filtered_kicks.gif).
video: $(STAMP)
	$(PY) -m bumps_jax video --preset $(PRESET)

bench-scene: $(STAMP)
	$(PY) benchmarks/scene_bench.py --out benchmarks/results/scene.json

# Single-task experts: BC of the kick prior, then PPO, all tasks in one vmapped program.
# A killed run resumes from its last checkpoint. Outputs go to runs/$(PRESET)/<stage>/.
train-experts: $(STAMP)
	$(PY) -m bumps_jax train-experts --preset $(PRESET)

# Every speed side by side on this device: physics, env, experts vs Brax PPO, BC, filtering.
# PRESET=paper (a GPU) writes benchmarks/results/training.json; the tiny preset is a CPU smoke
# test in runs/bench.
bench: $(STAMP)
	$(PY) -m benchmarks.bench --preset $(PRESET) $(if $(filter paper,$(PRESET)),,--out-dir runs/bench)

# The same work on one GPU and on DEVICES of them, one process per GPU (Warp's way):
# benchmarks/results/scaling.json with PRESET=paper; the tiny preset runs on the CPU into runs/bench.
DEVICES ?= 2
bench-scaling: $(STAMP)
	$(PY) -m benchmarks.scaling --preset $(PRESET) --devices $(DEVICES) $(if $(filter paper,$(PRESET)),,--out-dir runs/bench)

# Behaviour cloning of the experts (runs/$(PRESET)/experts) into the two meta-policies.
meta-train: $(STAMP)
	$(PY) -m bumps_jax meta-train --preset $(PRESET)

filter: $(STAMP)
	$(PY) -m bumps_jax filter --preset $(PRESET)

# The paper's Figure 1: plain multi-task PPO (one contextual policy, targets U[7, 18] m).
baseline: $(STAMP)
	$(PY) -m bumps_jax baseline --preset $(PRESET)

clean:
	rm -rf $(VENV) runs
