"""The episode programs' batching (rollout.py) on a stand-in env without physics: a call of more
episodes than the env's physics holds runs in equal chunks, with the outputs of one call."""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax.algo import rollout


class WalkState(NamedTuple):
    obs: jax.Array
    reward: jax.Array
    metrics: dict


class Walk:
    """A stand-in env: the position moves by each action plus noise from its reset key; the final
    error is the distance to the target. `max_episodes`: the most episodes one call may hold."""

    n_steps = 3

    def __init__(self, max_episodes):
        self.max_episodes = max_episodes

    def reset(self, key, target):
        start = jax.random.normal(key, ())
        return WalkState(start[None], jnp.zeros(()), {"final_error": jnp.abs(start - target), "target": target})

    def step(self, state, action):
        obs = state.obs + action
        return WalkState(obs, -obs[0], {**state.metrics, "final_error": jnp.abs(obs[0] - state.metrics["target"])})

    def with_context(self, obs, context):
        return jnp.concatenate([obs, jnp.atleast_1d(context)])


def gain_policy(params, obs):
    """Moves by params x context: (1,)."""
    return params * obs[1:]


def test_a_batch_beyond_the_pool_runs_in_equal_chunks_with_the_outputs_of_one_call():
    contexts, targets = jnp.arange(7.0), jnp.arange(7.0) + 0.5
    keys = rollout.repetition_keys(0, 7, 2)  # 7 items x 2 repetitions
    calls = []

    def counted(program):
        def run(params, contexts, targets, keys):
            calls.append(keys.shape)
            return program(params, contexts, targets, keys)

        return run

    # Matched: each item its own policy (the N axis is the chunked one).
    params = jnp.linspace(0.1, 0.7, 7)
    whole = rollout.matched_fn(Walk(None), gain_policy)(params, contexts, targets, keys)
    vmapped = jax.jit(jax.vmap(rollout.over_reps(rollout.episode_fn(Walk(6), gain_policy))))
    chunked = rollout.in_chunks(counted(vmapped), Walk(6), axis=0, per_item=1)(params, contexts, targets, keys)
    # A pool of 6 episodes holds 3 items of 2 repetitions: 7 items in 3 equal calls (the last padded).
    assert calls == [(3, 2)] * 3
    for name in whole:
        np.testing.assert_allclose(chunked[name], whole[name], rtol=1e-6)
        assert chunked[name].shape == (7, 2)
    # A grid of 2 policies: each item holds 2 x 2 episodes, so 8 episodes are 2 items a call.
    stack = jnp.array([0.5, -0.5])
    one_call = rollout.grid_fn(Walk(None), gain_policy)(stack, contexts, targets, keys)
    in_chunks = rollout.grid_fn(Walk(8), gain_policy)(stack, contexts, targets, keys)
    for name in one_call:
        np.testing.assert_allclose(in_chunks[name], one_call[name], rtol=1e-6)
        assert in_chunks[name].shape == (2, 7, 2)
    # A pool of at least the whole batch: one call.
    calls.clear()
    rollout.in_chunks(counted(vmapped), Walk(14), axis=0, per_item=1)(params, contexts, targets, keys)
    assert calls == [(7, 2)]
