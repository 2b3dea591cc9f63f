"""Shared fixtures: compiled environments are expensive on the CPU, so build them once."""

import jax
import pytest
import tiny_experts

from bumps_jax import config, evaluate, kick_env, synthetic_experts


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
    """(grid, params): every-pair rollouts of the synthetic contextual policy (a stack of one) on
    one device, jitted once for the filtering tests and the single-device side of the sharding
    test (each MJX program costs ~50 s to compile on a CPU)."""
    params = synthetic_experts.synthetic_contextual_params()
    return evaluate.grid_fn(env, synthetic_experts.contextual_apply), jax.tree.map(lambda a: a[None], params)


@pytest.fixture(scope="session")
def expert_programs(env):
    """The tiny experts' programs (tiny_experts.py), compiled on first use: test_experts.py
    trains with them and test_sharding.py's single-device side too."""
    from bumps_jax.stages import experts as experts_stage

    return experts_stage.compile_programs(tiny_experts.pipeline_config(), env)
