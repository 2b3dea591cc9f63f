"""Shared fixtures: compiled environments are expensive on the CPU, so build them once."""

import os
import subprocess
import sys
from pathlib import Path

import jax
import pytest

from bumps_jax import kick_env

ROOT = Path(__file__).resolve().parents[1]
SHARDED = pytest.StashKey[subprocess.Popen]()


def pytest_collection_modifyitems(session, config, items):
    """Start the 4-device sharding check (tests/sharded_run.py, its own process: XLA reads the
    device count at start-up) as soon as it is selected, so that it compiles on the second core
    while the rest of the suite runs; test_sharding.py collects its output."""
    if any(item.path.name == "test_sharding.py" for item in items):
        env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
        env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
        config.stash[SHARDED] = subprocess.Popen(
            [sys.executable, str(ROOT / "tests" / "sharded_run.py")],
            env=env,
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )


def pytest_unconfigure(config):
    proc = config.stash.get(SHARDED, None)
    if proc is not None and proc.poll() is None:
        proc.kill()


@pytest.fixture(scope="session")
def env():
    return kick_env.KickEnv()


@pytest.fixture(scope="session")
def jit_env(env):
    """(reset, step) jitted once for the whole session."""
    return jax.jit(env.reset), jax.jit(env.step)
