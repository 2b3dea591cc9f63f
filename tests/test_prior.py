"""The keyframe kick prior: key poses, config checks, a tiny CMA-ES run, the committed prior."""

import csv
import json

import jax
import numpy as np
import pytest

from bumps_jax import prior, scene


@pytest.fixture(scope="module")
def rollout(env):
    return prior.make_rollout(env)


def test_actions_shape_and_joint_limits():
    rng = np.random.default_rng(0)
    batch = rng.uniform(prior.PARAM_LOW, prior.PARAM_HIGH, size=(64, prior.N_PARAMS))
    batch = np.concatenate([batch, prior.DEFAULT_PARAMS[None], prior.PARAM_LOW[None], prior.PARAM_HIGH[None]])
    actions = np.asarray(jax.vmap(lambda p: prior.keyframes_to_actions(p, 75))(batch))
    assert actions.shape == (len(batch), 75, scene.N_JOINTS)
    assert np.isfinite(actions).all()
    ids = scene.scene_ids(scene.load_model())
    lo, hi = ids.joint_range[:, 0], ids.joint_range[:, 1]
    # Inside the bounds every key pose, so every interpolated target, is a reachable pose.
    assert (actions >= lo - 1e-5).all() and (actions <= hi + 1e-5).all()
    # The kick starts from the stance and, with the default timings, ends back in it.
    default = actions[-3]
    np.testing.assert_allclose(default[-1], scene.STANCE, atol=1e-6)
    assert np.abs(default[0] - scene.STANCE).max() < np.deg2rad(2.0)


def test_strength_slows_the_swing():
    times = {s: np.asarray(prior.keyframes(np.r_[prior.DEFAULT_PARAMS[:-1], s])[0]) for s in (0.3, 1.0)}
    swing = {s: t[4] - t[3] for s, t in times.items()}
    assert swing[0.3] > 2.5 * swing[1.0]


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("population_size", 1),
        ("generations", 0),
        ("repetitions", -2),
        ("sigma_init", 0.0),
        ("target", 30.0),
        ("start_strength", 1.5),
        ("fitness.invalid", -1.0),
        ("free_params", ("lean", "no_such_param")),
    ],
)
def test_bad_config_values_raise_naming_them(key, value):
    cfg = prior.make_config(None, {key: value})
    with pytest.raises(ValueError, match=key.split(".")[-1]):
        prior.validate_config(cfg)


def test_unknown_config_key_raises():
    with pytest.raises(ValueError, match="popsize"):
        prior.make_config(None, {"popsize": 8})


def test_tiny_optimisation_improves(tmp_path, env, rollout):
    # Start from a poor kick (swing too weak for 12 m) so there is something to improve.
    start = prior.load_prior()["params"]
    cfg = prior.make_config(None, {
        "population_size": 6, "generations": 4, "repetitions": 1, "eval_repetitions": 4,
        "start_strength": 0.45, "free_params": ("strength", "swing_hip", "back_knee"), "sigma_init": 1.5,
    })  # fmt: skip
    # The module's rollout: the final evaluation (one kick, 4 episodes) is then the program that
    # test_committed_prior_kicks_the_ball runs, compiled once (~40 s on a CPU). The session env
    # differs from optimise's own only in its range of admissible targets, which holds 12 m.
    record = prior.optimise(cfg, tmp_path, start=start, verbose=False, env=env, rollout=rollout)
    with open(tmp_path / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 4
    first_mean = float(rows[0]["mean_fitness"])
    assert float(rows[-1]["best_so_far"]) < first_mean
    saved = prior.load_prior(tmp_path / "kick_prior.json")
    np.testing.assert_allclose(saved["params"], record["params"], rtol=1e-6)
    assert saved["evaluation"]["repetitions"] == 4


def test_committed_prior_kicks_the_ball(env, rollout):
    record = prior.load_prior()
    assert record["params"].shape == (prior.N_PARAMS,)
    result = prior.evaluate(record["params"], record["config"], repetitions=4, env=env, rollout=rollout)
    assert result["struck_fraction"] == 1.0
    assert result["fallen_fraction"] == 0.0
    assert result["mean_distance"] > 3.0


def _stand_in_stage(monkeypatch, env):
    """`run_stage` with its CMA-ES runs and sweep replaced by stand-ins: the file bookkeeping
    alone, no MJX program compiled. Each optimised kick leans by its target (deg) to tell the
    anchors apart."""

    def optimise(cfg, out_dir, start=None, env=None, rollout=None):
        params = prior.DEFAULT_PARAMS.copy()
        params[prior.PARAM_NAMES.index("lean")] = cfg.target
        numbers = {"mean_error": 0.5, "std_error": 0.2, "mean_distance": cfg.target, "valid_fraction": 1.0,
                   "fallen_fraction": 0.0, "struck_fraction": 1.0}  # fmt: skip
        return {"params": params, "evaluation": numbers}

    def sweep(anchors, strengths, config=None, repetitions=8, env=None, rollout=None):
        return [{"strength": float(s), "distance_m": 6.0 + 15.0 * float(s), "valid_fraction": 1.0} for s in strengths]

    monkeypatch.setattr(prior, "_env_for", lambda cfg: env)
    monkeypatch.setattr(prior, "optimise", optimise)
    monkeypatch.setattr(prior, "sweep", sweep)
    monkeypatch.setattr(prior, "plot_sweep", lambda payload, path: None)


def test_run_stage_keeps_the_prior_record_it_publishes(tmp_path, monkeypatch, env):
    _stand_in_stage(monkeypatch, env)
    asset = tmp_path / "repo" / "assets" / "kick_prior.json"
    asset.parent.mkdir(parents=True)
    asset.write_text("committed")
    monkeypatch.setattr(prior, "PRIOR_JSON", asset)

    # Unpublished, the run still keeps its record: the experts stage reads it from there.
    prior.run_stage("tiny", tmp_path / "own")
    assert asset.read_text() == "committed"
    record = prior.load_prior(tmp_path / "own" / prior.RUN_PRIOR_JSON)
    assert record["params"][prior.PARAM_NAMES.index("lean")] == 12.0
    np.testing.assert_array_equal(record["anchors"][:, 0], [6.0, 12.0, 21.0])  # short, main, long
    assert prior.calibration(record)[-1].tolist() == [1.0, 21.0]

    # Published, the committed asset is that same record, byte for byte.
    prior.run_stage("tiny", tmp_path / "published", publish=True)
    assert asset.read_bytes() == (tmp_path / "published" / prior.RUN_PRIOR_JSON).read_bytes()

    # A run from before runs kept their record: the payload rebuilds what the stages read.
    rebuilt = prior.record_from_payload(json.loads((tmp_path / "own" / "kick_prior.json").read_text()))
    prior.save_prior(rebuilt, tmp_path / "rebuilt.json")
    again = prior.load_prior(tmp_path / "rebuilt.json")
    np.testing.assert_array_equal(again["params"], record["params"])
    np.testing.assert_array_equal(again["anchors"], record["anchors"])
    np.testing.assert_array_equal(prior.calibration(again), prior.calibration(record))
    assert rebuilt["config"] == json.loads((tmp_path / "own" / prior.RUN_PRIOR_JSON).read_text())["config"]


def test_load_prior_refuses_other_formats(tmp_path):
    record = json.loads(prior.PRIOR_JSON.read_text())
    record["format_version"] = 99
    path = tmp_path / "old.json"
    path.write_text(json.dumps(record))
    with pytest.raises(ValueError, match="format_version"):
        prior.load_prior(path)


def test_tuning_for_tasks_rejects_bad_inputs_before_compiling():
    starts = np.tile(prior.DEFAULT_PARAMS, (2, 1))
    with pytest.raises(ValueError, match="starts"):
        prior.tune_for_tasks([8.0, 12.0], starts[:1])
    with pytest.raises(ValueError, match="generations"):
        prior.tune_for_tasks([8.0, 12.0], starts, generations=-1)
    with pytest.raises(ValueError, match="40.0"):
        prior.tune_for_tasks([8.0, 40.0], starts)


def test_best_starts_picks_the_candidate_that_kicks_nearest(env):
    # Per target, the committed 12 m kick against the same kick at a tenth of its swing speed
    # (a few metres at most): the 12 m kick must win at 12 m, whichever order they come in.
    main = prior.load_prior()["params"]
    slow = main.copy()
    slow[prior.PARAM_NAMES.index("strength")] = 0.1
    slow[prior.PARAM_NAMES.index("t_swing")] = prior.PARAM_HIGH[prior.PARAM_NAMES.index("t_swing")]
    candidates = np.stack([[slow, main], [main, slow]])
    params, index, costs = prior.best_starts([12.0, 12.0], candidates, repetitions=2, env=env)
    assert index.tolist() == [1, 0] and costs.shape == (2, 2)
    np.testing.assert_allclose(params, np.stack([main, main]), atol=1e-6)
    assert costs[0, 1] < costs[0, 0] and costs[1, 0] < costs[1, 1]


def test_best_starts_rejects_bad_inputs_before_compiling():
    candidates = np.tile(prior.DEFAULT_PARAMS, (2, 3, 1))
    with pytest.raises(ValueError, match="candidates"):
        prior.best_starts([8.0, 12.0], candidates[0])
    with pytest.raises(ValueError, match="repetitions"):
        prior.best_starts([8.0, 12.0], candidates, repetitions=0)
    with pytest.raises(ValueError, match="40.0"):
        prior.best_starts([8.0, 40.0], candidates)
