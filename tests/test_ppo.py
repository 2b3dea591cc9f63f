"""The PPO trainer: GAE by hand, config errors, a tiny run that learns (vmapped = alone and
resuming are in test_experts.py, which shares their compiled programs)."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from bumps_jax import config, kick_model, ppo
from bumps_jax.stages import experts

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
    ],
)
def test_bad_ppo_config_names_the_value(overrides, named):
    cfg = ppo.make_config(overrides=overrides)
    with pytest.raises(ValueError, match=named):
        ppo.validate_config(cfg, N_STEPS)


def test_annealed_policy_rate_reaches_zero_and_spares_the_critic():
    """The policy's steps shrink linearly to nothing over the run's Adam steps; the value net's
    do not. Adam's first step has size lr per weight, so the step sizes read off the rate."""
    cfg = ppo.make_config(overrides={"anneal_learning_rate": True, "learning_rate": 1e-3, "value_learning_rate": 1e-3})
    total = ppo.sgd_steps(cfg, N_STEPS)
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
        ppo.make_config(overrides={"num_env": 4})


NO_NOISE = {f"noise.{k}": 0.0 for k in ("ball_xy", "joint_angle", "friction", "actuator_gain")}


def test_tiny_ppo_improves_return():
    """A short PPO run from the behaviour-cloned prior raises the return it optimises: that of
    its own (stochastic) policy, on the episodes it collects.

    Noise-free env; target 16 m with the 12 m prior kick cloned (3.8 m short). Measured with the
    prior in tests/data (an earlier committed one, frozen here: the outcome depends on the kick,
    and the committed asset changes with each paper run; CPU, 16 episodes per update, lr 1e-5,
    sigma 0.018 rad): the collected
    return rises over the first updates (-158.6, -156.1, -155.3, -151.7 with the 2.5 ms physics
    step; -156.7, -154.0, -154.5, -152.1 with 5 ms). With 5 ms the deterministic mean kick did
    not follow (-156.1 -> -157.4 after 4 updates), and at this step size longer runs fell back
    (-172 at update 5): the kick's outcome is that sensitive to its trajectory.
    So the test checks the stochastic return over 4 updates, not the deterministic one.
    """
    n_updates = 4
    cfg = config.make_config(
        "tiny",
        {
            **{f"env.{k}": v for k, v in NO_NOISE.items()},
            # The physics these numbers were measured on, with the frozen prior made on it: a test
            # of the trainer on a fixed problem. (On Warp the same 4 updates left the collected
            # return flat at lr 1e-5 to 1e-4: -158.9 -> -158.4.)
            "env.impl": "jax",
            "env.solver_iterations": None,
            "experts.tasks": (16.0,),
            "experts.bc.per_task_strength": False,  # the one 12 m kick, ~4 m short of 16 m
            "experts.ppo.num_envs": 16,
            "experts.ppo.num_minibatches": 4,
            "experts.ppo.num_epochs": 4,
            "experts.ppo.total_env_steps": 16 * N_STEPS * n_updates,
            "experts.ppo.learning_rate": 1e-5,
            "experts.updates_per_chunk": n_updates,
            "experts.tune.generations": 0,
        },
    )
    programs = experts.compile_programs(cfg)
    frozen = kick_model.load_record(Path(__file__).parent / "data" / "kick_prior_h200.json")
    kicks, _ = experts.starting_kicks(cfg, frozen, say=lambda *a, **k: None)
    tasks = jnp.asarray(cfg.experts.tasks)
    state, _ = experts.run_init(programs, experts.task_rngs(cfg.experts.seed, 1), tasks, kicks)
    _, metrics = experts.run_chunk(programs, state, tasks)
    returns = np.asarray(metrics.episode_return[0])  # (updates,), each collected before its update
    print(f"collected returns per update {returns.round(2).tolist()}")
    assert returns[2:].mean() > returns[0] + 1.0
