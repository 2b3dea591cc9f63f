"""One family of experts (a centre expert first, every expert continued from it), the family
check, closed-loop cloning (DART noise, clipped labels), headlines over seeds and the
env-step table."""

import json
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bumps_jax import config
from bumps_jax.algo import evaluate, ppo, rollout
from bumps_jax.pipeline import family
from bumps_jax.pipeline import runner as pipeline
from bumps_jax.pipeline.stages import meta as meta_stage
from bumps_jax.report import budgets, readme, seeds
from bumps_jax.tasks.cheetah_vel import env as cheetah_env


def test_the_centre_is_the_context_nearest_the_mean_and_targets_ramp_out_from_it():
    assert family.family_centre([0.0, 0.5, 1.0, 1.5, 3.0]) == 2  # mean 1.2
    assert family.family_centre([[1.0, 1.0], [0.1, 0.0], [-1.0, -1.0]]) == 1
    tasks = np.array([0.0, 1.0, 3.0])
    # Chunks of 10 updates, a ramp of 30: a third of the way after the first chunk, all of it from the third on.
    np.testing.assert_allclose(family.ramped_targets(tasks, 1, 0, 10, 30), [2 / 3, 1.0, 5 / 3])
    np.testing.assert_allclose(family.ramped_targets(tasks, 1, 20, 10, 30), tasks)
    np.testing.assert_allclose(family.ramped_targets(tasks, 1, 0, 10, 0), tasks)  # no ramp


def test_every_expert_starts_as_the_centre_with_its_own_rng_and_no_updates():
    centre = ppo.TrainState(
        params={"w": jnp.arange(3.0)[None]}, opt_state={"m": jnp.ones((1, 3))}, normalizer={"n": jnp.full((1,), 7.0)},
        rng=jax.random.split(jax.random.PRNGKey(0), 1), update=jnp.array([40]), env_steps=jnp.array([4000]),
    )  # fmt: skip
    rngs = jax.random.split(jax.random.PRNGKey(1), 4)
    state = family.family_state(centre, rngs)
    np.testing.assert_array_equal(state.params["w"], np.tile(np.arange(3.0), (4, 1)))
    np.testing.assert_array_equal(state.opt_state["m"], np.ones((4, 3)))
    np.testing.assert_array_equal(state.normalizer["n"], np.full(4, 7.0))
    np.testing.assert_array_equal(state.rng, rngs)
    assert state.update.tolist() == [0] * 4 and state.env_steps.tolist() == [0] * 4


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"experts.family.centre_updates": 3}, "must be a multiple of experts.updates_per_chunk"),
        ({"experts.family.ramp_updates": -1}, "experts.family.ramp_updates must be an integer >= 0, got -1"),
        ({"experts.family.candidates": 0}, "experts.family.candidates must be an integer >= 1, got 0"),
        ({"experts.family.rounds": 0}, "experts.family.rounds must be an integer >= 1, got 0"),
        (
            {"experts.family.choose_after": 4},
            r"choose_after must be an integer in \[0, experts.family.centre_updates 2\], got 4",
        ),
        (
            {"experts.family.choose_after": 1},
            "experts.family.choose_after 1 must be a multiple of experts.updates_per_chunk 2",
        ),
        ({"meta.dataset.action_noise": -0.1}, "meta.dataset.action_noise must be a finite std >= 0, got -0.1"),
    ],
)
def test_bad_family_and_cloning_settings_are_named(overrides, message):
    base = {"task": "cheetah_vel", "experts.updates_per_chunk": 2, "experts.family.centre_updates": 2,
            "experts.family.choose_after": 0}  # fmt: skip
    with pytest.raises(ValueError, match=message):
        config.make_config("tiny", {**base, **overrides})


def test_the_family_check_reads_postures_and_neighbours_errors():
    env = object.__new__(cheetah_env.CheetahVelEnv)  # posture and error_against read no model
    qpos = np.zeros((3, 2, 4, 9))
    qpos[1, :, :, cheetah_env.ROOT_PITCH_QPOS] = np.pi  # the second expert runs on its back
    posture = {k: v.mean(axis=1) for k, v in env.posture(qpos).items()}
    assert posture["flipped_fraction"].tolist() == [0.0, 1.0, 0.0]
    vels = np.stack([np.full((2, 5), v) for v in (0.5, 1.0, 2.0)])  # (E=3, R=2, steps): each expert's speed
    metrics = {"forward_vels": vels, "valid": np.ones((3, 2)), "final_error": np.zeros((3, 2)),
               "mean_forward_vel": vels.mean(axis=-1)}  # fmt: skip
    check = evaluate.family_check(env, [0.5, 1.0, 2.0], metrics, posture)
    assert check["flipped_experts"] == 1 and check["achieved_rises"] is True
    first = check["per_task"][0]
    assert first["neighbours_m"] == [1.0, 2.0] and first["error_at_neighbours_m"] == pytest.approx([0.5, 1.5])
    assert "| 1 | 1 | 0.000 | 0.5: 0.50, 2: 1.00 | 3.14 | 1.00 | 0.00 |" in evaluate.family_table(check, "m/s")


class DriftState(NamedTuple):
    obs: jax.Array
    reward: jax.Array
    metrics: dict


class Drift:
    """A stand-in env whose state is a position that each action moves: what `rollout.episode_fn` needs."""

    n_steps = 5
    ACTION_BOUND = 1.0

    def reset(self, key, target):
        return DriftState(jnp.zeros(2), jnp.zeros(()), {"final_error": jnp.zeros(())})

    def step(self, state, action):
        obs = state.obs + action
        return DriftState(obs, -jnp.abs(obs).sum(), {"final_error": jnp.abs(obs).sum()})

    def with_context(self, obs, context):
        return jnp.concatenate([obs, jnp.atleast_1d(context)])


def test_dart_episodes_act_with_noise_but_record_the_policys_own_action():
    env = Drift()

    def policy(params, obs):
        return params * jnp.ones(2)

    clean = rollout.episode_fn(env, policy, "trajectory")
    noisy = rollout.episode_fn(env, policy, "trajectory", action_noise=0.5)
    _, (obs_clean, act_clean) = clean(0.3, 1.0, 1.0, jax.random.key(0))
    _, (obs_noisy, act_noisy) = noisy(0.3, 1.0, 1.0, jax.random.key(0))
    np.testing.assert_allclose(act_noisy, 0.3)  # the labels: the policy's action, not the one executed
    np.testing.assert_allclose(act_clean, 0.3)
    np.testing.assert_allclose(obs_clean[:, :2], 0.3 * np.arange(5)[:, None] * np.ones(2), rtol=1e-6)
    assert not np.allclose(obs_clean[1:], obs_noisy[1:])  # the states the noise led to
    np.testing.assert_allclose(obs_clean[0], obs_noisy[0])  # the same reset
    np.testing.assert_allclose(meta_stage.clipped(env, np.array([[-3.0, 0.5]]), True), [[-1.0, 0.5]])
    np.testing.assert_allclose(meta_stage.clipped(env, np.array([[-3.0, 0.5]]), False), [[-3.0, 0.5]])


def record(task, experts_err, meta_err, filtered_err, env=None, flipped=0):
    env = env or {"impl": "warp", "physics_dt": None, "episode_steps": 10}
    return {
        "experts/experts.json": {"error_mean_all_m": experts_err, "tasks_m": [1.0, 2.0],
                                 "family_check": {"flipped_experts": flipped}},
        "meta/table1.json": {"rows": {"experts": {}, "meta_4x256": {"error_mean_all_m": meta_err}},
                             "cloning": {"variant": "plain"}},
        "filter/table2.json": {"rows": {"filtered_4x256": {"error_mean_m": filtered_err}}, "task": task, "unit": "m/s",
                               "env": env, "device": "GPU", "versions": {}, "preset": "paper"},
    }  # fmt: skip


def write_run(path, files, seed):
    for rel, data in files.items():
        (path / rel).parent.mkdir(parents=True, exist_ok=True)
        (path / rel).write_text(json.dumps(data))
    (path / "pipeline.json").write_text(json.dumps({"overrides": {"experts.seed": seed}, "wall_s": 10.0}))


def test_headlines_over_seeds_are_means_with_every_seed_kept(tmp_path):
    write_run(tmp_path / "s0", record("cheetah_vel", 0.4, 0.3, 0.2), 0)
    write_run(tmp_path / "s1", record("cheetah_vel", 0.6, 0.5, 0.4, flipped=11), 1)
    out = seeds.seeds_record([tmp_path / "s0", tmp_path / "s1"], "publish")
    assert out["n_seeds"] == 2 and out["wall_s"] == 20.0 and out["device"] == "GPU"
    row = out["rows"]["meta_4x256"]
    assert row["per_seed"] == pytest.approx([0.3, 0.5])
    assert [row[k] for k in ("mean", "std", "min", "max")] == pytest.approx([0.4, 0.1, 0.3, 0.5])
    assert [r["seeds"]["experts.seed"] for r in out["runs"]] == [0, 1]
    assert [r["flipped_experts"] for r in out["runs"]] == [0, 11]
    write_run(tmp_path / "s2", record("cheetah_vel", 0.6, 0.5, 0.4, env={"impl": "jax", "physics_dt": None}), 2)
    with pytest.raises(ValueError, match="another env config"):
        seeds.seeds_record([tmp_path / "s0", tmp_path / "s2"], "publish")


def test_returns_over_seeds_where_every_run_keeps_them(tmp_path):
    for i, (ret, meta_ret) in enumerate([(-100.0, -300.0), (-200.0, None)]):
        files = record("ant_goal", 1.0 + i, 1.5, 1.2)
        files["filter/table2.json"]["rows"]["filtered_4x256"]["return_mean"] = ret
        if meta_ret is not None:  # the second run's net has no return: no row of returns for it
            files["meta/table1.json"]["rows"]["meta_4x256"]["return_mean"] = meta_ret
        files["experts/experts.json"]["return_mean"] = 10.0 * (i + 1)
        files["meta/table1.json"]["rows"]["experts"] = {"return_mean": -1e9}  # the experts' return is experts.json's
        write_run(tmp_path / f"s{i}", files, i)
    out = seeds.seeds_record([tmp_path / "s0", tmp_path / "s1"], "publish")
    assert out["returns"]["filtered_4x256"]["per_seed"] == pytest.approx([-100.0, -200.0])
    assert out["returns"]["filtered_4x256"]["mean"] == pytest.approx(-150.0)
    assert out["returns"]["experts"]["per_seed"] == pytest.approx([10.0, 20.0])
    assert "meta_4x256" not in out["returns"] and out["rows"]["meta_4x256"]["mean"] == pytest.approx(1.5)
    write_run(tmp_path / "s2", record("ant_goal", 1.0, 1.5, 1.2), 2)  # no run keeps a return: no returns at all
    assert "returns" not in seeds.seeds_record([tmp_path / "s0", tmp_path / "s2"], "publish")


def test_the_kicks_seeds_are_published_beside_its_run_and_set_in_readmes_table(tmp_path):
    for i, (e, m, f, h) in enumerate([(0.3, 0.4, 0.2, 0.5), (0.5, 0.8, 0.4, 0.7)]):
        files = record("kick", e, m, f)
        files["heldout/heldout.json"] = {"rows": {"filtered_4x256": {"error_mean_m": h}}}
        write_run(tmp_path / f"seed{i}", files, i)
    (tmp_path / "seed1" / "heldout" / "heldout.json").unlink()  # a run without held-out: no held-out rows
    runs = [tmp_path / "seed0", tmp_path / "seed1"]
    root = tmp_path / "repo"
    written = seeds.publish_seeds(runs, "kick", "publish", root)
    assert root / "results" / "seeds.json" in written  # the default task's records: results/ itself
    assert (root / "results" / "seeds" / "seed0" / "heldout.json").exists()
    assert not (root / "results" / "seeds" / "seed1" / "heldout.json").exists()
    out = json.loads((root / "results" / "seeds.json").read_text())
    assert list(out["rows"]) == ["experts", "meta_4x256", "filtered_4x256"]  # rows every run has
    assert out["rows"]["filtered_4x256"]["per_seed"] == pytest.approx([0.2, 0.4])
    # README's column: each row's mean +- std, "-" where the seeds have none.
    assert readme.seeds_cell(("experts",), out) == "0.40 +- 0.10 m"
    assert readme.seeds_cell(("meta_4x256", "filtered_4x256"), out) == "0.60 +- 0.20 / 0.30 +- 0.10 m"
    assert readme.seeds_cell(("heldout_filtered_4x256",), out) == ""  # not every seed has it
    assert readme.seeds_cell((), out) == ""
    table = readme.readme_table(root)
    assert "| what | over 2 training seeds, mean +- std | the published run |" in table
    (line,) = [x for x in readme.findings(root) if "training seeds" in x]
    assert "at most 0.03 m, except experts 0.10 m (0.30, 0.50 m); meta_4x256 0.20 m (0.40, 0.80 m)" in line


def test_the_env_step_table_counts_every_part_of_each_arm():
    rec = {
        "experts.json": {"tasks_m": [1.0, 2.0], "env_steps": 100,
                         "env_steps_breakdown": {"ppo": 100, "family_centre_share": 20}},
        "table1.json": {"dataset_pairs": 50, "cloning": {"variant": "v", "env_steps_total": 70}},
        "table2.json": {"env": {"episode_steps": 10}, "rows": {"filtered_4x256": {"rollouts": 3, "n_tasks": 2}}},
        "baseline.json": {"seeds": 3, "env_steps_per_seed": 240},
    }  # fmt: skip
    rows = budgets.rows("cheetah_vel", rec)
    assert [s for _, _, s in rows] == [200, 40, 70, 30, 240]
    assert rows[-1][0] == "baseline" and rows[3][1].startswith("filtering: filtered_4x256")


def test_a_pipeline_seed_sets_every_training_seed_and_keeps_the_rest():
    cfg = config.make_config("tiny", {"task": "cheetah_vel", "meta.train.epochs": 30})
    seeded = config.seeded(cfg, 7)
    assert [seeded.experts.seed, seeded.meta.dataset.seed, seeded.meta.train.seed, seeded.filter.seed] == [7] * 4
    assert seeded.meta.train.epochs == 30 and seeded.meta.eval.seed == cfg.meta.eval.seed  # evaluation noise stays
    kick = config.seeded(config.make_config("tiny"), 3)
    assert kick.prior.seed == kick.experts.tune.seed == 3  # the kick's own training seeds too
    with pytest.raises(ValueError, match="a seed must be an integer >= 0, got -1"):
        config.seeded(cfg, -1)


def test_seeds_run_the_pipeline_per_seed_the_baseline_once_and_summarise(tmp_path, monkeypatch, capsys):
    from bumps_jax import cli

    calls = []

    def fake_pipeline(stages, cfg, run_dir, force=False):
        calls.append((tuple(stages), cfg.experts.seed, run_dir.name))
        err = 0.1 * (cfg.experts.seed + 1)
        write_run(run_dir, record("cheetah_vel", err, err, err), cfg.experts.seed)

    monkeypatch.setattr(pipeline, "run_pipeline", fake_pipeline)
    cfg = config.make_config("tiny", {"task": "cheetah_vel"})
    cli.run_seeds([0, 2], ("experts", "meta", "filter", "baseline"), cfg, tmp_path)
    assert calls == [
        (("experts", "meta", "filter", "baseline"), 0, "seed0"),
        (("experts", "meta", "filter"), 2, "seed2"),
    ]
    summary = json.loads((tmp_path / "seeds.json").read_text())
    assert summary["rows"]["experts"]["per_seed"] == pytest.approx([0.1, 0.3]) and summary["n_seeds"] == 2
    assert "experts: 0.200 +- 0.100 over 2 seeds" in capsys.readouterr().out
    with pytest.raises(ValueError, match="--seeds: 2 given twice"):
        cli.run_seeds([2, 2], ("experts",), cfg, tmp_path)


def test_commands_of_other_seeds_run_side_by_side_in_one_run_directory(tmp_path, monkeypatch):
    """One command a seed (a GPU each, a SLURM array): each holds its seed's directory and shares
    the run directory; the same seed twice, or a whole-directory command beside them, is refused."""
    from bumps_jax import cli, runio

    def fake_pipeline(stages, cfg, run_dir, force=False):
        write_run(run_dir, record("cheetah_vel", 0.1, 0.1, 0.1), cfg.experts.seed)

    monkeypatch.setattr(pipeline, "run_pipeline", fake_pipeline)
    cfg = config.make_config("tiny", {"task": "cheetah_vel"})
    with runio.run_lock(tmp_path, shared=True), runio.run_lock(tmp_path / "seed0"):  # another command, at seed 0
        with runio.run_lock(tmp_path, shared=True):
            cli.run_seeds([1], ("experts", "meta", "filter"), cfg, tmp_path)
        assert (tmp_path / "seed1" / "experts").is_dir()
        with pytest.raises(ValueError, match=r"seed0 is in use by another process \(pid \d+\)"):
            cli.run_seeds([0], ("experts",), cfg, tmp_path)
        with pytest.raises(ValueError, match="is in use by another process"), runio.run_lock(tmp_path):
            pass
