"""The multi-task PPO baseline (experiments/multitask_baseline.py) at its tiny preset."""

import json

import numpy as np
import pytest

from experiments import multitask_baseline


def test_tiny_baseline_writes_curve_for_two_seeds(tmp_path):
    payload = multitask_baseline.run(multitask_baseline.tiny_config(), tmp_path)
    saved = json.loads((tmp_path / "baseline.json").read_text())
    assert saved["seeds"] == 2
    curve = saved["curve"]
    n = len(curve["env_steps"])
    assert n == 3 and all(len(curve[k]) == n for k in ("mean", "ci_low", "ci_high"))
    assert np.all(np.asarray(curve["ci_low"]) <= np.asarray(curve["mean"]) + 1e-6)
    assert np.all(np.asarray(curve["mean"]) <= np.asarray(curve["ci_high"]) + 1e-6)
    assert curve["env_steps"][-1] == payload["env_steps"] == 3 * 8 * 75
    assert np.isfinite(saved["error_mean_m"]) and 0.0 <= saved["accuracy_mean"] <= 1.0
    assert (tmp_path / "baseline_curve.png").stat().st_size > 0
    # The clone every seed started from is evaluated on the same tasks, and its fit recorded.
    # Cloned at every context, the 12 m kick strikes whatever the target (cloned at 12 m only,
    # it did not: accuracy 0.25 here, 0.67 on the GPU).
    assert saved["start"]["accuracy_mean"] == 1.0 and saved["start"]["n_tasks"] == len(saved["eval_tasks"])
    assert 0.0 <= saved["bc_final_loss"] < 1e-3


def test_sampled_task_range_is_validated():
    cfg = multitask_baseline.tiny_config()
    cfg.ppo.sample_task_range = (18.0, 7.0)
    with pytest.raises(ValueError, match="sample_task_range"):
        multitask_baseline.run(cfg, "unused")


def test_paper_clone_fits_the_kick_with_the_deep_net():
    """The paper's 11 x 256 policy at the paper preset's BC learning rate fits the 12 m kick
    (at the experts' 1e-2 it stalled at a loss of ~0.02 rad^2 and never struck the ball)."""
    import jax
    import jax.numpy as jnp

    from bumps_jax import experts, kick_env, ppo, prior

    cfg = multitask_baseline.paper_config()
    env = kick_env.KickEnv()
    networks = ppo.make_train(cfg.ppo, env).networks
    obs, actions = experts.bc_dataset(env, 12.0, jnp.asarray(prior.load_prior()["params"]))
    policy = networks.policy_network.init(jax.random.key(0))
    _, losses = jax.jit(lambda p: experts.behaviour_clone(networks, p, obs, actions, 2000, cfg.bc_learning_rate))(
        policy
    )
    assert float(losses[-1]) < 1e-3, float(losses[-1])
