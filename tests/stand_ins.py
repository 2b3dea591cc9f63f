"""Stand-ins for the PPO experts and for a contextual policy, built from the committed kick prior.

Not learned policies: they let behaviour cloning and policy filtering be tested on a CPU
without training experts first.

- `synthetic_experts(tasks)`: one "expert" per task, the keyframe actions (T, 22) of the
  prior's blended kick family (short -> main -> long) at the strength calibrated for that task,
  played by phase (`rollout.table_policy`). Params stacked over experts: (E, T, 22); the same
  interface as the trained experts (`Family(apply_fn, params, tasks)`).
- `synthetic_contextual_params()` / `contextual_apply`: one policy for every context, the
  blended kick at a strength linear in the context.

The task -> strength map is the prior's sweep (`kick_model.calibration`), so these experts kick
roughly, not exactly, to their task. The prior is read when they are built, not at import.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax.algo import rollout
from bumps_jax.pipeline.stages.experts import Family
from bumps_jax.tasks.kick import keyframes as kick_model


def strength_for(targets, record: dict | None = None) -> np.ndarray:
    """The calibrated strength (...,) in [0, 1] for target distances (...,) m, from `record`'s
    sweep (default: the committed prior, read now)."""
    record = record or kick_model.load_record(kick_model.ASSET)
    s, d = np.asarray(kick_model.calibration(record), np.float64).T
    return np.interp(np.asarray(targets, np.float64), d, s)


def synthetic_experts(tasks, n_steps: int = 75, ctrl_dt: float = 0.02) -> Family:
    """Stand-in experts, one per task (E,): params (E, n_steps, 22), the blended kick's actions per task."""
    tasks = np.asarray(tasks, np.float64)
    record = kick_model.load_record(kick_model.ASSET)
    strengths = jnp.asarray(strength_for(tasks, record), jnp.float32)
    kicks = jax.vmap(kick_model.blend_params, in_axes=(None, 0))(jnp.asarray(record["anchors"]), strengths)
    return Family(rollout.table_policy, kick_model.action_tables(kicks, n_steps, ctrl_dt), tasks)


class ContextualParams(NamedTuple):
    """Params of the stand-in contextual policy (leaves may carry a leading stacking axis)."""

    anchors: jax.Array  # (3, 14) the short, main and long kicks
    slope: jax.Array  # () strength per normalised context unit
    offset: jax.Array  # () strength at normalised context 0


def synthetic_contextual_params(task_range=(7.0, 18.0)) -> ContextualParams:
    """The prior with strength linear in the context, through the calibration at the range ends."""
    record = kick_model.load_record(kick_model.ASSET)
    lo, hi = task_range
    s_lo, s_hi = strength_for([lo, hi], record)
    return ContextualParams(
        anchors=jnp.asarray(record["anchors"]),
        slope=jnp.float32(s_hi - s_lo),
        offset=jnp.float32(s_lo),
    )


def contextual_apply(params: ContextualParams, obs: jax.Array, n_steps: int = 75, ctrl_dt: float = 0.02):
    """Stand-in contextual policy: obs (2,) = (phase, normalised context) -> action (22,)."""
    kick = kick_model.blend_params(params.anchors, params.offset + params.slope * obs[1])
    return rollout.table_policy(kick_model.keyframes_to_actions(kick, n_steps, ctrl_dt), obs)
