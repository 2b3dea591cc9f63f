"""The contextual tasks the pipeline runs (`task` in the config), and their envs by name.

    kick         the paper's: the NAO kicks a ball to a target distance (m); kick_env
    cheetah_vel  HalfCheetah-Vel: the half-cheetah runs at a target velocity (m/s); cheetah_env

Each env module has default_config, make_config, validate_config, resolved (its config as records
carry it), noise_free (overrides that switch its noise off) and its env class.
"""

from __future__ import annotations

import importlib

TASKS = ("kick", "cheetah_vel")
_MODULES = {"kick": "bumps_jax.tasks.kick.env", "cheetah_vel": "bumps_jax.tasks.cheetah_vel.env"}
_CLASSES = {"kick": "KickEnv", "cheetah_vel": "CheetahVelEnv"}
# The stages each task runs, in the pipeline's order: the keyframe prior and the held-out targets
# are the kick's (a closed-loop task's experts and baseline start from a fresh policy).
STAGES = {
    "kick": ("prior", "experts", "meta", "filter", "heldout", "baseline"),
    "cheetah_vel": ("experts", "meta", "filter", "baseline"),
}


def check_task(task: str) -> str:
    """`task`, or ValueError naming the tasks there are."""
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; choose one of {TASKS}")
    return task


def env_module(task: str):
    """The env module of `task` (kick_env or cheetah_env)."""
    return importlib.import_module(_MODULES[check_task(task)])


def make_env(task: str, env_cfg, overrides: dict | None = None):
    """The env of `task` built from its env config (and dotted `overrides`)."""
    return getattr(env_module(task), _CLASSES[task])(env_cfg, overrides)


def resolved(task: str, env_cfg) -> dict:
    """`task`'s env config as plain data, as records carry it (`<env module>.resolved`)."""
    return env_module(task).resolved(env_cfg)


def check_stage(task: str, stage: str) -> str:
    """`stage`, or ValueError if `task` has no such stage."""
    if stage not in STAGES[check_task(task)]:
        raise ValueError(f"the {task} task has no {stage} stage; its stages are {STAGES[task]}")
    return stage
