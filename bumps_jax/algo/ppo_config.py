"""The PPO section of the config: its defaults, validation and the run length it implies.

`bumps_jax.algo.ppo.make_train` takes such a section; `bumps_jax.config` nests one under
`experts.ppo` and `baseline.ppo`.
"""

from __future__ import annotations

import ml_collections
import numpy as np

from bumps_jax.envs.base import locked_config


def default_config() -> ml_collections.ConfigDict:
    """PPO hyperparameters; the paper's value beside each (docs/decisions.md says where ours differ)."""
    cfg = ml_collections.ConfigDict()
    cfg.num_envs = 16  # episodes per update; paper: 4096 steps per batch (~55 episodes of 75)
    cfg.num_minibatches = 4  # whole episodes per minibatch = num_envs / this; paper: 1024 steps
    cfg.num_epochs = 4  # paper: 30
    cfg.total_env_steps = 12_000  # per expert; paper: 12M
    cfg.learning_rate = 3e-4  # policy; paper: 1e-6
    cfg.anneal_learning_rate = False  # decay the policy's rate linearly to 0 over the run; paper: constant
    cfg.value_learning_rate = 1e-3  # the value net's own Adam; paper: one Adam at 1e-6 for both
    cfg.max_grad_norm = 1.0  # clip the gradient's global norm; paper (Baselines PPO1): none
    cfg.discount = 0.999  # paper: 0.999
    cfg.gae_lambda = 1.0  # paper: 1.0
    cfg.clip_epsilon = 0.29  # paper: 0.29
    cfg.entropy_cost = 0.01  # paper: 0.01
    cfg.vf_coefficient = 0.5  # paper (Baselines PPO1): 1.0 on a separate value loss
    # Reward factor on top of the env's own 0.1 per-step factor (the paper's "x 0.1" in all).
    cfg.reward_scaling = 0.01
    cfg.normalize_advantage = True  # paper (Baselines PPO1): yes
    # Weight w of potential-based shaping (Ng et al. 1999): training rewards get w * (discount *
    # phi(s') - phi(s)) from the env's metrics["potential"]; the optimal policy is unchanged; 0: off.
    cfg.potential_shaping = 0.0
    # GAE's backward recursion unrolled into one fused program (True) or a device loop of one
    # iteration per time step, as Brax's (False). The same numbers up to float rounding; speed only.
    cfg.unroll_gae = True
    # Running observation statistics; off: observations are (phase, context) in [0, 1] already.
    cfg.normalize_observations = False
    cfg.policy_hidden = (64, 64)  # paper: 64-64 tanh
    cfg.value_hidden = (64, 64)  # paper: 64-64 tanh
    cfg.init_log_std = -6.0  # state-independent log-std at the start; paper: -6
    # None: every episode of `train(rng, target)` kicks for `target` (an expert). (low, high):
    # each episode draws its own target from U[low, high] and `target` is ignored (multi-task PPO).
    cfg.sample_task_range = ml_collections.FieldReference(None, field_type=tuple)
    return cfg


def brax_defaults() -> ml_collections.ConfigDict:
    """`default_config()` at the defaults of Brax's PPO (`brax.training.agents.ppo`), which its
    locomotion notebooks keep: one Adam at 3e-4 for both nets, GAE lambda 0.95, clip 0.3,
    observation normalisation, a 4 x 32 policy and a 5 x 256 value net, the tanh-normal's std
    softplus(0) = 0.69 at the start. A task sets its own batch, discount, entropy and reward scale."""
    cfg = default_config()
    cfg.learning_rate = 3e-4
    cfg.value_learning_rate = 3e-4  # Brax: one Adam for both nets
    cfg.gae_lambda = 0.95
    cfg.clip_epsilon = 0.3
    cfg.normalize_observations = True
    cfg.policy_hidden = (32, 32, 32, 32)
    cfg.value_hidden = (256, 256, 256, 256, 256)
    cfg.init_log_std = -0.37  # std 0.69
    return cfg


def make_config(config=None, overrides: dict | None = None) -> ml_collections.ConfigDict:
    """A locked copy of a PPO section (default: `default_config()`) with dotted `overrides`."""
    return locked_config(default_config() if config is None else config, overrides)


def validate_config(cfg: ml_collections.ConfigDict, n_steps: int, prefix: str = "ppo.") -> None:
    """ValueError naming the first bad value of a PPO section (`n_steps`: the env's episode length;
    `prefix`: where the section sits in the config tree, for the message)."""
    for key in ("num_envs", "num_minibatches", "num_epochs", "total_env_steps"):
        value = cfg[key]
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
            raise ValueError(f"{prefix}{key} must be a positive integer, got {value!r}")
    if cfg.num_envs % cfg.num_minibatches:
        raise ValueError(
            f"{prefix}num_minibatches {cfg.num_minibatches} must divide {prefix}num_envs {cfg.num_envs}"
            " (minibatches are whole episodes)"
        )
    if cfg.total_env_steps < cfg.num_envs * n_steps:
        raise ValueError(
            f"{prefix}total_env_steps {cfg.total_env_steps} is less than one update "
            f"(num_envs {cfg.num_envs} x {n_steps} steps)"
        )
    for key in ("learning_rate", "value_learning_rate", "max_grad_norm", "clip_epsilon", "reward_scaling"):
        if not np.isfinite(cfg[key]) or cfg[key] <= 0:
            raise ValueError(f"{prefix}{key} must be > 0, got {cfg[key]!r}")
    for key in ("discount", "gae_lambda"):
        if not 0.0 <= cfg[key] <= 1.0:
            raise ValueError(f"{prefix}{key} must be in [0, 1], got {cfg[key]!r}")
    for key in ("entropy_cost", "vf_coefficient", "potential_shaping"):
        if cfg[key] < 0:
            raise ValueError(f"{prefix}{key} must be >= 0, got {cfg[key]!r}")
    for key in ("policy_hidden", "value_hidden"):
        if not cfg[key] or any(int(h) < 1 for h in cfg[key]):
            raise ValueError(f"{prefix}{key} must be positive layer sizes, got {tuple(cfg[key])!r}")
    low_high = cfg.sample_task_range
    if low_high is not None and (len(low_high) != 2 or not np.isfinite(low_high).all() or low_high[0] >= low_high[1]):
        raise ValueError(f"{prefix}sample_task_range must be (low, high) with low < high, got {tuple(low_high)}")


def n_updates(cfg: ml_collections.ConfigDict, n_steps: int) -> int:
    """Updates that fit in `total_env_steps` (whole updates only)."""
    return int(cfg.total_env_steps // (cfg.num_envs * n_steps))


def sgd_steps(cfg: ml_collections.ConfigDict, n_steps: int) -> int:
    """Adam steps of a whole run: updates x epochs x minibatches."""
    return n_updates(cfg, n_steps) * cfg.num_epochs * cfg.num_minibatches
