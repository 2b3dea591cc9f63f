"""SYNTHETIC stand-ins for the PPO experts and for contextual policies, built from the kick prior.

Not learned policies: they exist so that behaviour cloning and policy filtering can be tested
and demonstrated on a CPU before the real experts (`bumps_jax.experts`) are trained.

- `synthetic_experts(tasks)`: one "expert" per task = the prior's keyframe actions (T, 22) at a
  strength chosen for that task, looked up by the observation's phase. Params stacked over
  experts: (E, T, 22). Same interface as the PPO experts: `apply_fn(params, obs) -> (22,)`.
- `synthetic_contextual_policy()`: one policy for every context: the keyframe kick at the
  strength the context asks for. Its context -> distance map is the prior's strength sweep.

The task -> strength map is a rough calibration of the committed prior (a CPU strength sweep
in MJX, noisy, 8 repetitions): the experts kick roughly, not exactly, to their task.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax import kick_env, prior

# (strength, mean resting distance m) of the committed prior; see the module docstring.
# Below ~0.6 the swing mostly misses the ball; 7-18 m needs strengths of about 0.64-0.77.
CALIBRATION = (
    (0.6, 3.9),
    (0.7, 12.2),
    (0.8, 20.4),
    (0.9, 21.5),
    (1.0, 25.5),
)
_STRENGTH = prior.PARAM_NAMES.index("strength")


class ExpertFamily(NamedTuple):
    """Deterministic policies stacked over experts: params leaves have a leading axis (E,)."""

    apply_fn: object  # (params of one expert, obs (2,)) -> action (22,)
    params: object  # pytree, leading axis E
    tasks: np.ndarray  # (E,) the target distance (m) each expert was made for


def strength_for(targets) -> np.ndarray:
    """The calibrated strength (..,) for target distances (..,) m, clipped to [0.1, 1]."""
    s, d = np.asarray(CALIBRATION, np.float64).T
    return np.clip(np.interp(np.asarray(targets, np.float64), d, s), 0.1, 1.0)


def lookup_action(table: jax.Array, obs: jax.Array) -> jax.Array:
    """The row of `table` (T, 22) for the observation's phase obs[0] = step / T."""
    n_steps = table.shape[0]
    index = jnp.clip(jnp.round(obs[0] * n_steps).astype(jnp.int32), 0, n_steps - 1)
    return table[index]


def synthetic_experts(tasks, n_steps: int = 75, ctrl_dt: float = 0.02) -> ExpertFamily:
    """SYNTHETIC experts, one per task: params (E, n_steps, 22), the prior's actions per task."""
    tasks = np.asarray(tasks, np.float64)
    base = np.asarray(prior.load_prior()["params"], np.float32)
    batch = np.tile(base, (len(tasks), 1))
    batch[:, _STRENGTH] = strength_for(tasks)
    to_actions = jax.vmap(lambda p: prior.keyframes_to_actions(p, n_steps, ctrl_dt))
    tables = to_actions(prior.clip_params(jnp.asarray(batch)))
    return ExpertFamily(lookup_action, tables, tasks)


class ContextualParams(NamedTuple):
    """Params of the synthetic contextual policy (leaves may carry a leading stacking axis)."""

    kick: jax.Array  # (14,) prior params; strength is replaced per context
    slope: jax.Array  # () strength per normalised context unit
    offset: jax.Array  # () strength at normalised context 0


def synthetic_contextual_params(task_range=(7.0, 18.0)) -> ContextualParams:
    """The prior with strength linear in the context, through the calibration at the range ends."""
    lo, hi = task_range
    s_lo, s_hi = strength_for([lo, hi])
    return ContextualParams(
        kick=jnp.asarray(prior.load_prior()["params"], jnp.float32),
        slope=jnp.float32(s_hi - s_lo),
        offset=jnp.float32(s_lo),
    )


def contextual_apply(params: ContextualParams, obs: jax.Array, n_steps: int = 75, ctrl_dt: float = 0.02):
    """SYNTHETIC contextual policy: obs (2,) = (phase, normalised context) -> action (22,)."""
    strength = jnp.clip(params.offset + params.slope * obs[1], 0.1, 1.0)
    kick = prior.clip_params(params.kick.at[_STRENGTH].set(strength))
    return lookup_action(prior.keyframes_to_actions(kick, n_steps, ctrl_dt), obs)


def default_tasks() -> np.ndarray:
    return np.asarray(kick_env.meta_train_tasks())
