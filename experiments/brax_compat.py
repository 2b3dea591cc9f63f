"""Brax's own `ppo.train` on our kick env, with our PPO hyperparameters: the reference our trainer
is compared with (experiments/compare_brax_ppo.py) and timed against (benchmarks/bench.py).

Brax 0.14's `ppo.train` replicates its training state with `jax.device_put_replicated`, which
newer jax no longer has. `patched()` provides it for the duration of a call and restores jax as
it was afterwards; `train` runs Brax inside it:

    with brax_compat.patched():
        brax_ppo.train(...)
    # or
    make_policy, params, metrics = brax_compat.train(cfg.experts.ppo, env, num_timesteps=...)
"""

from __future__ import annotations

import contextlib

import jax
import jax.numpy as jnp
import ml_collections
from brax.training.agents.ppo import train as brax_ppo

from bumps_jax.algo import ppo
from bumps_jax.tasks.kick import env as kick_env

_NAME = "device_put_replicated"


def _device_put_replicated(x, devices):
    """x's leaves stacked once per device (leading axis len(devices)): what Brax's pmap expects."""
    return jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (len(devices), *jnp.shape(a))), x)


@contextlib.contextmanager
def patched():
    """Within the block `jax.device_put_replicated` exists (jax's own where it still has one);
    afterwards jax is as it was."""
    if hasattr(jax, _NAME):
        yield
        return
    setattr(jax, _NAME, _device_put_replicated)
    try:
        yield
    finally:
        delattr(jax, _NAME)


def network_factory(ppo_cfg: ml_collections.ConfigDict):
    """Brax's network-factory signature over our networks (`ppo.make_networks`: same policy and value nets)."""

    def factory(obs_size, action_size, preprocess_observations_fn):
        del preprocess_observations_fn  # ours is fixed by ppo_cfg.normalize_observations
        return ppo.make_networks(ppo_cfg, obs_size, action_size)

    return factory


def train_kwargs(ppo_cfg: ml_collections.ConfigDict, env: kick_env.KickEnv) -> dict:
    """Our PPO section as keyword arguments of Brax's `ppo.train` (budget, seed and logging aside).

    One rollout is one whole episode per env, and a minibatch holds whole episodes, as ours.
    Brax has one learning rate for both networks: our policy's (`learning_rate`).
    """
    p = ppo_cfg
    return {
        "environment": env,
        "num_envs": int(p.num_envs),
        "episode_length": env.n_steps,
        "unroll_length": env.n_steps,
        "batch_size": int(p.num_envs // p.num_minibatches),
        "num_minibatches": int(p.num_minibatches),
        "num_updates_per_batch": int(p.num_epochs),
        "learning_rate": float(p.learning_rate),
        "entropy_cost": float(p.entropy_cost),
        "discounting": float(p.discount),
        "gae_lambda": float(p.gae_lambda),
        "clipping_epsilon": float(p.clip_epsilon),
        "reward_scaling": float(p.reward_scaling),
        "max_grad_norm": float(p.max_grad_norm),
        "vf_loss_coefficient": float(p.vf_coefficient),
        "normalize_observations": bool(p.normalize_observations),
        "network_factory": network_factory(p),
    }


def train(ppo_cfg: ml_collections.ConfigDict, env: kick_env.KickEnv, **kwargs):
    """Brax's `ppo.train` with `train_kwargs(ppo_cfg, env)` and `kwargs` (num_timesteps, seed,
    restore_params, progress_fn, ...; they win over ours), inside `patched()`.

    Returns what Brax returns: (make_policy, (normalizer, policy, value) params, metrics). Brax
    resets its envs through `env.reset(rng)`, which draws each episode's target from env.config.tasks.
    """
    with patched():
        return brax_ppo.train(**{**train_kwargs(ppo_cfg, env), **kwargs})
