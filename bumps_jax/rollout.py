"""The one episode scan of the project, and its batched, grid and sharded forms.

A policy is `apply_fn(params, obs) -> action (22,)`. Every episode is

    state = env.reset(key, target)
    repeat env.n_steps times: state = env.step(state, apply_fn(params, env.with_context(obs, context)))

so the policy sees `context` (m) while the env scores the kick against `target` (m): the same
for both when an expert kicks for its own task, different when filtering asks a meta-policy for
another distance. What it returns besides the final metrics is chosen by `record`:

    None          metrics
    "trajectory"  (metrics, (obs (T, obs_size), actions (T, 22)))  behaviour-cloning data
    "return"      (metrics, undiscounted return ())                 what PPO maximises
    "qpos"        (metrics, qpos (T, nq) after each control step)   rendering

Keyframe kicks run through the same scan as a table policy (`table_policy`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from bumps_jax import kick_env, sharding

RECORDS = (None, "trajectory", "return", "qpos")


def episode_fn(env: kick_env.KickEnv, apply_fn, record: str | None = None):
    """A pure fn (params, context, target, key) -> metrics (or (metrics, recorded), see above)."""
    if record not in RECORDS:
        raise ValueError(f"record must be one of {RECORDS}, got {record!r}")

    def episode(params, context, target, key):
        def body(carry, _):
            state, ret = carry
            obs = env.with_context(state.obs, context)
            action = apply_fn(params, obs)
            state = env.step(state, action)
            recorded = {"trajectory": (obs, action), "qpos": state.pipeline_state.qpos}.get(record)
            return (state, ret + state.reward), recorded

        (state, ret), recorded = jax.lax.scan(body, (env.reset(key, target), jnp.zeros(())), None, env.n_steps)
        if record is None:
            return state.metrics
        return state.metrics, (ret if record == "return" else recorded)

    return episode


def over_reps(episode):
    """(params, context, target, keys (R,)) -> outputs with a leading (R,) axis."""
    return jax.vmap(episode, in_axes=(None, None, None, 0))


def matched_fn(env: kick_env.KickEnv, apply_fn, record: str | None = None, mesh=None):
    """Jitted (params (N, ...), contexts (N,), targets (N,), keys (N, R)) -> outputs of (N, R, ...).

    Policy i on its own (context i, target i), R noisy repetitions: experts on their tasks,
    the kick prior's candidates, the meta-policy's dataset. With a `mesh` the N axis is split
    over its devices (N must then be a multiple of the mesh size: `sharding.pad`).
    """
    fn = jax.vmap(over_reps(episode_fn(env, apply_fn, record)), in_axes=(0, 0, 0, 0))
    if mesh is None:
        return jax.jit(fn)
    return sharding.over_batch(fn, mesh, (True, True, True, True))


def grid_fn(env: kick_env.KickEnv, apply_fn, mesh=None):
    """Jitted (params (P, ...), contexts (n,), targets (n,), keys (n, R)) -> metrics of (P, n, R).

    Every policy of a stack (seeds, networks of one architecture) on every (context, target)
    pair, R noisy repetitions each: one XLA program. With a `mesh` the pairs are split over
    its devices (n must then be a multiple of the mesh size; `filtering.run_blocked` pads).
    """
    over_pairs = jax.vmap(over_reps(episode_fn(env, apply_fn)), in_axes=(None, 0, 0, 0))
    over_policies = jax.vmap(over_pairs, in_axes=(0, None, None, None))
    if mesh is None:
        return jax.jit(over_policies)
    return sharding.over_batch(over_policies, mesh, (False, True, True, True), out_axis=1)


def repetition_keys(seed: int, n: int, n_reps: int) -> jax.Array:
    """(n, n_reps) independent episode keys."""
    return jax.random.split(jax.random.key(seed), n * n_reps).reshape(n, n_reps)


def table_policy(table: jax.Array, obs: jax.Array) -> jax.Array:
    """An open-loop policy: the row of `table` (T, 22) for the observation's phase obs[0] = step / T."""
    n_steps = table.shape[0]
    index = jnp.clip(jnp.round(obs[0] * n_steps).astype(jnp.int32), 0, n_steps - 1)
    return table[index]
