"""The Brax comparison (experiments/compare_brax_ppo.py), halfcheetah mode: Brax's published
settings reach Brax through our PPO section unchanged, the gpu preset is a valid run of about
Brax's published update, bad settings fail before anything compiles, checkpoints are scored back
to the right trainer, seed and step, and the record's verdict. The run in parts: its smoke preset
(Brax's `fast` env, 2 seeds) stopped after every part and rerun gives the record of a run in one
call, a rerun with every part saved trains nothing, parts of another setting are refused by name.
The real env (`--env halfcheetah`) compiles for minutes on a CPU: it is run by hand, not here."""

import contextlib
import inspect
import io

import jax
import numpy as np
import pytest
from brax.training.agents.ppo import train as brax_ppo

from bumps_jax import runio
from experiments import brax_compat
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
    run, (env, length, scored) = cmp.PRESETS["gpu"], cmp.PRESET_ENV["gpu"]
    assert env == "halfcheetah" and length == scored == cmp.EPISODE_LENGTH
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


def test_the_gpu_10m_preset_trains_4x_longer_on_short_episodes_and_scores_whole_ones():
    run, (env, length, scored) = cmp.PRESETS["gpu_10m"], cmp.PRESET_ENV["gpu_10m"]
    assert env == "halfcheetah" and length == 100 and scored == cmp.EPISODE_LENGTH
    cfg = cmp.check_cheetah_run(run["num_envs"], run["num_minibatches"], run["env_steps"], run["eval_every"], length)
    assert run["env_steps"] == 4 * cmp.PRESETS["gpu"]["env_steps"]
    assert (
        cfg.num_minibatches == cmp.BRAX_HALFCHEETAH["num_minibatches"]
        and run["env_steps"] // run["num_envs"] // 100 == 50
    )


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
    # Welch's t by hand: means 4 and 3, variances (ddof 1) 19 and 0.25 over 3 seeds each.
    t = (4.0 - 3.0) / np.sqrt(19.0 / 3 + 0.25 / 3)
    assert one_way["welch_t"] == pytest.approx(t) and 0.5 < one_way["welch_p"] < 1.0
    assert cmp.spread_check([1.0], [2.0, 3.0])["welch_t"] is None


def test_seeds_other_than_the_default_name_the_record():
    assert cmp.seeds_suffix([0, 1, 2]) == ""
    assert cmp.seeds_suffix(range(6)) == "_seeds0-5"
    assert cmp.seeds_suffix([1, 4, 7]) == "_seeds1_4_7"


# -- the halfcheetah comparison in parts (`--stop-after-s`, the parts directory) ---------------

SMOKE = ["--mode", "halfcheetah", "--preset", "smoke", "--seeds", "0", "1"]
PARTS = "compare_brax_ppo_fast_smoke_seeds0-1_parts"


def _main(args) -> tuple[dict | None, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        record = cmp.main(args)
    return record, out.getvalue()


@pytest.fixture(scope="module")
def jax_cache(tmp_path_factory):
    """One compilation cache (JAX_COMPILATION_CACHE_DIR) for the module's runs of the smoke
    comparison, as a user's would be: a run's programs compile once."""
    return tmp_path_factory.mktemp("jax_cache")


@pytest.fixture(scope="module")
def smoke_runs(tmp_path_factory, jax_cache):
    """The smoke comparison (Brax's `fast` env, 2 seeds) run whole, and run again one part a call
    (`--stop-after-s 0`): 3 parts, 3 calls. One compilation cache for all, as a user's would be."""
    root = tmp_path_factory.mktemp("compare")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("JAX_COMPILATION_CACHE_DIR", str(jax_cache))
        whole, _ = _main([*SMOKE, "--out-dir", str(root / "whole")])
        calls, parted = [], [*SMOKE, "--out-dir", str(root / "parted"), "--stop-after-s", "0"]
        for _ in range(3):
            record, said = _main(parted)
            parts = sorted(p.name for p in (root / "parted" / PARTS).glob("*.npz"))
            calls.append({"record": record, "said": said, "parts": parts})
    in_parts = (root / "parted" / PARTS / "jax_cache").exists()
    cache = {"env var's": any(jax_cache.iterdir()), "parts'": in_parts}
    return {"whole": whole, "calls": calls, "parted": parted, "parts_dir": root / "parted" / PARTS, "cache": cache}


def _same_result(a: dict, b: dict) -> None:
    for arm in ("ours", "brax"):
        assert a[arm]["env_steps"] == b[arm]["env_steps"] == [0, 400, 800]
        assert a[arm]["eval_return"] == b[arm]["eval_return"], arm
    assert a["ours"]["training_return"] == b["ours"]["training_return"]


def test_a_run_stopped_between_parts_and_rerun_writes_the_record_of_a_whole_run(smoke_runs):
    first, second, third = smoke_runs["calls"]
    assert first["record"] is None and first["parts"] == ["ours.npz"]
    assert "left brax_seed0, brax_seed1 and the scoring" in first["said"]
    assert "rerun the same command" in first["said"]
    assert second["record"] is None and second["parts"] == ["brax_seed0.npz", "ours.npz"]
    assert "ours: done in an earlier call" in second["said"] and "ours: 2 seeds" not in second["said"]
    record = third["record"]
    assert third["parts"] == ["brax_seed0.npz", "brax_seed1.npz", "ours.npz"]
    assert "brax: seed 1" in third["said"] and "brax: seed 0" not in third["said"]
    _same_result(record, smoke_runs["whole"])
    assert np.asarray(record["brax"]["eval_return"]).shape == (2, 3)  # seeds x checkpoints
    assert set(record["parts"]) == {"ours", "brax_seed0", "brax_seed1"}
    assert record["brax"]["wall_s"] == [record["parts"][f"brax_seed{s}"]["wall_s"] for s in (0, 1)]
    # The compiled programs went where JAX_COMPILATION_CACHE_DIR says, not into the parts directory.
    assert smoke_runs["cache"] == {"env var's": True, "parts'": False}


def test_a_rerun_with_every_part_saved_trains_nothing_and_writes_the_same_record(smoke_runs, monkeypatch):
    def no_training(*args, **kwargs):
        raise AssertionError("a saved part was trained again")

    monkeypatch.setattr(cmp, "run_ours_cheetah", no_training)
    monkeypatch.setattr(cmp, "run_brax_cheetah", no_training)
    record, said = _main(smoke_runs["parted"])
    for name in ("ours", "brax_seed0", "brax_seed1"):
        assert f"{name}: done in an earlier call" in said
    _same_result(record, smoke_runs["calls"][-1]["record"])
    assert record["parts"] == smoke_runs["calls"][-1]["record"]["parts"]


def test_saved_parts_are_scored_on_episodes_of_the_scoring_length(smoke_runs, monkeypatch):
    def no_training(*args, **kwargs):
        raise AssertionError("a saved part was trained again")

    monkeypatch.setattr(cmp, "run_ours_cheetah", no_training)
    monkeypatch.setattr(cmp, "run_brax_cheetah", no_training)
    parts_dir = smoke_runs["parts_dir"]
    smoke = cmp.PRESETS["smoke"]
    sizes = [smoke[k] for k in ("env_steps", "num_envs", "num_minibatches", "eval_every")]
    quiet = dict(say=lambda *a, **k: None, env_name="fast", preset="smoke")
    record = cmp.compare_cheetah(*sizes, parts_dir, seeds=(0, 1), eval_episodes=smoke["eval_episodes"],
                                 episode_length=100, eval_episode_length=300, **quiet)  # fmt: skip
    trained_on = smoke_runs["calls"][-1]["record"]
    assert record["eval_episode_length"] == 300 and record["env"]["episode_length"] == 100
    assert trained_on["eval_episode_length"] == 100
    for arm in ("ours", "brax"):  # the same checkpoints, scored over 3x the steps
        assert not np.allclose(record[arm]["eval_return"], trained_on[arm]["eval_return"]), arm


@pytest.mark.parametrize(
    ("change", "named"),
    [
        (["--eval-every", "2"], "eval_every 1 there, 2 here"),
        (["--num-minibatches", "4"], "ppo.num_minibatches 2 there, 4 here"),
        # Other seeds name another record, so only a parts directory given by hand can meet them.
        (["--seeds", "0", "2", "--parts-dir", "{parts}"], "seeds [0, 1] there, [0, 2] here"),
    ],
)
def test_parts_of_another_setting_are_refused_naming_it(smoke_runs, capsys, change, named):
    with pytest.raises(SystemExit):
        cmp.main([*smoke_runs["parted"], *(arg.format(parts=smoke_runs["parts_dir"]) for arg in change)])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert named in err and f"{PARTS} holds the parts of another run" in err
    assert err.count(" there, ") == 1  # only the setting that differs


def test_a_part_round_trips_and_one_of_other_networks_is_refused(tmp_path):
    cfg = cmp.cheetah_ppo_config(4, 2, 800)
    env = cmp.TimeLimited(cmp.make_brax_env("fast"), 100)
    treedef = cmp.checkpoint_treedef(cfg, env)
    leaves = [np.full((2, 3), float(i), np.float32) for i in range(treedef.num_leaves)]
    checkpoints = [jax.tree_util.tree_unflatten(treedef, [x + k for x in leaves]) for k in range(3)]
    path = cmp.save_part(tmp_path / "ours.npz", {"checkpoints": checkpoints, "env_steps": [0, 1, 2], "wall_s": 1.5})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ours.npz"]  # no temp file left
    run = cmp.load_part(path, treedef)
    assert run["env_steps"] == [0, 1, 2] and run["wall_s"] == 1.5
    assert cmp.part_meta(path)["wall_s"] == 1.5
    for saved, loaded in zip(checkpoints, run["checkpoints"], strict=True):
        assert jax.tree_util.tree_structure(loaded) == treedef
        for a, b in zip(jax.tree_util.tree_leaves(saved), jax.tree_util.tree_leaves(loaded), strict=True):
            np.testing.assert_array_equal(a, b)
            assert a.dtype == b.dtype
    # A later call builds the structure anew: the same one.
    again = cmp.checkpoint_treedef(cmp.cheetah_ppo_config(4, 2, 800), cmp.TimeLimited(cmp.make_brax_env("fast"), 100))
    assert again == treedef
    wider = cfg.copy_and_resolve_references()
    with wider.unlocked():
        wider.policy_hidden = (32,) * 5
    with pytest.raises(ValueError, match="not trees of this run's networks"):
        cmp.load_part(path, cmp.checkpoint_treedef(wider, env))


def test_stop_before_next_weighs_the_longest_part_against_the_budget():
    assert not cmp.stop_before_next(500.0, [231.0, 265.0], None)  # no budget: never
    assert cmp.stop_before_next(240.0, [231.0], 420.0)  # 240 + 231 > 420
    assert not cmp.stop_before_next(100.0, [231.0, 30.0], 420.0)  # 100 + 231 <= 420
    assert cmp.stop_before_next(190.0, [231.0, 30.0], 420.0)  # the longest, not the last
    assert cmp.stop_before_next(1.0, [0.5], 0.0)  # 0: one part a call


# -- Brax's resets (`--brax-resets`) -------------------------------------------------------------


class _KeyedFast:
    """Brax's `fast` env whose reset hands every key it is given to the host (`seen`)."""

    def __init__(self):
        self.env, self.seen = cmp.make_brax_env("fast"), []

    def __getattr__(self, name):
        return getattr(self.env, name)

    def reset(self, rng):
        jax.debug.callback(lambda key: self.seen.append(tuple(np.asarray(key).ravel())), rng)
        return self.env.reset(rng)


def _starts(mode: str, num_envs: int, updates: int) -> set:
    """The reset keys Brax's training run of `mode` used (`--brax-resets`), `updates` updates of `num_envs`."""
    cfg = cmp.check_cheetah_run(num_envs, 2, num_envs * 100 * updates, updates, 100)
    raw = _KeyedFast()
    run = cmp.run_brax_cheetah(cfg, cmp.TimeLimited(raw, 100), raw, 0, updates, lambda *a: None, mode)
    assert run["env_steps"] == [0, num_envs * 100 * updates]
    return set(raw.seen)


def test_brax_starts_every_update_from_fresh_resets_only_when_asked():
    num_envs, updates = 4, 3
    first, fresh = _starts("first", num_envs, updates), _starts("fresh", num_envs, updates)
    # first: the num_envs start states of the first reset, restarted by Brax's AutoResetWrapper for
    # the whole run; fresh: those and new ones after every update (the last update's unused). Both
    # also reset the one env of Brax's evaluator once, built though it does not run.
    assert first <= fresh
    assert len(fresh - first) == num_envs * updates
    assert len(first) == num_envs + 1


def test_the_resets_choice_names_its_record_its_parts_and_its_difference(tmp_path, capsys, monkeypatch, jax_cache):
    # The user's compilation cache: the part this call trains (ours, which the resets leave as it
    # is) loads its programs from the smoke runs' where they ran before.
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(jax_cache))
    args = [*SMOKE, "--brax-resets", "fresh", "--out-dir", str(tmp_path), "--stop-after-s", "0"]
    record, said = _main(args)
    assert record is None and "left brax_seed0" in said
    parts = tmp_path / "compare_brax_ppo_fast_smoke_fresh_resets_seeds0-1_parts"
    manifest = runio.read_json(parts / "manifest.json", "")
    assert manifest["settings"]["brax_resets"] == "fresh"
    assert cmp.differences("fresh")[-1].startswith("resets: matched")
    with pytest.raises(SystemExit):
        cmp.main([*SMOKE, "--brax-resets", "never"])
    assert "--brax-resets: invalid choice: 'never'" in capsys.readouterr().err
