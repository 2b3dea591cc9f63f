"""Shared fixtures: compiled environments are expensive on the CPU, so build them once."""

import jax
import pytest

from bumps_jax import kick_env


@pytest.fixture(scope="session")
def env():
    return kick_env.KickEnv()


def strong_types(tree):
    """`tree` with weakly typed leaves made strong. A fresh state from `reset` has one weakly
    typed field that `step` returns strongly typed: without this, stepping a stepped state would
    compile `step` a second time (~15 s on a CPU)."""
    return jax.tree.map(lambda x: x.astype(x.dtype), tree)


@pytest.fixture(scope="session")
def jit_env(env):
    """(reset, step) jitted once for the whole session; one compiled step serves every state."""
    reset = jax.jit(env.reset)
    return (lambda rng, target: strong_types(reset(rng, target))), jax.jit(env.step)
