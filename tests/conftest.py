"""Shared fixtures: compiled environments are expensive on the CPU, so build them once."""

import jax
import pytest
import stand_ins
import tiny_experts

from bumps_jax import config, kick_env, rollout


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
    one device, jitted once for the filtering tests and the single-device side of the sharding
    test (each MJX program costs ~50 s to compile on a CPU)."""
    params = stand_ins.synthetic_contextual_params(tuple(env.config.task_range))
    return rollout.grid_fn(env, stand_ins.contextual_apply), jax.tree.map(lambda a: a[None], params)


@pytest.fixture(scope="session")
def expert_programs(env):
    """The tiny experts' programs (tiny_experts.py), compiled on first use: test_experts.py
    trains with them and test_sharding.py's single-device side too."""
    from bumps_jax.stages import experts as experts_stage

    return experts_stage.compile_programs(tiny_experts.pipeline_config(), env)


def pytest_collection_modifyitems(config, items):
    """With `-n 2 --dist loadgroup`, every test file runs whole on one worker (its module-scoped
    compiled programs are built once); files that share conftest's programs name one group."""
    for item in items:
        if not item.get_closest_marker("xdist_group"):
            item.add_marker(pytest.mark.xdist_group(item.module.__name__))
