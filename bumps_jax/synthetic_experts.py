"""SYNTHETIC stand-ins for the PPO experts and for contextual policies, built from the kick prior.

Not learned policies: they exist so that behaviour cloning and policy filtering can be tested
and demonstrated on a CPU before the real experts (`bumps_jax.experts`) are trained.

- `synthetic_experts(tasks)`: one "expert" per task = the keyframe actions (T, 22) of the
  prior's blended kick family (short -> 12 m -> long) at the strength calibrated for that task,
  looked up by the observation's phase. Params stacked over experts: (E, T, 22). Same
  interface as the PPO experts: `apply_fn(params, obs) -> (22,)`.
- `synthetic_contextual_params()` / `contextual_apply`: one policy for every context: the
  blended kick at a strength linear in the context.
The task -> strength map is the committed prior's GPU sweep (`prior.calibration`), so these
experts kick roughly, not exactly, to their task.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax import kick_env, prior

# (strength, mean resting distance m) along the committed prior's short -> 12 m -> long family,
# from its GPU sweep (assets/kick_prior.json): the experts kick roughly, not exactly, to their task.
CALIBRATION = tuple(map(tuple, prior.calibration(prior.load_prior()).tolist()))


class ExpertFamily(NamedTuple):
    """Deterministic policies stacked over experts: params leaves have a leading axis (E,)."""

    apply_fn: object  # (params of one expert, obs (2,)) -> action (22,)
    params: object  # pytree, leading axis E
    tasks: np.ndarray  # (E,) the target distance (m) each expert was made for


def strength_for(targets) -> np.ndarray:
    """The calibrated strength (..,) for target distances (..,) m, in [0, 1]."""
    s, d = np.asarray(CALIBRATION, np.float64).T
    return np.interp(np.asarray(targets, np.float64), d, s)


def lookup_action(table: jax.Array, obs: jax.Array) -> jax.Array:
    """The row of `table` (T, 22) for the observation's phase obs[0] = step / T."""
    n_steps = table.shape[0]
    index = jnp.clip(jnp.round(obs[0] * n_steps).astype(jnp.int32), 0, n_steps - 1)
    return table[index]


def synthetic_experts(tasks, n_steps: int = 75, ctrl_dt: float = 0.02) -> ExpertFamily:
    """SYNTHETIC experts, one per task: params (E, n_steps, 22), the blended kick's actions per task."""
    tasks = np.asarray(tasks, np.float64)
    anchors = jnp.asarray(prior.load_prior()["anchors"])
    kicks = jax.vmap(prior.blend_params, in_axes=(None, 0))(anchors, jnp.asarray(strength_for(tasks), jnp.float32))
    tables = jax.vmap(lambda p: prior.keyframes_to_actions(p, n_steps, ctrl_dt))(kicks)
    return ExpertFamily(lookup_action, tables, tasks)


class ContextualParams(NamedTuple):
    """Params of the synthetic contextual policy (leaves may carry a leading stacking axis)."""

    anchors: jax.Array  # (3, 14) the short, 12 m and long kicks
    slope: jax.Array  # () strength per normalised context unit
    offset: jax.Array  # () strength at normalised context 0


def synthetic_contextual_params(task_range=(7.0, 18.0)) -> ContextualParams:
    """The prior with strength linear in the context, through the calibration at the range ends."""
    lo, hi = task_range
    s_lo, s_hi = strength_for([lo, hi])
    return ContextualParams(
        anchors=jnp.asarray(prior.load_prior()["anchors"]),
        slope=jnp.float32(s_hi - s_lo),
        offset=jnp.float32(s_lo),
    )


def contextual_apply(params: ContextualParams, obs: jax.Array, n_steps: int = 75, ctrl_dt: float = 0.02):
    """SYNTHETIC contextual policy: obs (2,) = (phase, normalised context) -> action (22,)."""
    kick = prior.blend_params(params.anchors, params.offset + params.slope * obs[1])
    return lookup_action(prior.keyframes_to_actions(kick, n_steps, ctrl_dt), obs)


def default_tasks() -> np.ndarray:
    return np.asarray(kick_env.meta_train_tasks())
