"""The Brax shim (bumps_jax/brax_compat.py): jax is patched only inside the block, and our PPO
section maps onto Brax's arguments."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bumps_jax import config
from bumps_jax.tasks.kick import env as kick_env
from experiments import brax_compat


def test_patched_provides_device_put_replicated_and_restores_jax():
    had = hasattr(jax, "device_put_replicated")
    before = getattr(jax, "device_put_replicated", None)
    with brax_compat.patched():
        tree = {"a": jnp.arange(3.0), "b": jnp.ones(())}
        out = jax.device_put_replicated(tree, jax.local_devices()[:1])
        assert out["a"].shape == (1, 3) and out["b"].shape == (1,)
        np.testing.assert_array_equal(out["a"][0], tree["a"])
    assert hasattr(jax, "device_put_replicated") == had
    assert getattr(jax, "device_put_replicated", None) is before


def test_patched_restores_jax_when_the_block_raises():
    had = hasattr(jax, "device_put_replicated")
    with pytest.raises(RuntimeError), brax_compat.patched():
        raise RuntimeError("inside")
    assert hasattr(jax, "device_put_replicated") == had


def test_train_kwargs_follow_our_ppo_section():
    cfg = config.make_config("tiny")
    env = kick_env.KickEnv(cfg.env)
    p = cfg.experts.ppo
    kw = brax_compat.train_kwargs(p, env)
    assert kw["environment"] is env
    assert kw["episode_length"] == kw["unroll_length"] == env.n_steps
    assert kw["num_envs"] == p.num_envs and kw["num_minibatches"] == p.num_minibatches
    assert kw["batch_size"] * kw["num_minibatches"] == p.num_envs
    assert kw["learning_rate"] == p.learning_rate and kw["clipping_epsilon"] == p.clip_epsilon
    networks = kw["network_factory"](env.observation_size, env.action_size, None)
    assert networks.policy_network is not None
