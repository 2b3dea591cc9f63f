"""A pure, vmappable PPO trainer for one contextual task (one target per call), built from Brax's PPO pieces.

PureJaxRL pattern: `make_train(config, env)` returns pure functions; the whole training loop is
a `lax.scan` over updates with no host round-trip inside, so `jax.vmap` over tasks trains every
expert in one compiled program. From Brax we take the networks (`ppo.networks`), the
observation normaliser (`acme.running_statistics`) and the gradient step
(`gradients.gradient_update_fn`); the loss is Brax's `ppo.losses.compute_ppo_loss` rewritten
(`ppo_loss`: the same terms, GAE from the minibatch's current values) so that its GAE can be
unrolled (`unroll_gae`), and a test holds the two equal. We do not
use `ppo.train` (it replicates over devices with `jax.device_put_replicated` and cannot be
vmapped).

Rollouts are whole episodes: every update resets `num_envs` episodes and runs the env's
`n_steps` (the kick's 75), so the batch is (num_envs, n_steps) and minibatches are whole
episodes. An episode's end is a termination unless the env flags it a truncation (a time-limit
cut) in `state.info["truncation"]`, Brax's convention; GAE then bootstraps through it as Brax
does (`truncation_of`, `advantages`). The behaviour follows from the env, not from a
hyperparameter: the kick env keeps no such flag.

The only randomness comes from `TrainState.rng`, split once per update: a run cut into chunks of
any size, or killed and resumed from a checkpoint, takes exactly the same path as one
uninterrupted scan.

The PPO section of the config (its defaults, checks and the run length it implies) is
`bumps_jax.algo.ppo_config`.
"""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import ml_collections
import optax
from brax.training import gradients, types
from brax.training.acme import running_statistics
from brax.training.agents.ppo import losses as ppo_losses
from brax.training.agents.ppo import networks as ppo_networks
from flax import linen

from bumps_jax.algo import ppo_config
from bumps_jax.envs import base as task_env

PPONetworkParams = ppo_losses.PPONetworkParams


# -- state ------------------------------------------------------------------------------------


class TrainState(NamedTuple):
    """Everything a run carries from one update to the next (one expert; vmap adds a task axis)."""

    params: PPONetworkParams  # policy and value network params
    opt_state: Any  # optax state of the Adam optimiser
    normalizer: running_statistics.RunningStatisticsState  # observation statistics
    rng: jax.Array  # (2,) uint32 raw key: the only source of randomness
    update: jax.Array  # () int32, updates done
    env_steps: jax.Array  # () int32, env steps taken


class UpdateMetrics(NamedTuple):
    """What one update reports (each a scalar; a scan stacks them to (n_updates,))."""

    episode_return: jax.Array  # mean over the batch's episodes
    final_error: jax.Array  # mean final resting error (m); NaN for an env that reports none
    valid: jax.Array  # fraction of valid kicks; NaN for an env that reports none
    total_loss: jax.Array  # mean over the update's minibatch steps
    policy_loss: jax.Array
    v_loss: jax.Array
    kl_mean: jax.Array
    policy_std: jax.Array  # mean action std (rad)


class Trainer(NamedTuple):
    """The pure functions of one PPO configuration (from `make_train`).

    init(rng, policy_params=None, learning_rate=None) -> TrainState
    run_updates(state, target, n) -> (TrainState, UpdateMetrics of (n,)); n static
    train(rng, target, policy_params=None, learning_rate=None) -> (TrainState, UpdateMetrics of (n_updates,))
    """

    networks: ppo_networks.PPONetworks
    init: Any
    run_updates: Any
    train: Any
    n_updates: int
    steps_per_update: int


class _Context(NamedTuple):
    """The static pieces the scan bodies need, bound with functools.partial."""

    env: task_env.ContextualEnv
    networks: ppo_networks.PPONetworks
    optimizer: optax.GradientTransformation
    config: ml_collections.ConfigDict


# -- networks ---------------------------------------------------------------------------------


def make_networks(cfg: ml_collections.ConfigDict, obs_size: int, action_size: int) -> ppo_networks.PPONetworks:
    """Brax's PPO networks: Gaussian policy (tanh MLP mean, state-independent trainable log-std).

    Brax 0.14's `distribution_type='normal'` with `noise_std_type='log'` and
    `state_dependent_std=False` is exactly the paper's policy: the std is a learned vector
    `exp(log_std)` (22,), unbounded Gaussian actions (the env clips joint targets itself).
    """
    preprocess = running_statistics.normalize if cfg.normalize_observations else types.identity_observation_preprocessor
    return ppo_networks.make_ppo_networks(
        obs_size,
        action_size,
        preprocess_observations_fn=preprocess,
        policy_hidden_layer_sizes=tuple(int(h) for h in cfg.policy_hidden),
        value_hidden_layer_sizes=tuple(int(h) for h in cfg.value_hidden),
        activation=linen.tanh,
        distribution_type="normal",
        noise_std_type="log",
        init_noise_std=math.exp(cfg.init_log_std),
        state_dependent_std=False,
    )


def policy_mean(networks: ppo_networks.PPONetworks, normalizer, policy_params, obs: jax.Array) -> jax.Array:
    """Deterministic action: the Gaussian's mean. obs (..., obs_size) -> (..., action_size)."""
    loc, _ = networks.policy_network.apply(normalizer, policy_params, obs)
    return loc


def init_normalizer(obs_size: int) -> running_statistics.RunningStatisticsState:
    return running_statistics.init_state(jnp.zeros((obs_size,)))


# -- GAE as the loss sees it ------------------------------------------------------------------


def gae(truncation, termination, rewards, values, bootstrap_value, discount: float, gae_lambda: float, unroll: bool):
    """Brax's GAE (`ppo.losses.compute_gae`: the same recursion and outputs) over (T, B) arrays:
    (value targets, advantages), both (T, B) and without gradient.

    A truncated step's own TD error is zeroed and the step before it bootstraps on its value;
    a termination stops the return. With `unroll` the backward recursion is unrolled into
    straight-line code that XLA fuses; otherwise it is a device loop of one iteration per time
    step, as Brax's (on a GPU each iteration costs kernel launches: see docs/decisions.md).
    """
    keep = 1.0 - truncation
    live = discount * (1.0 - termination)
    next_values = jnp.concatenate([values[1:], bootstrap_value[None]], axis=0)
    deltas = (rewards + live * next_values - values) * keep

    def back(acc, step):
        delta, decay = step
        acc = delta + decay * acc
        return acc, acc

    _, vs_minus_v = jax.lax.scan(
        back, jnp.zeros_like(bootstrap_value), (deltas, live * keep * gae_lambda), reverse=True, unroll=bool(unroll)
    )
    vs = vs_minus_v + values
    next_vs = jnp.concatenate([vs[1:], bootstrap_value[None]], axis=0)
    advantage = (rewards + live * next_vs - values) * keep
    return jax.lax.stop_gradient(vs), jax.lax.stop_gradient(advantage)


def advantages(
    rewards, values, dones, bootstrap_value, discount: float, gae_lambda: float, truncation=None, unroll=True
):
    """GAE with our episode ends: returns (value targets, advantages), both (T, B).

    rewards, values, dones: (T, B); bootstrap_value: (B,); truncation: (T, B) or None (zeros).
    A done step is a termination unless it is also a truncation (a time-limit cut, flagged by
    the env's `info["truncation"]`); a truncated step bootstraps as in Brax: its own TD error
    and advantage are zeroed and the step before it bootstraps on its value. `ppo_loss` calls it
    on its minibatch (done = 1 - the transitions' discount), as Brax's loss maps them.
    """
    truncation = jnp.zeros_like(rewards) if truncation is None else truncation
    return gae(truncation, dones * (1 - truncation), rewards, values, bootstrap_value, discount, gae_lambda, unroll)


# -- rollout ----------------------------------------------------------------------------------


class _RolloutCarry(NamedTuple):
    env_state: Any  # brax State batched over (num_envs,)
    rng: jax.Array


def truncation_of(state) -> jax.Array:
    """Which episodes of `state` (B,) a time limit cut rather than ended: the env's
    `info["truncation"]` (Brax's convention, as its EpisodeWrapper and MuJoCo Playground set it),
    or zeros for an env that keeps none (the kick env: its episode end is a termination)."""
    if "truncation" in state.info:
        return jnp.asarray(state.info["truncation"], state.done.dtype)
    return jnp.zeros_like(state.done)


def _env_step(ctx: _Context, normalizer, policy_params, carry: _RolloutCarry, _unused):
    """One control step of every episode in the batch: (carry, None) -> (carry, Transition)."""
    rng, key = jax.random.split(carry.rng)
    dist = ctx.networks.parametric_action_distribution
    state = carry.env_state
    logits = ctx.networks.policy_network.apply(normalizer, policy_params, state.obs)
    raw = dist.sample_no_postprocessing(logits, key)
    log_prob = dist.log_prob(logits, raw)
    nxt = jax.vmap(ctx.env.step)(state, dist.postprocess(raw))
    state_extras = {"truncation": truncation_of(nxt)}
    if ctx.config.potential_shaping:  # the potentials the loss shapes the reward with
        state_extras.update(potential=state.metrics["potential"], next_potential=nxt.metrics["potential"])
    transition = types.Transition(
        observation=state.obs,
        action=raw,
        reward=nxt.reward,
        discount=1.0 - nxt.done,
        next_observation=nxt.obs,
        extras={
            "policy_extras": {"log_prob": log_prob, "raw_action": raw, "distribution_params": logits},
            "state_extras": state_extras,
        },
    )
    return _RolloutCarry(nxt, rng), transition


def rollout(ctx: _Context, normalizer, policy_params, target, rng):
    """`num_envs` whole episodes at `target` m (or at sampled targets, see `sample_task_range`).

    Returns (final env State (B,), Transition (B, T)).
    """
    rng_reset, rng_steps = jax.random.split(rng)
    keys = jax.random.split(rng_reset, ctx.config.num_envs)
    # A vector context (env.CONTEXT_SIZE K > 1): targets (B, K), each coordinate from U[low, high].
    shape = (ctx.config.num_envs, *task_env.context_shape(getattr(ctx.env, "CONTEXT_SIZE", 1)))
    if ctx.config.sample_task_range is None:
        targets = jnp.broadcast_to(target, shape)
    else:
        low, high = ctx.config.sample_task_range
        rng_task = jax.random.fold_in(rng_reset, 1)
        targets = jax.random.uniform(rng_task, shape, minval=low, maxval=high)
    env_state = jax.vmap(ctx.env.reset)(keys, targets)
    body = functools.partial(_env_step, ctx, normalizer, policy_params)
    carry, data = jax.lax.scan(body, _RolloutCarry(env_state, rng_steps), None, ctx.env.n_steps)
    # (T, B) -> (B, T): Brax's loss takes batch-major data and swaps it back itself.
    return carry.env_state, jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), data)


# -- one update -------------------------------------------------------------------------------


class _SGDCarry(NamedTuple):
    params: PPONetworkParams
    opt_state: Any
    rng: jax.Array


def shaped_rewards(cfg, data) -> jax.Array:
    """The env's rewards (T, M), plus potential-based shaping w * (discount * phi(s') - phi(s))
    where `potential_shaping` w is set: phi of a terminal state is 0, and a truncated step's
    reward is dropped by `advantages` anyway (its successor's value stands in)."""
    w = cfg.potential_shaping
    if not w:
        return data.reward
    extras = data.extras["state_extras"]
    termination = (1 - data.discount) * (1 - extras["truncation"])
    return data.reward + w * (cfg.discount * extras["next_potential"] * (1 - termination) - extras["potential"])


def ppo_loss(ctx: _Context, params, normalizer, data, rng):
    """Brax's PPO loss (`ppo.losses.compute_ppo_loss` at our settings: no value clipping, no
    distributional critic) on a minibatch of whole episodes `data` (M, T), its GAE from
    `advantages` with the current value net: (total loss, metrics)."""
    cfg = ctx.config
    dist = ctx.networks.parametric_action_distribution
    data = jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), data)  # time first: (T, M)
    logits = ctx.networks.policy_network.apply(normalizer, params.policy, data.observation)
    values = ctx.networks.value_network.apply(normalizer, params.value, data.observation)
    bootstrap = ctx.networks.value_network.apply(normalizer, params.value, data.next_observation[-1])
    truncation = data.extras["state_extras"]["truncation"]
    rewards = shaped_rewards(cfg, data) * cfg.reward_scaling
    vs, advantage = advantages(
        rewards, values, 1 - data.discount, bootstrap, cfg.discount, cfg.gae_lambda, truncation, cfg.unroll_gae
    )
    if cfg.normalize_advantage:
        advantage = (advantage - advantage.mean()) / (advantage.std() + 1e-8)
    behaviour = data.extras["policy_extras"]
    ratio = jnp.exp(dist.log_prob(logits, behaviour["raw_action"]) - behaviour["log_prob"])
    clipped = jnp.clip(ratio, 1 - cfg.clip_epsilon, 1 + cfg.clip_epsilon)
    policy_loss = -jnp.mean(jnp.minimum(ratio * advantage, clipped * advantage))
    v_loss = 0.5 * cfg.vf_coefficient * jnp.mean((vs - values) ** 2)
    entropy_loss = -cfg.entropy_cost * jnp.mean(dist.entropy(logits, rng))
    kl = dist.create_dist(logits).kl_divergence(dist.create_dist(behaviour["distribution_params"]))
    total = policy_loss + v_loss + entropy_loss
    metrics = {"total_loss": total, "policy_loss": policy_loss, "v_loss": v_loss, "entropy_loss": entropy_loss}
    return total, {**metrics, "kl_mean": jnp.mean(kl)}


def _minibatch_step(ctx: _Context, normalizer, carry: _SGDCarry, minibatch):
    """One gradient step on one minibatch of whole episodes (M, T): -> (carry, loss metrics)."""
    rng, key = jax.random.split(carry.rng)
    step = gradients.gradient_update_fn(
        functools.partial(ppo_loss, ctx), ctx.optimizer, pmap_axis_name=None, has_aux=True
    )
    (_, metrics), params, opt_state = step(carry.params, normalizer, minibatch, key, optimizer_state=carry.opt_state)
    return _SGDCarry(params, opt_state, rng), metrics


def _epoch(ctx: _Context, normalizer, data, carry: _SGDCarry, _unused):
    """One pass over the batch (B, T) in shuffled minibatches of whole episodes."""
    rng, key = jax.random.split(carry.rng)
    cfg = ctx.config
    order = jax.random.permutation(key, cfg.num_envs)

    def to_minibatches(x):
        return x[order].reshape((cfg.num_minibatches, -1) + x.shape[1:])

    minibatches = jax.tree_util.tree_map(to_minibatches, data)
    body = functools.partial(_minibatch_step, ctx, normalizer)
    carry, metrics = jax.lax.scan(body, carry._replace(rng=rng), minibatches)
    return carry, metrics


def _final_mean(final, name: str) -> jax.Array:
    """The batch mean of the episodes' final `metrics[name]`, or NaN for an env that keeps no such
    metric (the kick's `final_error` and `valid` mean nothing to Brax's halfcheetah)."""
    if name in final.metrics:
        return final.metrics[name].mean()
    return jnp.full((), jnp.nan, jnp.float32)


def _update_step(ctx: _Context, target, state: TrainState, _unused):
    """Collect one batch at `target` and run the PPO epochs on it: (state, None) -> (state, metrics)."""
    cfg = ctx.config
    rng, rng_rollout, rng_sgd = jax.random.split(state.rng, 3)
    final, data = rollout(ctx, state.normalizer, state.params.policy, target, rng_rollout)
    normalizer = state.normalizer
    if cfg.normalize_observations:
        normalizer = running_statistics.update(normalizer, data.observation)
    body = functools.partial(_epoch, ctx, normalizer, data)
    sgd, losses = jax.lax.scan(body, _SGDCarry(state.params, state.opt_state, rng_sgd), None, cfg.num_epochs)
    _, std = ctx.networks.policy_network.apply(normalizer, sgd.params.policy, data.observation[0, :1])
    metrics = UpdateMetrics(
        episode_return=data.reward.sum(axis=1).mean(),
        final_error=_final_mean(final, "final_error"),
        valid=_final_mean(final, "valid"),
        total_loss=losses["total_loss"].mean(),
        policy_loss=losses["policy_loss"].mean(),
        v_loss=losses["v_loss"].mean(),
        kl_mean=losses["kl_mean"].mean(),
        policy_std=std.mean(),
    )
    new_state = TrainState(
        params=sgd.params,
        opt_state=sgd.opt_state,
        normalizer=normalizer,
        rng=rng,
        update=state.update + 1,
        env_steps=state.env_steps + cfg.num_envs * ctx.env.n_steps,
    )
    return new_state, metrics


# -- the trainer ------------------------------------------------------------------------------


def _labels(params: PPONetworkParams) -> PPONetworkParams:
    return PPONetworkParams(
        policy=jax.tree_util.tree_map(lambda _: "policy", params.policy),
        value=jax.tree_util.tree_map(lambda _: "value", params.value),
    )


def make_optimizer(
    cfg: ml_collections.ConfigDict, n_steps: int, traced_learning_rate: bool = False
) -> optax.GradientTransformation:
    """Adam with separate learning rates for the policy and the value net, after norm clipping.

    With `anneal_learning_rate` the policy's rate falls linearly to 0 over the run; the
    critic's stays constant, so it keeps tracking the returns of the settling policy. With
    `traced_learning_rate` the policy's rate is a value of the optimiser state
    (`optax.inject_hyperparams`), so that runs at several rates vmap as one program.
    """
    policy_lr = cfg.learning_rate
    if cfg.anneal_learning_rate:
        if traced_learning_rate:
            raise ValueError("a traced learning rate is constant: anneal_learning_rate must be false")
        policy_lr = optax.linear_schedule(cfg.learning_rate, 0.0, ppo_config.sgd_steps(cfg, n_steps))
    policy_adam = optax.inject_hyperparams(optax.adam)(learning_rate=policy_lr) if traced_learning_rate else None
    adam = optax.multi_transform(
        {"policy": policy_adam or optax.adam(policy_lr), "value": optax.adam(cfg.value_learning_rate)}, _labels
    )
    return optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), adam)


def reset_metrics(env) -> dict:
    """The shapes of the metrics an episode of `env` starts with (nothing is computed)."""
    target = jnp.zeros(task_env.context_shape(getattr(env, "CONTEXT_SIZE", 1)), jnp.float32)
    return jax.eval_shape(env.reset, jax.random.key(0), target).metrics


def make_train(
    config, env: task_env.ContextualEnv, traced_learning_rate: bool = False, prefix: str = "ppo."
) -> Trainer:
    """Validate `config` (a PPO ConfigDict, its keys `prefix`... in messages) and build the pure
    trainer for `env`.

    All returned functions are pure and unjitted: jit / vmap them as needed. The target is a
    traced argument, so one compiled program serves any task (and a vmapped batch of tasks).
    With `traced_learning_rate`, `init` and `train` take the policy's learning rate too
    (`learning_rate`, default config.learning_rate), so a vmapped batch may mix rates.
    """
    cfg = ppo_config.make_config(config)
    ppo_config.validate_config(cfg, env.n_steps, prefix)
    if cfg.potential_shaping and "potential" not in reset_metrics(env):
        raise ValueError(
            f"{prefix}potential_shaping {cfg.potential_shaping!r} needs an env that reports metrics['potential']; "
            f"{type(env).__name__} does not: set it to 0"
        )
    networks = make_networks(cfg, env.observation_size, env.action_size)
    optimizer = make_optimizer(cfg, env.n_steps, traced_learning_rate)
    ctx = _Context(env, networks, optimizer, cfg)
    total = ppo_config.n_updates(cfg, env.n_steps)

    def init(rng: jax.Array, policy_params=None, learning_rate=None) -> TrainState:
        """A fresh state; `policy_params` (e.g. from behaviour cloning) replace the random policy;
        `learning_rate` (traced trainers only) the policy's rate."""
        rng, key_policy, key_value = jax.random.split(rng, 3)
        policy = networks.policy_network.init(key_policy) if policy_params is None else policy_params
        params = PPONetworkParams(policy=policy, value=networks.value_network.init(key_value))
        opt_state = optimizer.init(params)
        if learning_rate is not None:
            if not traced_learning_rate:
                raise ValueError("this trainer's learning rate is fixed: make_train(..., traced_learning_rate=True)")
            opt_state = optax.tree_utils.tree_set(opt_state, learning_rate=jnp.asarray(learning_rate, jnp.float32))
        return TrainState(
            params=params,
            opt_state=opt_state,
            normalizer=init_normalizer(env.observation_size),
            rng=rng,
            update=jnp.zeros((), jnp.int32),
            env_steps=jnp.zeros((), jnp.int32),
        )

    def run_updates(state: TrainState, target, n: int):
        """`n` (static) PPO updates at `target` (scalar m)."""
        body = functools.partial(_update_step, ctx, jnp.asarray(target, jnp.float32))
        return jax.lax.scan(body, state, None, n)

    def train(rng: jax.Array, target, policy_params=None, learning_rate=None):
        """The whole budget in one scan: (final TrainState, UpdateMetrics of (n_updates,))."""
        return run_updates(init(rng, policy_params, learning_rate), target, total)

    return Trainer(networks, init, run_updates, train, total, cfg.num_envs * env.n_steps)
