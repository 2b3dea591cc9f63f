"""The keyframe kick prior: key poses, the prior section's checks, the prior stage's files."""

import json

import numpy as np
import pytest

from bumps_jax import config
from bumps_jax.tasks.kick import cmaes, prior, scene
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model
from bumps_jax.tasks.kick import scoring as kick_scoring


def test_actions_shape_and_joint_limits():
    rng = np.random.default_rng(0)
    batch = rng.uniform(kick_model.PARAM_LOW, kick_model.PARAM_HIGH, size=(64, kick_model.N_PARAMS))
    extremes = [kick_model.DEFAULT_PARAMS[None], kick_model.PARAM_LOW[None], kick_model.PARAM_HIGH[None]]
    batch = np.concatenate([batch, *extremes])
    actions = np.asarray(kick_model.action_tables(batch, 75, 0.02))
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
    times = {s: np.asarray(kick_model.keyframes(np.r_[kick_model.DEFAULT_PARAMS[:-1], s])[0]) for s in (0.3, 1.0)}
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
        ("extremes.long", 40.0),
        ("start_strength", 1.5),
        ("fitness.invalid", -1.0),
        ("free_params", ("lean", "no_such_param")),
        ("sweep_strengths", (0.0, 1.5)),
    ],
)
def test_bad_config_values_raise_naming_them(key, value):
    with pytest.raises(ValueError, match=key.split(".")[0]):
        config.make_config("tiny", {f"prior.{key}": value})


def test_unknown_config_key_raises():
    with pytest.raises(ValueError, match="popsize"):
        config.make_config("tiny", {"prior.popsize": 8})


def test_load_record_refuses_other_formats(tmp_path):
    record = json.loads(kick_model.ASSET.read_text())
    record["format_version"] = 99
    path = tmp_path / "old.json"
    path.write_text(json.dumps(record))
    with pytest.raises(ValueError, match="format_version") as err:
        kick_model.load_record(path)
    assert str(path) in str(err.value)


# -- the stage, its CMA-ES runs and sweep replaced by stand-ins: the file bookkeeping alone ------


class StandIns:
    """cmaes.optimise / evaluate_kick / sweep without MJX: each optimised kick leans by its target
    (deg) to tell the anchors apart; every call is recorded."""

    def __init__(self, monkeypatch):
        self.calls = []
        monkeypatch.setattr(cmaes, "optimise", self.optimise)
        monkeypatch.setattr(kick_scoring, "evaluate_kick", self.evaluate_kick)
        monkeypatch.setattr(kick_scoring, "sweep", self.sweep)

    def optimise(self, env, start, target, free_params, cfg, csv_path=None, mesh=None, say=print, label="",
                 resume_path=None):  # fmt: skip
        self.calls.append({"target": target, "start": np.asarray(start).copy(), "free": tuple(free_params),
                           "resume_path": resume_path})  # fmt: skip
        csv_path.write_text("generation\n0\n")
        params = np.asarray(start, np.float32).copy()
        params[kick_model.PARAM_NAMES.index("lean")] = target
        return {"params": params, "best_cost": 0.5, "mean_params": params, "history": {}}

    def evaluate_kick(self, env, params, target, fitness, repetitions, seed=1, mesh=None):
        return {"repetitions": repetitions, "target": target, "mean_error": 0.5, "std_error": 0.2,
                "mean_distance": float(target), "mean_lateral": 0.0, "mean_fitness": 0.9, "valid_fraction": 1.0,
                "struck_fraction": 1.0, "fallen_fraction": 0.0}  # fmt: skip

    def sweep(self, env, anchors, strengths, target, repetitions=8, seed=2, mesh=None):
        return [{"strength": float(s), "distance_m": 6.0 + 15.0 * float(s), "distance_std_m": 0.1, "lateral_m": 0.0,
                 "valid_fraction": 1.0, "fallen_fraction": 0.0} for s in strengths]  # fmt: skip


@pytest.fixture
def asset(tmp_path, monkeypatch):
    """The committed prior copied to a tmp file that stands for assets/kick_prior.json."""
    path = tmp_path / "assets" / "kick_prior.json"
    path.parent.mkdir()
    path.write_text(kick_model.ASSET.read_text())
    monkeypatch.setattr(kick_model, "ASSET", path)
    return path


def test_the_stage_writes_the_record_later_stages_start_from(tmp_path, monkeypatch, asset):
    stand_ins, cfg, lines = StandIns(monkeypatch), config.make_config("tiny"), []
    payload = prior.run(cfg, tmp_path / "run", say=lines.append)
    out = tmp_path / "run" / "prior"
    assert json.loads((out / prior.OUTPUT).read_text()) == json.loads(json.dumps(payload))
    assert payload["env"]["physics_dt"] > 0 and payload["preset"] == "tiny" and payload["reused_anchors"] == []
    record = kick_model.load_record(out / prior.ASSET, env_cfg=kick_env.resolved(cfg.env))
    assert record["params"][kick_model.PARAM_NAMES.index("lean")] == 12.0
    np.testing.assert_array_equal(record["anchors"][:, 0], [6.0, 12.0, 21.0])  # short, main, long
    assert kick_model.calibration(record)[-1].tolist() == [1.0, 21.0]
    # The main kick starts from the asset at start_strength and moves only the free parameters;
    # the extremes start from the main kick and move every parameter.
    main, short, long = stand_ins.calls
    assert main["start"][kick_model.PARAM_NAMES.index("strength")] == cfg.prior.start_strength
    assert main["free"] == tuple(cfg.prior.free_params) and short["free"] == kick_model.PARAM_NAMES
    np.testing.assert_array_equal(short["start"], record["anchors"][1])
    assert (short["target"], long["target"]) == (6.0, 21.0)
    timing = json.loads((out / prior.TIMING).read_text())
    assert timing["env"] == payload["env"] and timing["episodes_per_optimisation"] == 3 * 8 * 2
    # What the stage cost: 3 anchors x (3 generations x 8 candidates x 2 kicks + 8 to evaluate), and
    # 9 strengths x 4 kicks of sweep; the record the experts read says so too.
    assert payload["episodes"] == record["episodes"] == prior.episodes_of(record) == 3 * (3 * 8 * 2 + 8) + 9 * 4
    del record["episodes"]  # an older record: counted from its config and sweep
    assert prior.episodes_of(record) == 3 * (3 * 8 * 2 + 8) + 9 * 4
    assert (out / prior.SWEEP_PLOT).stat().st_size > 0
    assert (out / prior.START).read_bytes() == asset.read_bytes()


def test_a_rerun_reuses_finished_anchors_and_resumes_an_unfinished_one(tmp_path, monkeypatch, asset):
    stand_ins, cfg = StandIns(monkeypatch), config.make_config("tiny")
    first = prior.run(cfg, tmp_path, say=lambda m: None)
    out = tmp_path / "prior"
    (out / "anchor_long.json").unlink()  # killed during the long kick's search: its CSV is left
    stand_ins.calls.clear()
    lines = []
    again = prior.run(cfg, tmp_path, say=lines.append)
    assert [c["target"] for c in stand_ins.calls] == [21.0]
    assert again["reused_anchors"] == ["short", "main"] and again["anchors"] == first["anchors"]
    text = "\n".join(lines)
    assert "anchor main (12 m) reused" in text and "anchor short (6 m) reused" in text
    assert stand_ins.calls[0]["resume_path"] == out / "search_long.npz"  # its search resumes from there


def test_a_rerun_starts_from_the_runs_own_start_after_the_asset_changes(tmp_path, monkeypatch, asset):
    stand_ins, cfg = StandIns(monkeypatch), config.make_config("tiny")
    prior.run(cfg, tmp_path, say=lambda m: None)
    committed = json.loads(asset.read_text())
    changed = dict(committed, params=[p + 1.0 for p in committed["params"]])
    asset.write_text(json.dumps(changed))  # assets/ gets a new prior after the first call
    for anchor in ("main", "short", "long"):
        (tmp_path / "prior" / f"anchor_{anchor}.json").unlink()
    stand_ins.calls.clear()
    assert prior.inputs(cfg, tmp_path) == {"start": tmp_path / "prior" / prior.START}
    prior.run(cfg, tmp_path, say=lambda m: None)
    expected = np.asarray(committed["params"], np.float32)
    expected[kick_model.PARAM_NAMES.index("strength")] = cfg.prior.start_strength
    np.testing.assert_array_equal(stand_ins.calls[0]["start"], expected)
    assert [c["target"] for c in stand_ins.calls] == [12.0, 6.0, 21.0]


def test_an_extreme_searched_from_another_main_kick_is_searched_again(tmp_path, monkeypatch, asset):
    stand_ins, cfg = StandIns(monkeypatch), config.make_config("tiny")
    prior.run(cfg, tmp_path, say=lambda m: None)
    main = json.loads((tmp_path / "prior" / "anchor_main.json").read_text())
    main["params"][0] += 1.0  # as if the main kick had been searched again
    (tmp_path / "prior" / "anchor_main.json").write_text(json.dumps(main))
    stand_ins.calls.clear()
    lines = []
    prior.run(cfg, tmp_path, say=lines.append)
    assert [c["target"] for c in stand_ins.calls] == [6.0, 21.0]
    assert "searched from another start" in "\n".join(lines)


def test_inputs_name_a_start_record_that_does_not_load(tmp_path):
    missing = tmp_path / "nope.json"
    with pytest.raises(ValueError, match="nope.json"):
        prior.inputs(config.make_config("tiny", {"prior.start": str(missing)}), tmp_path / "run")
    bad = tmp_path / "bad.json"
    bad.write_text('{"format_version": 1, "param_names": ["x"]}')
    with pytest.raises(ValueError, match="bad.json"):
        prior.inputs(config.make_config("tiny", {"prior.start": str(bad)}), tmp_path / "run")
