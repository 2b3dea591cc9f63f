"""HalfCheetah-Vel through the pipeline at CPU size: experts from a fresh policy (PPO), their
clone into the meta-policies over (state, context), policy filtering scored from per-step
velocities, the multi-task PPO baseline, the report and the published records."""

import json

import numpy as np
import pytest

from bumps_jax import config
from bumps_jax.algo import filtering
from bumps_jax.pipeline import expert_programs, family
from bumps_jax.pipeline import runner as pipeline
from bumps_jax.report import publish
from bumps_jax.tasks.cheetah_vel import env as cheetah_env


@pytest.fixture(scope="module")
def cheetah_run(tmp_path_factory):
    """The tiny preset's cheetah pipeline (experts, meta, filter, baseline) in one call: its config, directory and
    timing."""
    run_dir = tmp_path_factory.mktemp("cheetah")
    # Both meta-policies of one small architecture: one compiled rollout program serves the two.
    nets = {f"meta.nets.{name}": (1, 16) for name in ("meta_4x256", "meta_11x128")}
    cfg = config.make_config("tiny", {"task": "cheetah_vel", **nets})
    # The first round's candidates are made to look flipped (their measured posture replaced), so
    # the run draws its second round; every later rollout is the real one.
    real, calls = expert_programs.own_context_rollouts, []

    def first_round_flipped(*args):
        metrics, posture = real(*args)
        calls.append(len(calls))
        if len(calls) == 1:
            posture = {**posture, "flipped_fraction": np.ones_like(posture["flipped_fraction"])}
        return metrics, posture

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(family, "own_context_rollouts", first_round_flipped)  # the centre's choice
        timing = pipeline.run_pipeline(pipeline.ORDER, cfg, run_dir, say=lambda *a, **k: None)
    return {"cfg": cfg, "dir": run_dir, "timing": timing}


def test_the_tiny_pipeline_runs_the_cheetahs_stages(cheetah_run):
    run_dir, view = cheetah_run["dir"], cheetah_run["cfg"]
    assert sorted(cheetah_run["timing"]["stages_s"]) == ["baseline", "experts", "filter", "meta"]
    experts = json.loads((run_dir / "experts" / "experts.json").read_text())
    assert experts["task"] == "cheetah_vel" and experts["unit"] == "m/s"
    assert experts["tasks_m"] == list(view.experts.tasks)
    assert experts["env_steps"] == view.experts.ppo.total_env_steps
    # One family: two centre candidates trained side by side for one update (their own progress);
    # every one of them flipped (made to look so), so two fresh ones for one update more; of those
    # the one chosen (upright first, then the lower error on the centre context) alone for two
    # more, every expert from it; each expert's budget counts its share of the centre's steps,
    # every candidate's of both rounds included.
    fam = view.experts.family
    assert (fam.candidates, fam.choose_after, fam.centre_updates, fam.rounds) == (2, 1, 3, 2)
    centre_steps = (2 * 2 * 1 + 2) * view.experts.ppo.num_envs * view.env.episode_steps
    centre = experts["family_centre"]
    assert {k: centre[k] for k in ("context", "updates", "choose_after", "env_steps", "rounds")} == {
        "context": 0.5, "updates": 3, "choose_after": 1, "env_steps": centre_steps, "rounds": 2}  # fmt: skip
    parts = ("centre", "centre_round2", "centre_chosen")
    rows = {part: (run_dir / "experts" / part / "progress.csv").read_text().split()[1:] for part in parts}
    updates = {part: [int(r.split(",")[0]) for r in lines] for part, lines in rows.items()}
    # The candidates' rows of each round, then the chosen one's.
    assert updates == {"centre": [1, 1], "centre_round2": [1, 1], "centre_chosen": [2, 3]}
    assert rows["centre"] != rows["centre_round2"]  # fresh candidates: their own seeds
    candidates = centre["candidates"]
    assert [c["round"] for c in candidates] == [1, 1, 2, 2]
    assert centre["choice_env_steps"] == 2 * 2 * view.experts.eval.repetitions * 10
    assert all(set(c) == {"error_m", "pitch_rad", "flipped_fraction", "height_m", "round"} for c in candidates)
    assert [c["flipped_fraction"] for c in candidates[:2]] == [1.0, 1.0]
    rank = [(c["flipped_fraction"] > 0.5, c["error_m"]) for c in candidates[2:]]
    assert centre["chosen"] == 2 + rank.index(min(rank))  # from the second round
    for r, part in enumerate(parts[:2]):
        choice = json.loads((run_dir / "experts" / part / "choice.json").read_text())
        assert len(choice["candidates"]) == 2 and (r == 0 or choice["chosen"] == centre["chosen"] - 2)
    assert experts["env_steps_breakdown"] == {"ppo": experts["env_steps"], "family_centre_share": centre_steps // 2}
    assert experts["env_steps_total"] == experts["env_steps"] + centre_steps // 2
    for part in parts:
        assert not (run_dir / "experts" / part / "checkpoints").exists()  # scratch, gone with the record
    # The family check: each expert's posture beside its neighbour's error, in the record and experts.md.
    check = experts["family_check"]
    assert [r["target_m"] for r in check["per_task"]] == list(view.experts.tasks)
    for row in check["per_task"]:
        assert {"pitch_rad", "flipped_fraction", "height_m", "achieved"} <= set(row)
        assert len(row["error_at_neighbours_m"]) == 1 and 0.0 <= row["flipped_fraction"] <= 1.0
    assert check["flipped_experts"] in (0, 1, 2) and isinstance(check["achieved_rises"], bool)
    assert "## Family check" in (run_dir / "experts" / "experts.md").read_text()
    # Two updates of PPO leave the experts near where a random policy runs: errors of the order of
    # the targets, every episode valid (no physics overflow).
    assert experts["accuracy_mean"] == 1.0
    for row in experts["per_task"]:
        assert 0.0 < row["error_mean_m"] < row["target_m"] + 2.0
    table1 = json.loads((run_dir / "meta" / "table1.json").read_text())
    assert table1["obs_size"] == 18 and table1["n_actions"] == 6  # the state (17) and the context
    # The meta-policies see the state normalised by the dataset's statistics, kept with the nets.
    assert len(table1["obs_shift"]) == len(table1["obs_scale"]) == 18 and min(table1["obs_scale"]) > 0
    # Cloned with the preset's DART noise and clipped labels: its env steps are the recording's.
    assert table1["cloning"]["variant"] == "2 episode(s) per expert, DART action noise 0.2, labels clipped"
    assert table1["cloning"]["env_steps"] == {"dataset": table1["dataset_pairs"]}
    assert table1["dataset_pairs"] == 2 * view.meta.dataset.repetitions * view.env.episode_steps
    for name in ("meta_4x256", "meta_11x128"):
        assert np.isfinite(table1["rows"][name]["error_mean_all_m"])
    table2 = json.loads((run_dir / "filter" / "table2.json").read_text())
    assert "paper" not in table2 and table2["unit"] == "m/s"
    for name, row in table2["rows"].items():
        assert np.isfinite(row["error_mean_m"]) and row["rel_error_mean"] is None, name
        # The chosen context is one of the task's candidates within +- width.
        if name in table2["chosen_contexts"]:
            assert abs(table2["chosen_contexts"][name][0] - table2["tasks"][0]) <= view.filter.width + 1e-6
    text = (run_dir / "report.md").read_text()
    assert "BUMPS on cheetah_vel" in text and "error (m/s)" in text


def test_a_rerun_is_up_to_date_and_publishes_into_results(cheetah_run, tmp_path):
    log = []
    pipeline.run_pipeline(pipeline.ORDER, cheetah_run["cfg"], cheetah_run["dir"], say=log.append)
    assert sum("up to date" in line for line in log) == 4
    written = publish.publish_task(cheetah_run["dir"], "cheetah_vel", root=tmp_path)
    names = sorted(p.name for p in written)
    assert {"experts.json", "table1.json", "table2.json", "pipeline.json", "baseline.json"} <= set(names)
    assert all(p.parent == tmp_path / "results" / "cheetah_vel" for p in written)
    assert "error_map.png" not in names  # a scalar context has no map
    report = (tmp_path / "results" / "cheetah_vel" / "report.md").read_text()  # its figures by their published names
    assert "](context_map.png)" in report and "](filter/" not in report and "](baseline/" not in report
    with pytest.raises(ValueError, match="holds no kick run"):
        publish.publish_task(cheetah_run["dir"], "kick", root=tmp_path)
    with pytest.raises(ValueError, match="empty holds no stage results to publish"):
        publish.publish_task(tmp_path / "empty", "cheetah_vel", root=tmp_path)


def test_the_baseline_trains_one_policy_on_the_experts_velocities_and_scores_the_test_ones(cheetah_run):
    """Multi-task PPO from a fresh policy that sees the target, on velocities drawn from the
    experts' range, scored on the test velocities with the cheetah's mean velocity error."""
    run_dir, view = cheetah_run["dir"], cheetah_run["cfg"]
    b = view.baseline
    saved = json.loads((run_dir / "baseline" / "baseline.json").read_text())
    assert saved["task"] == "cheetah_vel" and saved["unit"] == "m/s" and "bc_final_loss" not in saved
    assert saved["sample_task_range"] == [min(view.experts.tasks), max(view.experts.tasks)]
    # Per seed, the env steps all of BUMPS's experts use together in one round of centre
    # candidates (2 candidates' 40 each, the chosen one's 80 and 2 experts x 80); this run drew a
    # second round (2 x 40 more), which its record counts.
    experts = json.loads((run_dir / "experts" / "experts.json").read_text())
    fam, per_update = view.experts.family, view.experts.ppo.num_envs * view.env.episode_steps
    second_round = fam.candidates * fam.choose_after * per_update
    assert saved["env_steps_per_seed"] == b.ppo.total_env_steps == 320
    assert len(experts["tasks_m"]) * experts["env_steps_total"] == 320 + second_round == 400
    n_updates = b.ppo.total_env_steps // (b.ppo.num_envs * view.env.episode_steps)
    for curve in (saved["curve"], saved["error_curve"]):
        assert len(curve["mean"]) == len(curve["env_steps"]) == n_updates == 8
        assert curve["env_steps"][-1] == saved["env_steps_per_seed"]
    assert np.isfinite(saved["error_curve"]["mean"]).all()
    assert saved["eval_tasks"] == pytest.approx(list(b.eval_tasks))
    # A mean velocity error per test velocity, finite and below the target plus the speed a
    # 4-update policy reaches; every episode valid; one row per seed (no second arm).
    assert len(saved["per_task_error_m"]) == len(b.eval_tasks)
    for target, error in zip(b.eval_tasks, saved["per_task_error_m"], strict=True):
        assert 0.0 < error < target + 2.0
    assert len(saved["per_seed"]) == b.seeds and len(saved["arms"]) == 1 and saved["accuracy_mean"] == 1.0
    assert saved["start"]["n_tasks"] == len(b.eval_tasks) and np.isfinite(saved["start"]["error_mean_all_m"])
    assert (run_dir / "baseline" / "baseline_curve.png").stat().st_size > 0
    text = (run_dir / "report.md").read_text()
    assert "## Multi-task PPO baseline" in text and "U[0.5, 2] m/s" in text
    assert f"{saved['error_mean_m']:.2f} m/s over {len(b.eval_tasks)} test targets" in text


def test_filtering_scores_contexts_from_per_step_velocities():
    """The cheetah's error against another target is the mean of |v_k - target| over its steps."""
    vels = np.array([[[0.5, 1.5, 1.0, 1.0]], [[2.0, 2.0, 2.0, 3.0]]])  # (C=2, R=1, steps=4)
    metrics = {"forward_vels": vels, "valid": np.ones((2, 1))}
    env = object.__new__(cheetah_env.CheetahVelEnv)  # error_against reads no model
    errors = filtering.scoring(env)["errors"](metrics, [1.0, 2.0])
    assert errors.shape == (2, 2, 1)
    np.testing.assert_allclose(errors[:, :, 0], [[0.25, 1.25], [1.0, 0.25]])
    scores = errors.mean(axis=-1)
    chosen = filtering.select_contexts(scores, [1.0, 2.0], [1.0, 2.0], 1.0, (0.0, 3.0))
    assert chosen.tolist() == [0, 1]
