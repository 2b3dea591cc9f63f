"""Expert training: config errors, vmapped = alone, checkpoint resume, Table-1 record."""

import json
import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from tiny_experts import N_STEPS
from tiny_experts import config as _tiny_config

from bumps_jax import experts, prior


@pytest.fixture(scope="module")
def programs(expert_programs):
    return expert_programs


@pytest.mark.parametrize(
    ("overrides", "named"),
    [
        ({"tasks": ()}, "tasks is empty"),
        ({"tasks": (8.0, 19.5)}, "19.5"),
        ({"updates_per_chunk": 3}, "updates_per_chunk 3"),
        ({"updates_per_chunk": 0}, "updates_per_chunk"),
        ({"bc.steps": 0}, "bc.steps"),
        ({"ppo.total_env_steps": 0}, "total_env_steps"),
        ({"ppo.num_envs": 5}, "num_minibatches 2 must divide ppo.num_envs 5"),
    ],
)
def test_bad_config_names_the_value(env, overrides, named):
    with pytest.raises(ValueError, match=named):
        experts.compile_programs(_tiny_config(**overrides), env)


def test_presets_validate(env):
    for name in experts.PRESETS:
        cfg = experts.preset_config(name)
        experts.validate_config(cfg, env)
    paper = experts.preset_config("paper")
    assert len(paper.tasks) == 23 and paper.ppo.total_env_steps == 12_000_000
    with pytest.raises(ValueError, match="huge"):
        experts.preset_config("huge")


def test_bc_dataset_is_the_prior_kick(env):
    params = jnp.asarray(prior.load_prior()["params"], jnp.float32)
    obs, actions = experts.bc_dataset(env, 12.0, params)
    assert obs.shape == (N_STEPS, 2) and actions.shape == (N_STEPS, 22)
    np.testing.assert_allclose(obs[:, 0], np.arange(N_STEPS) / N_STEPS, rtol=1e-6)
    np.testing.assert_allclose(obs[:, 1], (12.0 - 7.0) / 11.0, rtol=1e-6)
    np.testing.assert_allclose(actions, prior.keyframes_to_actions(params, N_STEPS, env.dt))


def test_starting_kicks_read_the_configured_prior(tmp_path):
    # A prior whose three anchors are one kick: every task's blended start is that kick.
    record = json.loads(prior.PRIOR_JSON.read_text())
    kick = prior.DEFAULT_PARAMS.tolist()
    record.update(params=kick, anchors=dict.fromkeys(prior.ANCHORS, kick))
    path = tmp_path / "run_prior.json"
    path.write_text(json.dumps(record))
    cfg = _tiny_config(prior_path=str(path))  # tune.generations 0: no CMA-ES, nothing compiled
    expected = np.tile(prior.DEFAULT_PARAMS, (len(cfg.tasks), 1))
    committed, _ = experts.starting_kicks(_tiny_config(), verbose=False)
    assert not np.allclose(committed, expected)  # else the test could not tell the two apart
    for per_task in (True, False):
        kicks, _ = experts.starting_kicks(experts.make_config(cfg, {"bc.per_task_strength": per_task}), verbose=False)
        np.testing.assert_allclose(kicks, expected, rtol=1e-6)


def test_missing_prior_path_is_named(tmp_path):
    path = tmp_path / "no_such_prior.json"
    with pytest.raises(ValueError, match=re.escape(str(path))):
        experts.starting_kicks(_tiny_config(prior_path=str(path)), verbose=False)


def test_vmapped_training_equals_each_task_alone(programs):
    """Experts in one vmapped program do not interact: expert 8 m trains bit-for-bit the same
    next to 12 m or next to 16 m. Trained alone (a differently fused XLA program), its first
    batch of episodes matches to float precision; later ones are not compared: contact
    dynamics amplify last-bit differences of the actions into different kicks (we measured
    policy-param differences of 1e-3 after two updates)."""
    cfg = _tiny_config()
    targets = jnp.asarray(cfg.tasks)
    kicks, _ = experts.starting_kicks(cfg, verbose=False)
    state, bc_losses = experts.run_init(programs, experts.task_rngs(cfg.seed, 2), targets, kicks)
    assert np.all(np.asarray(bc_losses[:, -1]) < 0.2 * np.asarray(bc_losses[:, 0]))
    together, metrics = experts.run_chunk(programs, state, targets)

    other_targets = jnp.asarray([8.0, 16.0])
    other_kicks, _ = experts.starting_kicks(experts.make_config(cfg, {"tasks": (8.0, 16.0)}), verbose=False)
    other_state, _ = experts.run_init(programs, experts.task_rngs(cfg.seed, 2), other_targets, other_kicks)
    other, _ = experts.run_chunk(programs, other_state, other_targets)
    for a, b in zip(jax.tree_util.tree_leaves(together), jax.tree_util.tree_leaves(other), strict=True):
        np.testing.assert_array_equal(np.asarray(a)[0], np.asarray(b)[0])

    alone = jax.jit(programs.trainer.run_updates, static_argnums=2)
    for i, target in enumerate(cfg.tasks):
        start = jax.tree_util.tree_map(lambda x, i=i: x[i], state)
        _, single_metrics = alone(start, target, cfg.updates_per_chunk)
        # The first batch is collected before any gradient step: the same episodes.
        np.testing.assert_allclose(single_metrics.episode_return[0], metrics.episode_return[i, 0], rtol=1e-3)
    assert int(together.env_steps[0]) == 1 * 4 * N_STEPS  # one update of 4 episodes


def test_killed_run_resumes_to_the_uninterrupted_result(programs, tmp_path):
    # One generation of tuning: the fresh run tunes and records its starting kicks, the resumed
    # one must not tune again (its BC came from the checkpoint).
    cfg = _tiny_config(**{"tune.generations": 1, "tune.eval_repetitions": 2})
    whole = experts.train_experts(cfg, tmp_path / "whole", verbose=False, programs=programs)
    assert whole["finished"]

    part = experts.train_experts(cfg, tmp_path / "split", verbose=False, programs=programs, stop_after_chunks=1)
    assert not part["finished"] and int(part["state"].update[0]) == 1
    assert not (tmp_path / "split" / "final_params").exists()
    resumed = experts.train_experts(cfg, tmp_path / "split", verbose=False, programs=programs)
    assert resumed["finished"] and resumed["bc_losses"] is None  # BC came from the checkpoint
    record = json.loads((tmp_path / "split" / "starting_kicks.json").read_text())
    assert record["tuned"] and np.asarray(record["params"]).shape == (2, prior.N_PARAMS)

    for a, b in zip(
        jax.tree_util.tree_leaves(whole["state"]), jax.tree_util.tree_leaves(resumed["state"]), strict=True
    ):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # The progress log is the same, row for row: one per update and task.
    whole_csv = (tmp_path / "whole" / "progress.csv").read_text()
    assert whole_csv == (tmp_path / "split" / "progress.csv").read_text()
    assert len(whole_csv.strip().splitlines()) == 1 + 2 * 2

    # Checkpoint round trip: the saved final params are the trained ones.
    loaded = experts.load_final_params(tmp_path / "whole", programs, 2)
    want = experts.expert_params(whole["state"])
    for a, b in zip(jax.tree_util.tree_leaves(loaded), jax.tree_util.tree_leaves(want), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))

    # The meta stage's loader rebuilds the same experts from the run directory alone.
    fam = experts.family(tmp_path / "whole")
    assert list(fam.tasks) == [8.0, 12.0]
    for a, b in zip(jax.tree_util.tree_leaves(fam.params), jax.tree_util.tree_leaves(want), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))

    # Table 1's first row, under the run directory, with the results contract's keys.
    record = experts.evaluate_run(cfg, tmp_path / "whole", whole["state"], programs, whole["wall_s"])
    on_disk = json.loads((tmp_path / "whole" / "experts.json").read_text())
    for key in (
        "tasks_m",
        "per_task",
        "accuracy_mean",
        "accuracy_std",
        "error_mean_m",
        "error_std_m",
        "env_steps",
        "device",
        "versions",
        "date",
        "command",
        "preset",
        "wall_s",
    ):
        assert key in on_disk, key
    assert on_disk["tasks_m"] == [8.0, 12.0] and on_disk["env_steps"] == 2 * 4 * N_STEPS
    assert set(on_disk["per_task"][0]) >= {"target_m", "accuracy", "error_mean_m", "error_std_m"}
    assert 0.0 <= record["accuracy_mean"] <= 1.0
    assert "single-task experts" in (tmp_path / "whole" / "experts.md").read_text()


def test_read_starting_kicks_finds_each_target_and_names_missing_ones():
    path = Path(__file__).resolve().parent.parent / "docs" / "experts_starting_kicks.json"
    record = json.loads(path.read_text())
    kicks = experts.read_starting_kicks(path, [12.0, 7.0])
    assert list(kicks) == [12.0, 7.0]
    np.testing.assert_array_equal(kicks[12.0], np.float32(record["params"][record["tasks_m"].index(12.0)]))
    with pytest.raises(ValueError, match=r"\[12.3\]"):
        experts.read_starting_kicks(path, [12.0, 12.3])


def test_a_run_config_from_before_a_key_existed_loads_with_its_default(tmp_path):
    # The committed paper run was saved before `ppo.anneal_learning_rate` existed: reloading its
    # experts (the meta stage does) must not fail on the missing key, and must not change what it had.
    saved = json.loads(_tiny_config().to_json())
    del saved["ppo"]["anneal_learning_rate"]
    saved["ppo"]["learning_rate"] = 1e-6
    (tmp_path / "config.json").write_text(json.dumps(saved))
    cfg = experts.load_run_config(tmp_path)
    assert cfg.ppo.anneal_learning_rate is False
    assert cfg.ppo.learning_rate == 1e-6 and list(cfg.tasks) == list(_tiny_config().tasks)
