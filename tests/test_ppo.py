"""The PPO trainer: GAE by hand (with and without truncated episode ends), truncation carried
from the env, config errors, a tiny run that learns (vmapped = alone and resuming are in
test_experts.py, which shares their compiled programs)."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from brax.envs.base import State
from brax.training import types
from brax.training.agents.ppo import losses as ppo_losses

from bumps_jax import config
from bumps_jax.algo import ppo, ppo_config
from bumps_jax.pipeline import expert_programs

N_STEPS = 75


def _hand_gae(rewards, values, dones, bootstrap, gamma, lam):
    """Textbook GAE for one trajectory, a Python loop: (value targets, advantages)."""
    T = len(rewards)
    adv = np.zeros(T)
    last = 0.0
    for t in reversed(range(T)):
        nonterminal = 1.0 - dones[t]
        next_value = bootstrap if t == T - 1 else values[t + 1]
        delta = rewards[t] + gamma * nonterminal * next_value - values[t]
        last = delta + gamma * lam * nonterminal * last
        adv[t] = last
    return adv + values, adv


def test_gae_matches_hand_computation():
    """Two trajectories; the first ends mid-way (a new episode starts after step 2)."""
    rewards = np.array([[1.0, -0.5], [0.5, 2.0], [-1.0, 0.0], [2.0, 1.0], [0.3, -0.2]])
    values = np.array([[0.2, 0.1], [0.4, -0.3], [0.1, 0.5], [-0.2, 0.3], [0.6, 0.0]])
    dones = np.array([[0, 0], [0, 0], [1, 0], [0, 0], [0, 1]], dtype=float)
    bootstrap = np.array([0.7, -0.4])
    gamma, lam = 0.9, 0.8
    vs, adv = ppo.advantages(
        jnp.asarray(rewards), jnp.asarray(values), jnp.asarray(dones), jnp.asarray(bootstrap), gamma, lam
    )
    for b in range(2):
        want_vs, want_adv = _hand_gae(rewards[:, b], values[:, b], dones[:, b], bootstrap[b], gamma, lam)
        np.testing.assert_allclose(np.asarray(vs)[:, b], want_vs, rtol=1e-5, atol=1e-6)
        # Brax's policy advantage is the one-step TD error on the lambda-returns, which
        # equals GAE's advantage for lambda = 1 and differs otherwise; check both ways.
        next_vs = np.append(want_vs[1:], bootstrap[b])
        td = rewards[:, b] + gamma * (1 - dones[:, b]) * next_vs - values[:, b]
        np.testing.assert_allclose(np.asarray(adv)[:, b], td, rtol=1e-5, atol=1e-6)
    # With lambda = 1 (the paper's) both advantages are the discounted return minus the value.
    vs1, adv1 = ppo.advantages(
        jnp.asarray(rewards), jnp.asarray(values), jnp.asarray(dones), jnp.asarray(bootstrap), gamma, 1.0
    )
    for b in range(2):
        _, want = _hand_gae(rewards[:, b], values[:, b], dones[:, b], bootstrap[b], gamma, 1.0)
        np.testing.assert_allclose(np.asarray(adv1)[:, b], want, rtol=1e-5, atol=1e-6)


def test_gae_bootstraps_through_truncation_as_brax():
    """Three steps, gamma 0.9, lambda 1, by hand. Column 0: a time limit cuts the episode at step 1
    and a new one starts at step 2 (Brax's auto-reset layout). Column 1: the cut is the last step
    (ours: whole episodes). A truncated step's own TD error and advantage are zeroed (its true
    successor is unknown to Brax's GAE), and the step before it bootstraps on its value instead of
    treating the end as a termination."""
    rewards = np.array([[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]])
    values = np.array([[0.5, 0.5], [1.0, 1.0], [1.5, 1.5]])
    dones = np.array([[0, 0], [1, 0], [0, 1]], dtype=float)
    truncation = dones.copy()  # every end here is a time-limit cut
    bootstrap = np.array([2.0, 2.0])
    args = [jnp.asarray(a) for a in (rewards, values, dones, bootstrap)]
    vs, adv = ppo.advantages(*args, 0.9, 1.0, truncation=jnp.asarray(truncation))
    # Column 0: step 0 -> 1 + 0.9 V(s1) = 1.9; step 1 -> its own value 1.0 (advantage 0);
    # step 2 (next episode) -> 3 + 0.9 * bootstrap 2.0 = 4.8.
    # Column 1: step 0 -> 1 + 0.9 * 2 + 0.81 V(s2) = 4.015; step 1 -> 2 + 0.9 V(s2) = 3.35;
    # step 2 -> its own value 1.5 (advantage 0).
    want_vs = np.array([[1.9, 4.015], [1.0, 3.35], [4.8, 1.5]])
    want_adv = np.array([[1.9 - 0.5, 1 + 0.9 * 3.35 - 0.5], [0.0, 3.35 - 1.0], [4.8 - 1.5, 0.0]])
    np.testing.assert_allclose(np.asarray(vs), want_vs, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(adv), want_adv, rtol=1e-6, atol=1e-6)
    # The same ends as terminations (an env without the flag) stop the return at the end instead.
    vs_term, _ = ppo.advantages(*args, 0.9, 1.0)
    np.testing.assert_allclose(np.asarray(vs_term)[:, 0], [1 + 0.9 * 2, 2.0, 4.8], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(vs_term)[:, 1], [1 + 0.9 * 2 + 0.81 * 3, 2 + 0.9 * 3, 3.0], rtol=1e-6)
    # And equal to Brax's own GAE fed as Brax's loss feeds it, at another lambda too, unrolled or a loop.
    for lam, unroll in ((1.0, True), (0.7, True), (0.7, False)):
        ours = ppo.advantages(*args, 0.9, lam, truncation=jnp.asarray(truncation), unroll=unroll)
        brax = ppo_losses.compute_gae(
            truncation=jnp.asarray(truncation),
            # Brax's loss: termination = (1 - discount) * (1 - truncation), with discount = 1 - done.
            termination=jnp.asarray(dones * (1 - truncation)),
            rewards=args[0],
            values=args[1],
            bootstrap_value=args[3],
            lambda_=lam,
            discount=0.9,
        )
        for a, b in zip(ours, brax, strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-6)


def _minibatch(rng, networks, n_episodes: int, n_steps: int, obs_size: int):
    """Transitions (M, T) as the rollout stores them, from the policy's own samples; episodes 0 and 1
    end early (a termination, then a time-limit cut)."""
    keys = jax.random.split(rng, 5)
    obs = jax.random.uniform(keys[0], (n_episodes, n_steps + 1, obs_size))
    policy = networks.policy_network.init(keys[1])
    logits = networks.policy_network.apply(None, policy, obs[:, :-1])
    dist = networks.parametric_action_distribution
    raw = dist.sample_no_postprocessing(logits, keys[2])
    done = jnp.zeros((n_episodes, n_steps)).at[:, -1].set(1.0).at[0, 5].set(1.0).at[1, 7].set(1.0)
    truncation = jnp.zeros_like(done).at[1, 7].set(1.0)
    return types.Transition(
        observation=obs[:, :-1],
        action=raw,
        reward=jax.random.normal(keys[3], (n_episodes, n_steps)) * 10 - 50,
        discount=1.0 - done,
        next_observation=obs[:, 1:],
        extras={
            "policy_extras": {
                "log_prob": dist.log_prob(logits, raw) + 0.1,
                "raw_action": raw,
                "distribution_params": logits,
            },
            "state_extras": {"truncation": truncation},
        },
    )


@pytest.mark.parametrize("unroll", [True, False])
def test_loss_and_gradient_equal_braxs(unroll):
    """`ppo.ppo_loss` is Brax's `compute_ppo_loss` at our settings: the same loss terms and
    gradient on a minibatch of 8 episodes of 12 steps (float rounding apart)."""
    cfg = ppo_config.make_config(overrides={"unroll_gae": unroll, "gae_lambda": 0.95})
    networks = ppo.make_networks(cfg, 3, 4)
    ctx = ppo._Context(None, networks, None, cfg)
    key = jax.random.PRNGKey(3)
    data = _minibatch(key, networks, 8, 12, 3)
    params = ppo.PPONetworkParams(networks.policy_network.init(key), networks.value_network.init(jax.random.PRNGKey(4)))

    def brax(p):
        return ppo_losses.compute_ppo_loss(
            p, None, data, key, networks, entropy_cost=cfg.entropy_cost, discounting=cfg.discount,
            reward_scaling=cfg.reward_scaling, gae_lambda=cfg.gae_lambda, clipping_epsilon=cfg.clip_epsilon,
            normalize_advantage=cfg.normalize_advantage, vf_coefficient=cfg.vf_coefficient,
        )  # fmt: skip

    (want, want_metrics), want_grad = jax.value_and_grad(brax, has_aux=True)(params)
    (got, got_metrics), got_grad = jax.value_and_grad(lambda p: ppo.ppo_loss(ctx, p, None, data, key), has_aux=True)(
        params
    )
    assert abs(float(want)) > 1e-3 and float(want_metrics["kl_mean"]) > 0
    for name in ("total_loss", "policy_loss", "v_loss", "entropy_loss", "kl_mean"):
        np.testing.assert_allclose(float(got_metrics[name]), float(want_metrics[name]), rtol=1e-5, err_msg=name)
    flat_want, flat_got = jax.tree.leaves(want_grad), jax.tree.leaves(got_grad)
    assert len(flat_want) == len(flat_got) and max(float(jnp.abs(g).max()) for g in flat_want) > 1e-3
    for a, b in zip(flat_got, flat_want, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)


class _CountingEnv:
    """A stand-in env of 3 steps: obs = step / 3, reward 1; `flag` keeps Brax's `info["truncation"]`;
    `potential` reports metrics["potential"] = -(step + 1)."""

    n_steps = 3
    observation_size = 1
    action_size = 1

    def __init__(self, flag: bool, potential: bool = False):
        self.flag, self.potential = flag, potential

    def _metrics(self, step):
        return {"potential": -(step + 1.0)} if self.potential else {}

    def reset(self, rng, target=None):
        del rng, target
        info = {"step": jnp.zeros(())} | ({"truncation": jnp.zeros(())} if self.flag else {})
        return State(None, jnp.zeros(1), jnp.zeros(()), jnp.zeros(()), self._metrics(jnp.zeros(())), info)

    def step(self, state, action):
        del action
        step = state.info["step"] + 1
        done = (step >= self.n_steps).astype(jnp.float32)
        info = {"step": step} | ({"truncation": done} if self.flag else {})
        return State(None, step[None] / 3, jnp.ones(()), done, self._metrics(step), info)


@pytest.mark.parametrize("flag", [True, False])
def test_rollout_carries_the_envs_truncation(flag):
    """Transitions carry the env's `info["truncation"]`; an env without it gives zeros."""
    env = _CountingEnv(flag)
    cfg = ppo_config.make_config(overrides={"num_envs": 2, "num_minibatches": 1, "total_env_steps": 6})
    networks = ppo.make_networks(cfg, env.observation_size, env.action_size)
    ctx = ppo._Context(env, networks, ppo.make_optimizer(cfg, env.n_steps), cfg)
    params = networks.policy_network.init(jax.random.PRNGKey(0))
    _, data = ppo.rollout(ctx, ppo.init_normalizer(1), params, 0.0, jax.random.PRNGKey(1))
    truncation = np.asarray(data.extras["state_extras"]["truncation"])  # (B, T)
    np.testing.assert_array_equal(truncation, [[0, 0, float(flag)]] * 2)
    np.testing.assert_array_equal(np.asarray(data.discount), [[1, 1, 0]] * 2)


@pytest.mark.parametrize("flag", [True, False])
def test_potential_shaping_adds_discounted_potential_differences(flag):
    """With `potential_shaping` w the loss's rewards are r + w (discount phi(s') - phi(s)), phi of a
    terminal state 0 (a truncated episode keeps its last potential); the logged return stays r."""
    env = _CountingEnv(flag, potential=True)
    overrides = {"num_envs": 2, "num_minibatches": 1, "total_env_steps": 6, "potential_shaping": 2.0, "discount": 0.9}
    cfg = ppo_config.make_config(overrides=overrides)
    networks = ppo.make_networks(cfg, env.observation_size, env.action_size)
    ctx = ppo._Context(env, networks, ppo.make_optimizer(cfg, env.n_steps), cfg)
    params = networks.policy_network.init(jax.random.PRNGKey(0))
    _, data = ppo.rollout(ctx, ppo.init_normalizer(1), params, 0.0, jax.random.PRNGKey(1))
    phi = -(np.arange(4) + 1.0)  # phi(s_0), ..., phi(s_3)
    after = phi[1:].copy()
    if not flag:
        after[-1] = 0.0  # the episode's end is a termination
    np.testing.assert_allclose(ppo.shaped_rewards(cfg, data), [1 + 2.0 * (0.9 * after - phi[:-1])] * 2, rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(data.reward), 1.0)
    ppo.make_train(cfg, env)  # accepted: the env reports a potential


def test_potential_shaping_needs_an_env_with_a_potential():
    cfg = ppo_config.make_config(
        overrides={"num_envs": 2, "num_minibatches": 1, "total_env_steps": 6, "potential_shaping": 1.0}
    )
    with pytest.raises(ValueError, match="potential_shaping 1.0 needs an env that reports"):
        ppo.make_train(cfg, _CountingEnv(True))


@pytest.mark.parametrize(
    ("overrides", "named"),
    [
        ({"num_envs": 6, "num_minibatches": 4}, "num_minibatches 4"),
        ({"total_env_steps": 0}, "total_env_steps"),
        ({"total_env_steps": -5}, "total_env_steps"),
        ({"num_envs": 8, "total_env_steps": 100}, "total_env_steps 100"),
        ({"num_epochs": 0}, "num_epochs"),
        ({"learning_rate": 0.0}, "learning_rate"),
        ({"discount": 1.5}, "discount"),
        ({"policy_hidden": ()}, "policy_hidden"),
        ({"potential_shaping": -1.0}, "potential_shaping"),
    ],
)
def test_bad_ppo_config_names_the_value(overrides, named):
    cfg = ppo_config.make_config(overrides=overrides)
    with pytest.raises(ValueError, match=named):
        ppo_config.validate_config(cfg, N_STEPS)


def test_annealed_policy_rate_reaches_zero_and_spares_the_critic():
    """The policy's steps shrink linearly to nothing over the run's Adam steps; the value net's
    do not. Adam's first step has size lr per weight, so the step sizes read off the rate."""
    overrides = {"anneal_learning_rate": True, "learning_rate": 1e-3, "value_learning_rate": 1e-3}
    cfg = ppo_config.make_config(overrides=overrides)
    total = ppo_config.sgd_steps(cfg, N_STEPS)
    params = ppo.PPONetworkParams(policy={"w": jnp.ones(3)}, value={"w": jnp.ones(3)})
    grads = jax.tree_util.tree_map(jnp.ones_like, params)
    optimizer = ppo.make_optimizer(cfg, N_STEPS)

    def first_step_at(count):
        state = optimizer.init(params)
        # Move the schedule's step counter to `count` (Adam's own counter stays at 0, so its
        # first step is still lr-sized).
        is_schedule = lambda x: isinstance(x, optax.ScaleByScheduleState)  # noqa: E731
        state = jax.tree_util.tree_map(
            lambda x: x._replace(count=jnp.full_like(x.count, count)) if is_schedule(x) else x,
            state,
            is_leaf=is_schedule,
        )
        updates, _ = optimizer.update(grads, state, params)
        return float(jnp.abs(updates.policy["w"][0])), float(jnp.abs(updates.value["w"][0]))

    start, end, half = first_step_at(0), first_step_at(total), first_step_at(total // 2)
    np.testing.assert_allclose(start, (1e-3, 1e-3), rtol=1e-3)
    np.testing.assert_allclose(half[0], 0.5e-3, rtol=1e-2)
    assert end[0] == 0.0 and end[1] > 0.5e-3


def test_unknown_key_is_refused():
    with pytest.raises(ValueError, match="num_env"):
        ppo_config.make_config(overrides={"num_env": 4})


def test_ppo_improves_the_return_on_the_warp_backend():
    """PPO from a fresh policy raises the collected return on MuJoCo Warp, the backend every
    result uses: HalfCheetah-Vel at 1.5 m/s, 30 updates of 16 ten-step episodes (on a CPU each
    physics step costs the same whatever the batch). From the first three updates to the last
    three (CPU, seeds 0-3): return +3.6 to +5.3, velocity error -0.41 to -0.57 m/s. Over 10
    updates (of twenty-step episodes) the gain was within the noise (seed 3: -1.1), and a CPU of
    another kind rounds the contacts otherwise: the margins below hold for every seed tried."""
    n, steps = 30, 10
    overrides = {
        "env.impl": "warp",
        "experts.tasks": (1.5,),
        "env.episode_steps": steps,
        "experts.ppo.num_envs": 16,
        "experts.ppo.num_minibatches": 4,
        "experts.ppo.num_epochs": 4,
        "experts.ppo.total_env_steps": 16 * steps * n,
        "experts.ppo.learning_rate": 3e-3,
        "experts.updates_per_chunk": n,
        "experts.family.centre_updates": 0,  # PPO from a fresh policy
    }
    view = config.make_config("tiny", {"task": "cheetah_vel", **overrides})
    programs = expert_programs.compile_programs(view)
    assert programs.env.config.impl == "warp"
    tasks = jnp.asarray(view.experts.tasks)
    state, _ = expert_programs.run_init(programs, expert_programs.task_rngs(0, 1), tasks, np.zeros((1, 0)))
    _, metrics = expert_programs.run_chunk(programs, state, tasks)
    returns, errors = np.asarray(metrics.episode_return)[0], np.asarray(metrics.final_error)[0]
    assert np.isfinite(returns).all() and returns.shape == (n,)
    assert returns[-3:].mean() > returns[:3].mean() + 2.0
    assert errors[-3:].mean() < errors[:3].mean() - 0.15
