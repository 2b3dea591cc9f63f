"""The Brax comparison (experiments/compare_brax_ppo.py), halfcheetah mode: Brax's published
settings reach Brax through our PPO section unchanged, the gpu preset is a valid run of about
Brax's published update, bad settings fail before anything compiles, checkpoints are scored back
to the right trainer, seed and step, and the record's verdict. The run itself compiles programs
for half a minute or more on a CPU: its smoke preset (`--preset smoke`) is run by hand, not here."""

import inspect

import numpy as np
import pytest
from brax.training.agents.ppo import train as brax_ppo

from bumps_jax import brax_compat, runio
from experiments import compare_brax_ppo as cmp


class _WholeEpisodes:
    n_steps = cmp.EPISODE_LENGTH


def test_brax_gets_its_published_halfcheetah_settings_through_ours():
    cfg = cmp.cheetah_ppo_config(256, 32, 256 * 1000 * 4)
    kw = brax_compat.train_kwargs(cfg, _WholeEpisodes())
    published = cmp.BRAX_HALFCHEETAH
    for key in ("learning_rate", "entropy_cost", "discounting", "reward_scaling", "num_updates_per_batch"):
        assert kw[key] == pytest.approx(published[key]), key
    assert kw["normalize_observations"] is published["normalize_observations"] is True
    # What the notebook leaves out: ppo.train's own defaults.
    defaults = inspect.signature(brax_ppo.train).parameters
    for key in ("gae_lambda", "clipping_epsilon", "vf_loss_coefficient"):
        assert kw[key] == defaults[key].default, key
    assert cfg.normalize_advantage is defaults["normalize_advantage"].default is True  # Brax is left at its own
    # Whole episodes, as ours: one unroll of one episode per env and update.
    assert kw["unroll_length"] == kw["episode_length"] == published["episode_length"]
    assert kw["batch_size"] * kw["num_minibatches"] == kw["num_envs"] == 256
    assert cfg.value_learning_rate == cfg.learning_rate  # Brax: one Adam for both networks
    assert cfg.policy_hidden == (32,) * 4 and cfg.value_hidden == (256,) * 5


def test_the_gpu_preset_is_a_valid_run_of_about_brax_s_published_update():
    run, (env, length) = cmp.PRESETS["gpu"], cmp.PRESET_ENV["gpu"]
    assert env == "halfcheetah" and length == cmp.EPISODE_LENGTH
    cfg = cmp.check_cheetah_run(run["num_envs"], run["num_minibatches"], run["env_steps"], run["eval_every"], length)
    b = cmp.BRAX_HALFCHEETAH
    published_update = b["num_envs"] * b["unroll_length"] * b["batch_size"] * b["num_minibatches"] // b["num_envs"]
    assert published_update == 327_680
    update = cfg.num_envs * length
    assert abs(update / published_update - 1) < 0.05
    assert cfg.num_minibatches == b["num_minibatches"] and cfg.num_epochs == b["num_updates_per_batch"]
    assert run["env_steps"] // update >= 8  # enough updates for a curve
    smoke = cmp.PRESETS["smoke"]
    cmp.check_cheetah_run(smoke["num_envs"], smoke["num_minibatches"], smoke["env_steps"], smoke["eval_every"], 100)


@pytest.mark.parametrize(
    ("settings", "named"),
    [
        ((4, 2, 4 * 100 * 3, 2, 100), "multiple of num_envs"),  # 3 updates do not split into evals of 2
        ((6, 4, 6 * 100 * 2, 1, 100), "num_minibatches 4"),
        ((4, 2, 100, 1, 100), "total_env_steps 100"),
    ],
)
def test_bad_run_settings_name_the_value(settings, named):
    with pytest.raises(ValueError, match=named):
        cmp.check_cheetah_run(*settings)


def test_main_refuses_bad_settings_before_running(capsys):
    with pytest.raises(SystemExit):
        cmp.main(["--mode", "halfcheetah", "--preset", "smoke", "--env-steps", "7"])
    assert "total_env_steps 7" in capsys.readouterr().err


def test_every_checkpoint_is_scored_back_to_its_trainer_seed_and_step():
    seeds, evals = 3, 4

    def code(trainer, seed, k):
        return 100 * trainer + 10 * seed + k

    # Ours: per eval, one tree with a leading seed axis; Brax: per seed, per eval, one tree.
    ours = [{"w": np.array([code(1, s, k) for s in range(seeds)], float)} for k in range(evals)]
    brax = [[{"w": np.array(code(2, s, k), float)} for k in range(evals)] for s in range(seeds)]

    def evaluate(normalizers, policies):  # (P,) policies -> (P, 5) returns: each its own code
        assert normalizers["w"].shape == (2 * seeds * evals,)
        return np.repeat(policies["w"][:, None], 5, axis=1)

    ours_curves, brax_curves = cmp.score_checkpoints(
        evaluate, [(t, t) for t in ours], [[(t, t) for t in r] for r in brax]
    )
    expected = np.array([[code(0, s, k) for k in range(evals)] for s in range(seeds)])
    np.testing.assert_array_equal(ours_curves, expected + 100)
    np.testing.assert_array_equal(brax_curves, expected + 200)


def test_the_record_holds_both_curves_the_spread_and_the_verdict(tmp_path):
    steps = [0, 640_000, 1_280_000]
    ours = [[0.0, 300.0, 900.0], [0.0, 250.0, 1100.0], [0.0, 280.0, 1000.0]]
    brax = [[0.0, 310.0, 950.0], [0.0, 200.0, 1200.0], [0.0, 260.0, 800.0]]
    rec = cmp.comparison_record(steps, ours, brax)
    assert rec["ours"]["env_steps"] == rec["brax"]["env_steps"] == steps
    assert rec["ours"]["eval_return"] == ours and rec["brax"]["eval_return"] == brax
    assert rec["ours"]["final_return"] == [900.0, 1100.0, 1000.0]
    assert rec["ours"]["final_return_mean"] == pytest.approx(1000.0)
    assert rec["ours"]["final_return_std"] == pytest.approx(np.std([900, 1100, 1000]))
    assert rec["brax"]["final_return_range"] == [800.0, 1200.0]
    assert rec["final_return_gap"] == pytest.approx(1000.0 - (950.0 + 1200.0 + 800.0) / 3)
    assert rec["within_each_others_spread"]  # 1000 in [800, 1200], 983.3 in [900, 1100]
    # One seed of Brax far ahead: its mean leaves our range, ours stays in its.
    brax[2][-1] = 2500.0
    apart = cmp.comparison_record(steps, ours, brax)
    assert apart["ours_mean_in_brax_range"] and not apart["brax_mean_in_ours_range"]
    assert not apart["within_each_others_spread"]
    # It goes through the experiments' writer as strict JSON, and the figure draws both curves.
    record = {"env_name": "halfcheetah", "device": "cpu", **rec}
    path = runio.write_experiment(tmp_path, "compare_brax_ppo_halfcheetah", record)
    assert path.name == "compare_brax_ppo_halfcheetah_cpu.json"  # the tests run on the CPU
    assert runio.read_json(path)["brax"] == rec["brax"]  # a copy: the later edit of `brax` left it as it was
    figure = cmp.plot_cheetah(record, path.with_suffix(".png"))
    assert figure.stat().st_size > 1000


def test_spread_check_asks_both_ways():
    assert cmp.spread_check([1.0, 2.0, 3.0], [1.5, 2.5, 2.0])["within_each_others_spread"]
    one_way = cmp.spread_check([1.0, 2.0, 9.0], [2.5, 3.0, 3.5])  # ours' mean 4 is above Brax's seeds
    assert not one_way["ours_mean_in_brax_range"] and one_way["brax_mean_in_ours_range"]
    assert not one_way["within_each_others_spread"]
