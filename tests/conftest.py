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


# Test files that share the compiled programs above (expert_programs, contextual): one worker
# runs them all, so that each program compiles once.
SHARED_PROGRAMS = ("test_experts.py", "test_filtering.py", "test_sharding.py")


@pytest.hookimpl(optionalhook=True, tryfirst=True)
def pytest_xdist_make_scheduler(config, log):
    """With `-n N --dist loadfile`, every test file runs whole on one worker (its module-scoped
    compiled programs are built once), the files of SHARED_PROGRAMS together on one.

    A scheduler rather than xdist_group marks: `--dist loadgroup` (xdist 3.8) groups by a suffix
    it writes into the test ids, which pytest 9.2 no longer reads, so every marked test ran
    wherever a worker was free and each worker compiled the programs again."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class FileScheduling(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = super()._split_scope(nodeid)
            return "shared programs" if path.rsplit("/", 1)[-1] in SHARED_PROGRAMS else path

    return FileScheduling(config, log)
