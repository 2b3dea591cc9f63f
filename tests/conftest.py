"""Shared fixtures: compiled environments are expensive on the CPU, so build them once."""

import jax
import pytest

from bumps_jax import kick_env


@pytest.fixture(scope="session")
def env():
    return kick_env.KickEnv()


@pytest.fixture(scope="session")
def jit_env(env):
    """(reset, step) jitted once for the whole session."""
    return jax.jit(env.reset), jax.jit(env.step)
