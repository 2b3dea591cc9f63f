"""Shared fixtures: compiled environments are expensive on the CPU, so build them once."""

import os
from pathlib import Path

# The tests' programs compile with LLVM's cheap pipeline and XLA's loop emitters: on a CPU
# compiling is about 40 % of the suite's time, and what their runs cost is Warp's physics (its own
# kernels, not XLA's code) or nets too small for the codegen to matter (test_bc_trainer.py:
# 84 s -> 33 s; an expert's first PPO update: compiles 20 s -> 9 s, its run time unchanged).
# Set before JAX starts its backend; a user's XLA_FLAGS come after these and win. Processes the
# tests start inherit them (tests/sharded_run.py's device count is added to them).
TEST_XLA_FLAGS = (
    "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true --xla_cpu_use_fusion_emitters=false"
)
os.environ["XLA_FLAGS"] = f"{TEST_XLA_FLAGS} {os.environ.get('XLA_FLAGS', '')}".strip()

import jax  # noqa: E402
import pytest  # noqa: E402
import stand_ins  # noqa: E402
import tiny_experts  # noqa: E402

from bumps_jax import config  # noqa: E402
from bumps_jax.algo import rollout  # noqa: E402
from bumps_jax.tasks.kick import env as kick_env  # noqa: E402


def _run_entries() -> set[Path]:
    """What the working directory's runs/ holds two levels deep (a run and its .lock)."""
    runs = Path("runs")
    return {*runs.glob("*"), *runs.glob("*/.*")} if runs.is_dir() else set()


@pytest.fixture(autouse=True)
def _leaves_no_run_behind():
    """A test writes no run into the working directory: a command's default run directory
    (runs/demo, runs/paper) belongs under tmp_path (`monkeypatch.chdir(tmp_path)`)."""
    before = _run_entries()
    yield
    left = sorted(str(p) for p in _run_entries() - before)
    if left:
        pytest.fail(f"left {', '.join(left)} in the working directory (this test, or one running beside it)")


@pytest.fixture(scope="session")
def env():
    """The tiny pipeline config's env (the scene's defaults)."""
    return kick_env.KickEnv(config.make_config("tiny").env)


@pytest.fixture(scope="session")
def jit_env(env):
    """(reset, step) jitted once for the whole session; one compiled step serves every state."""
    return jax.jit(env.reset), jax.jit(env.step)


@pytest.fixture(scope="session")
def contextual(env):
    """(grid, params): every-pair rollouts of the stand-in contextual policy (a stack of one) on
    one device, jitted once for the filtering tests (each batch shape compiles once)."""
    params = stand_ins.synthetic_contextual_params(tuple(env.config.task_range))
    return rollout.grid_fn(env, stand_ins.contextual_apply), jax.tree.map(lambda a: a[None], params)


@pytest.fixture(scope="session")
def expert_programs(env):
    """The tiny experts' programs (tiny_experts.py), compiled on first use: test_experts.py
    trains with them."""
    from bumps_jax.pipeline import expert_programs  # noqa: PLC0415

    return expert_programs.compile_programs(tiny_experts.pipeline_config(), env)


# The slowest test files (on a 2-core CPU), slowest first. `make test` runs each file whole on
# one of two workers (`--dist loadfile`, its module-scoped programs built once) in collection
# order (`--no-loadscope-reorder`): these start first, so that no long file is left running alone
# at the end. The other files follow in their usual order.
SLOWEST_FIRST = (
    "test_meta.py",
    "test_experts.py",
    "test_ant_goal.py",
    "test_baseline.py",
    "test_engines.py",
    "test_cheetah_pipeline.py",
    "test_cmaes.py",
    "test_sharding.py",
    "test_point_goal.py",
    "test_ppo.py",
    "test_compare_brax_ppo.py",
    "test_filtering.py",
    "test_bc_trainer.py",
    "test_kick_env.py",
    "test_cheetah_env.py",
)


def pytest_collection_modifyitems(items):
    """Collect the files of SLOWEST_FIRST first, in its order (each file's tests stay together)."""
    rank = {name: i for i, name in enumerate(SLOWEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
