"""The compiled episode programs of meta-policies, shared by every stage that rolls them out.

`meta_grid` builds the `rollout.grid_fn` program of one architecture in one env once per process:
the filter stage, the held-out evaluation and the shipped policies reuse
it (each MJX program costs tens of seconds to compile on a CPU).
"""

from __future__ import annotations

import json

from bumps_jax.algo import bc, rollout
from bumps_jax.envs import base
from bumps_jax.tasks import registry as tasks

# The processes' caches: (task, env config[, architecture, devices]) -> env / compiled program.
_PROGRAMS: dict = {}
_ENVS: dict = {}


def stage_env(env_cfg, task: str):
    """The env of `task` built from `env_cfg`, once per process and env config, and checked to
    step as the pipeline reads it (`base.check_episode`) when first built."""
    key = (task, json.dumps(tasks.resolved(task, env_cfg), sort_keys=True))
    if key not in _ENVS:
        env = tasks.make_env(task, env_cfg)
        base.check_episode(env)
        _ENVS[key] = env
    return _ENVS[key]


def meta_grid(env_cfg, depth: int, width: int, mesh, task: str, obs_norm=None):
    """The `rollout.grid_fn` program of a (depth, width) meta-policy (observations normalised by
    `obs_norm`, `bc.MetaPolicy`) in `task`'s env of `env_cfg`, once per process, env config,
    architecture and device mesh. Its apply_fn is bc.policy_apply."""
    key = (
        task,
        json.dumps(tasks.resolved(task, env_cfg), sort_keys=True),
        int(depth),
        int(width),
        tuple(d.id for d in mesh.devices.flat),
        obs_norm,
    )
    if key not in _PROGRAMS:
        env = stage_env(env_cfg, task)
        apply_fn = bc.policy_apply(bc.MetaPolicy(int(depth), int(width), env.action_size, obs_norm))
        _PROGRAMS[key] = rollout.grid_fn(env, apply_fn, mesh)
    return _PROGRAMS[key]
