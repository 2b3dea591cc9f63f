"""The one episode scan of the project, and its batched, grid and sharded forms.

A policy is `apply_fn(params, obs) -> action (A,)`. Every episode is

    state = env.reset(key, target)
    repeat env.n_steps times: state = env.step(state, apply_fn(params, env.with_context(obs, context)))

so the policy sees `context` while the env scores the episode against `target`: the same for
both when an expert acts for its own task, different when filtering asks a meta-policy for
another context. What it returns besides the final metrics is chosen by `record`:

    None          metrics
    "trajectory"  (metrics, (obs (T, obs_size), actions (T, A)))   behaviour-cloning data
    "return"      (metrics, undiscounted return ())                 what PPO maximises
    "qpos"        (metrics, qpos (T, nq) after each control step)   rendering

A scripted motion (a task's open-loop actions) runs through the same scan as a table policy
(`table_policy`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax.algo import sharding
from bumps_jax.envs.base import ContextualEnv

RECORDS = (None, "trajectory", "return", "qpos")


def episode_fn(env: ContextualEnv, apply_fn, record: str | None = None, action_noise: float = 0.0):
    """A pure fn (params, context, target, key) -> metrics (or (metrics, recorded), see above).
    action_noise: the env steps with the policy's action plus Gaussian noise of this std (its
    own draws from the episode's key), while "trajectory" records the policy's action (DART)."""
    if record not in RECORDS:
        raise ValueError(f"record must be one of {RECORDS}, got {record!r}")

    def episode(params, context, target, key):
        noise_key = jax.random.fold_in(key, 1)

        def body(carry, t):
            state, ret = carry
            obs = env.with_context(state.obs, context)
            action = apply_fn(params, obs)
            executed = action
            if action_noise:
                executed = action + action_noise * jax.random.normal(jax.random.fold_in(noise_key, t), action.shape)
            state = env.step(state, executed)
            recorded = (obs, action) if record == "trajectory" else None
            if record == "qpos":
                recorded = state.pipeline_state.qpos
            return (state, ret + state.reward), recorded

        steps = jnp.arange(env.n_steps)
        (state, ret), recorded = jax.lax.scan(body, (env.reset(key, target), jnp.zeros(())), steps)
        if record is None:
            return state.metrics
        return state.metrics, (ret if record == "return" else recorded)

    return episode


def over_reps(episode):
    """(params, context, target, keys (R,)) -> outputs with a leading (R,) axis."""
    return jax.vmap(episode, in_axes=(None, None, None, 0))


def in_chunks(program, env: ContextualEnv, axis: int, per_item: int, n_devices: int = 1):
    """`program(params, contexts (n,), targets (n,), keys (n, R))` run over chunks of the n axis
    so that no call holds more episodes per device than the env's physics can (Warp's contact
    pool: `env.max_episodes`); outputs joined along `axis`. Every chunk has the same size (the
    last padded by repeating its first item), so one compiled program serves them all.
    per_item: episodes per item of the n axis besides the repetitions (policies P of a grid)."""
    if env.max_episodes is None:
        return program

    def run(params, contexts, targets, keys):
        n, reps = keys.shape[:2]
        # At least one item per device: an item larger than the pool overflows, which marks its
        # episodes invalid (the physics' own report), rather than refusing here.
        per_call = max(env.max_episodes // (per_item * reps), 1) * n_devices
        per_call = -(-n // -(-n // per_call))  # equal chunks, as few as fit
        per_call = -(-per_call // n_devices) * n_devices
        if per_call >= n:
            return program(params, contexts, targets, keys)
        outs = []
        for start in range(0, n, per_call):
            idx = np.arange(start, start + per_call)
            idx = np.where(idx < n, idx, start)
            chunk_params = jax.tree.map(lambda a, i=idx: a[i], params) if axis == 0 else params
            out = program(chunk_params, contexts[idx], targets[idx], keys[idx])
            kept = min(per_call, n - start)
            outs.append(jax.tree.map(lambda a, k=kept: jax.lax.slice_in_dim(a, 0, k, axis=axis), out))
        return jax.tree.map(lambda *parts: jnp.concatenate(parts, axis=axis), *outs)

    return run


def matched_fn(env: ContextualEnv, apply_fn, record: str | None = None, mesh=None, action_noise: float = 0.0):
    """(params (N, ...), contexts (N,), targets (N,), keys (N, R)) -> outputs of (N, R, ...), jitted.

    Policy i on its own (context i, target i), R noisy repetitions: experts on their tasks,
    the kick prior's candidates, the meta-policy's dataset. With a `mesh` the N axis is split
    over its devices and the processes (N must then be a multiple of `sharding.ways(mesh)`:
    `sharding.pad`). A batch larger than the physics holds runs in chunks (`in_chunks`).
    action_noise: see `episode_fn`.
    """
    fn = jax.vmap(over_reps(episode_fn(env, apply_fn, record, action_noise)), in_axes=(0, 0, 0, 0))
    if mesh is None:
        return in_chunks(jax.jit(fn), env, axis=0, per_item=1)
    return in_chunks(sharding.over_batch(fn, mesh, (True, True, True, True)), env, 0, 1, sharding.ways(mesh))


def grid_fn(env: ContextualEnv, apply_fn, mesh=None):
    """Jitted (params (P, ...), contexts (n,), targets (n,), keys (n, R)) -> metrics of (P, n, R).

    Every policy of a stack (seeds, networks of one architecture) on every (context, target)
    pair, R noisy repetitions each: one XLA program. With a `mesh` the pairs are split over
    its devices and the processes (padded to a multiple of `sharding.ways(mesh)` and the copies
    dropped).
    """
    over_pairs = jax.vmap(over_reps(episode_fn(env, apply_fn)), in_axes=(None, 0, 0, 0))
    over_policies = jax.vmap(over_pairs, in_axes=(0, None, None, None))
    program = (
        jax.jit(over_policies)
        if mesh is None
        else sharding.over_batch(over_policies, mesh, (False, True, True, True), out_axis=1)
    )

    def run(params, contexts, targets, keys):
        n_policies, n = jax.tree.leaves(params)[0].shape[0], len(keys)
        ways = 1 if mesh is None else sharding.ways(mesh)
        chunked = in_chunks(program, env, axis=1, per_item=n_policies, n_devices=ways)
        pairs = sharding.pad((jnp.asarray(contexts), jnp.asarray(targets), keys), -(-n // ways) * ways)
        return jax.tree.map(lambda a: a[:, :n], chunked(params, *pairs))

    return run


def repetition_keys(seed: int, n: int, n_reps: int) -> jax.Array:
    """(n, n_reps) independent episode keys."""
    return jax.random.split(jax.random.key(seed), n * n_reps).reshape(n, n_reps)


def table_policy(table: jax.Array, obs: jax.Array) -> jax.Array:
    """An open-loop policy: the row of `table` (T, 22) for the observation's phase obs[0] = step / T."""
    n_steps = table.shape[0]
    index = jnp.clip(jnp.round(obs[0] * n_steps).astype(jnp.int32), 0, n_steps - 1)
    return table[index]
