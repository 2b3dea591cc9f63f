"""The multi-task PPO baseline stage (the paper's Figure 1) at its tiny preset."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bumps_jax import config
from bumps_jax.algo import bc, evaluate, ppo
from bumps_jax.pipeline.stages import baseline
from bumps_jax.report import curves
from bumps_jax.schema import sections
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model
from bumps_jax.tasks.kick import start as kick_start


def test_tiny_baseline_writes_curve_for_two_seeds_and_two_arms(tmp_path, monkeypatch):
    # The tiny preset with two updates instead of three and three test targets instead of six: on
    # a CPU each update's and each evaluation's episodes cost seconds.
    cfg = config.make_config(
        "tiny", {"baseline.ppo.total_env_steps": 2 * 8 * 75, "baseline.eval_tasks": kick_env.meta_test_tasks()[9::50]}
    )
    scored = []  # the per-episode metrics of every policy evaluated, in order
    original = evaluate.summarise_tasks
    monkeypatch.setattr(evaluate, "summarise_tasks", lambda m: scored.append(m) or original(m))
    # Stopped after one chunk (of 1 update) as a killed run would be, then resumed to the end.
    assert baseline.run(cfg, tmp_path, say=lambda *a, **k: None, max_chunks=1) is None
    stage_dir = tmp_path / "baseline"
    assert not (stage_dir / "baseline.json").exists()
    assert sorted(p.name for p in (stage_dir / "checkpoints").iterdir()) == ["0", "1"]
    assert len((stage_dir / "progress.csv").read_text().strip().splitlines()) == 1 + 2 * 2  # 4 runs, 1 update
    said = []
    payload = baseline.run(cfg, tmp_path, say=lambda *a, **k: said.append(a[0]))
    assert any("resumed from update 1" in line for line in said)
    assert sum("baseline update" in line for line in said) == 1  # update 2, not 1 again
    rows = (stage_dir / "progress.csv").read_text().strip().splitlines()
    assert len(rows) == 1 + 2 * 2 * 2 and len(set(rows)) == len(rows)  # each (update, run) once
    saved = json.loads((stage_dir / "baseline.json").read_text())
    assert sorted(p.name for p in (stage_dir / "checkpoints").iterdir()) == ["2"]  # the trained runs only
    assert saved["seeds"] == 2 and saved["env"]["physics_dt"] == 0.0025 and saved["env"]["impl"] == "warp"
    curve = saved["curve"]
    n = len(curve["env_steps"])
    assert n == 2 and all(len(curve[k]) == n for k in ("mean", "ci_low", "ci_high"))
    assert np.all(np.asarray(curve["ci_low"]) <= np.asarray(curve["mean"]) + 1e-6)
    assert np.all(np.asarray(curve["mean"]) <= np.asarray(curve["ci_high"]) + 1e-6)
    assert curve["env_steps"][-1] == payload["env_steps"] == payload["env_steps_per_seed"] == 2 * 8 * 75
    assert np.isfinite(saved["error_mean_m"])
    # Two arms (the paper's rate first), the same seeds each, in one program: the start, then 2 x 2 runs.
    assert saved["learning_rates"] == [1e-5, 1e-4] and [a["learning_rate"] for a in saved["arms"]] == [1e-5, 1e-4]
    assert len(scored) == 1 + 2 * 2
    for i, arm in enumerate(saved["arms"]):
        assert len(arm["per_seed"]) == 2 and len(arm["error_curve"]["mean"]) == n
        band = arm["error_curve"]
        assert np.all(np.asarray(band["ci_low"]) <= np.asarray(band["mean"]) + 1e-6)
        # Each seed's accuracy is its fraction of valid kicks, its error the mean final error,
        # recomputed from the per-episode metrics of its evaluation.
        for seed, row in enumerate(arm["per_seed"]):
            m = scored[1 + 2 * i + seed]
            assert m["valid"].shape == (len(saved["eval_tasks"]), 2)
            assert row["accuracy_mean"] == pytest.approx(float(np.mean(m["valid"])))
            assert row["error_mean_all_m"] == pytest.approx(float(np.mean(m["final_error"])))
        assert arm["error_mean_m"] == pytest.approx(np.mean([r["error_mean_all_m"] for r in arm["per_seed"]]))
    assert saved["error_mean_m"] == saved["arms"][0]["error_mean_m"] and saved["curve"] == saved["arms"][0]["curve"]
    # The two arms trained differently: another rate moves the same seeds elsewhere.
    assert saved["arms"][0]["curve"]["mean"] != saved["arms"][1]["curve"]["mean"]
    assert (tmp_path / "baseline" / "baseline_curve.png").stat().st_size > 0
    # The clone every seed started from is evaluated on the same tasks, and its fit recorded.
    # Cloned at every context, the 12 m kick strikes whatever the target.
    assert saved["start"]["accuracy_mean"] == 1.0 and saved["start"]["n_tasks"] == len(saved["eval_tasks"])
    assert 0.0 <= saved["bc_final_loss"] < 1e-3


def test_extra_arm_is_validated():
    with pytest.raises(ValueError, match="baseline.extra_learning_rate 1e-05 is the paper arm's own rate"):
        config.make_config("tiny", {"baseline.extra_learning_rate": 1e-5})
    with pytest.raises(ValueError, match="baseline.extra_learning_rate must be > 0"):
        config.make_config("tiny", {"baseline.extra_learning_rate": -1.0})
    assert config.make_config("tiny", {"baseline.extra_learning_rate": None}).baseline.extra_learning_rate is None
    paper = config.make_config("paper").baseline
    assert (paper.seeds, paper.ppo.total_env_steps, paper.ppo.learning_rate) == (6, 12_000_000, 1e-6)


def test_sampled_task_range_is_validated():
    with pytest.raises(ValueError, match="baseline.ppo.sample_task_range"):
        config.make_config("tiny", {"baseline.ppo.sample_task_range": (18.0, 7.0)})
    with pytest.raises(ValueError, match="baseline.ppo.sample_task_range must be"):
        config.make_config("tiny", {"baseline.ppo.sample_task_range": None})


def test_paper_clone_fits_the_kick_with_the_deep_net():
    """The paper's 11 x 256 policy at the paper preset's BC learning rate fits the 12 m kick
    (at the experts' 1e-2 it stalled at a loss of ~0.02 rad^2 and never struck the ball)."""
    cfg = config.make_config("paper")
    env = kick_env.KickEnv(cfg.env)
    networks = ppo.make_train(cfg.baseline.ppo, env).networks
    obs, actions = kick_start.kick_dataset(env, 12.0, jnp.asarray(kick_model.load_record()["params"]))
    policy = networks.policy_network.init(jax.random.key(0))
    lr = cfg.baseline.bc_learning_rate
    # 500 steps (measured: loss 4e-4 after 200, 1.3e-4 after 500, 4.3e-5 after 2000).
    _, losses = jax.jit(lambda p: bc.clone_policy(networks, p, obs, actions, 500, lr))(policy)
    assert float(losses[-1]) < 1e-3, float(losses[-1])


def test_one_seed_has_a_curve_without_a_band(tmp_path):
    """One seed: the mean curve is that seed's, with no bootstrap band (None), and it plots."""
    curve = baseline.bootstrap_curve(np.array([[1.0, 2.0, 3.0]]), 10)
    assert curve == {"env_steps": [10, 20, 30], "mean": [1.0, 2.0, 3.0], "ci_low": None, "ci_high": None}
    payload = {"seeds": 1, "device": "cpu", "preset": "tiny", "curve": curve, "error_curve": curve, "unit": "m",
               "sample_task_range": [7.0, 18.0]}  # fmt: skip
    assert curves.baseline(payload, tmp_path / "curve.png").exists()
    assert curves.arm_label({"learning_rate": 1e-6}, 1) == "lr 1e-06, 1 seed"
    assert curves.arm_label({"learning_rate": 1e-6}, 6) == "lr 1e-06, mean over 6 seeds"


# Centre candidates whose steps buy whole compiled chunks of the baseline (else a clear error).
@pytest.mark.parametrize(("task", "candidates"), [("cheetah_vel", 3), ("ant_goal", 4)])
def test_baseline_budget_follows_the_experts_overrides(task, candidates):
    """The baseline's per-seed budget is the experts' whole (`DERIVED`), recomputed after --set:
    more centre candidates or a longer PPO move it; a budget set by hand stays as set."""
    paper = config.make_config("paper", {"task": task})
    e, steps = paper.experts, paper.env.episode_steps
    per_update = e.ppo.num_envs * steps
    # The candidates side by side until the choice, then the chosen one alone: one round's.
    m = sections.choice_update(e.family)
    centre = e.family.candidates * m + e.family.centre_updates - m
    # ... in whole updates of the baseline's batch, the nearest number of them.
    whole = lambda n: round(n / (paper.baseline.ppo.num_envs * steps)) * paper.baseline.ppo.num_envs * steps  # noqa: E731
    experts_steps = len(e.tasks) * e.ppo.total_env_steps + centre * per_update
    assert paper.baseline.ppo.total_env_steps == whole(experts_steps)
    more = config.make_config("paper", {"task": task, "experts.family.candidates": candidates})
    assert config.overrides_of(more) == {"experts.family.candidates": candidates}  # what followed it is no override
    extra = (candidates - e.family.candidates) * m * per_update
    assert more.baseline.ppo.total_env_steps == whole(experts_steps + extra)
    longer = config.make_config(
        "paper",
        {"task": task, "experts.ppo.total_env_steps": 2 * e.ppo.total_env_steps, "baseline.updates_per_chunk": 1},
    )
    assert (
        longer.baseline.ppo.total_env_steps - paper.baseline.ppo.total_env_steps == len(e.tasks) * e.ppo.total_env_steps
    )
    # The episodes of one baseline update and Warp's contact pool follow the experts' batch.
    doubled = {"experts.ppo.num_envs": 2 * e.ppo.num_envs, "experts.ppo.total_env_steps": 2 * e.ppo.total_env_steps}
    wide = config.make_config("paper", {"task": task, **doubled})
    assert wide.baseline.ppo.num_envs == 2 * paper.baseline.ppo.num_envs
    assert wide.env.warp_contacts == 2 * paper.env.warp_contacts
    one_chunk = paper.baseline.ppo.num_envs * steps * paper.baseline.updates_per_chunk
    fixed = config.make_config(
        "paper", {"task": task, "experts.family.candidates": candidates, "baseline.ppo.total_env_steps": one_chunk}
    )
    assert fixed.baseline.ppo.total_env_steps == one_chunk
    assert config.overrides_of(fixed)["baseline.ppo.total_env_steps"] == one_chunk  # set by hand: an override
