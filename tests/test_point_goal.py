"""PointGoal, the task with a 2-D context (a goal (x, y) m): its env, its scoring against other
goals, policy filtering over a 2-D grid against a brute-force choice, and the tiny pipeline
(experts, meta, filter) beating a policy that does nothing."""

import itertools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bumps_jax import config
from bumps_jax.algo import filtering, rollout
from bumps_jax.pipeline import runner as pipeline
from bumps_jax.tasks import registry
from bumps_jax.tasks.point_goal import env as point_env


@pytest.fixture(scope="module")
def env():
    return point_env.PointGoalEnv()


def test_reset_and_step_jit_with_a_goal_context(env):
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    state = reset(jax.random.key(0), jnp.array([0.6, -0.2]))
    assert state.obs.shape == (env.observation_size,) == (4,)
    assert env.with_context(state.obs, state.info["target"]).shape == (env.context_observation_size,) == (6,)
    # The goal seen by a meta-policy: each coordinate normalised over the task range (-1, 1).
    np.testing.assert_allclose(env.with_context(state.obs, jnp.array([0.6, -0.2]))[4:], [0.8, 0.4], rtol=1e-6)
    for _ in range(env.n_steps):
        state = step(state, jnp.array([1.0, -0.5]))
    for key in ("final_error", "final_position", "return", "valid"):
        assert np.isfinite(np.asarray(state.metrics[key])).all(), key
    assert state.done == 1.0 and state.metrics["valid"] == 1.0
    pos = np.asarray(state.metrics["final_position"])
    assert pos.shape == (2,) and pos[0] > 0.5 and pos[1] < -0.2  # pushed along +x and -y
    np.testing.assert_allclose(state.metrics["final_error"], np.hypot(*(pos - [0.6, -0.2])), rtol=1e-5)
    # A default reset draws its goal on the disc; a concrete goal outside the task range raises.
    goals = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(1), 64)).info["target"]
    assert goals.shape == (64, 2) and float(jnp.linalg.norm(goals, axis=-1).max()) <= 1.0
    with pytest.raises(ValueError, match="outside the task range"):
        env.reset(jax.random.key(0), jnp.array([1.5, 0.0]))
    with pytest.raises(ValueError, match="vectors of 2"):
        env.check_targets([0.5, 0.2, 0.1])


def test_error_against_scores_final_positions_against_any_goal(env):
    # Two contexts x two repetitions of final positions; the second rollout of context 1 invalid.
    metrics = {
        "final_position": np.array([[[0.0, 0.0], [0.3, 0.4]], [[1.0, 1.0], [-0.6, 0.8]]]),
        "valid": np.array([[1.0, 1.0], [1.0, 0.0]]),
    }
    goals = np.array([[0.0, 0.0], [0.3, 0.0]])
    err = env.error_against(metrics, goals[:, None, None, :])
    expected = [
        [[0.0, 0.5], [np.sqrt(2.0), np.inf]],  # |p - (0, 0)|
        [[0.3, 0.4], [np.hypot(0.7, 1.0), np.inf]],  # |p - (0.3, 0)|
    ]
    np.testing.assert_allclose(err, expected)
    # filtering's scoring reshapes the tasks (T, 2) itself.
    np.testing.assert_allclose(filtering.scoring(env)["errors"](metrics, goals), expected)


def test_filtering_on_a_2d_grid_chooses_as_brute_force_does(env):
    grid = filtering.context_grid(-1.0, 1.0, 0.5, size=2)
    assert grid.shape == (25, 2) and sorted(map(tuple, grid))[:2] == [(-1.0, -1.0), (-1.0, -0.5)]
    tasks = np.array([[0.3, 0.1], [-0.5, 0.5], [0.0, -0.7]])  # (-0.5, 0.5) lies on the grid
    contexts = filtering.candidate_contexts(tasks, grid)
    assert contexts.shape == (27, 2)  # the grid and the two tasks off it
    width = 0.6

    # A stand-in meta-policy: asked for context c it ends at 0.7 c + (0.1, -0.05), repetition r
    # shifted by 0.01 r along x. `grid_fn`'s signature: metrics of (P = 1, B, R = 1).
    def program(params, ctx, targets, keys):
        r = jax.vmap(lambda k: jax.random.randint(k[0], (), 0, 3))(keys).astype(jnp.float32)
        pos = 0.7 * ctx + jnp.array([0.1, -0.05]) + 0.01 * r[:, None] * jnp.array([1.0, 0.0])
        return {"final_position": pos[None, :, None], "valid": jnp.ones((1, len(ctx), 1)),
                "final_error": jnp.linalg.norm(pos - targets, axis=-1)[None, :, None]}  # fmt: skip

    sel = filtering.filter_policy(
        program, None, contexts, tasks, width, 3, jax.random.key(0), task_range=(-1.0, 1.0), block=16,
        **filtering.scoring(env),
    )  # fmt: skip
    # Brute force: every (task, context) pair by loops, the same rollouts.
    keys = filtering.stage_keys(jax.random.key(0), len(contexts), 3)
    shift = np.array([int(jax.random.randint(k, (), 0, 3)) for k in keys]).reshape(len(contexts), 3)
    for t, task in enumerate(tasks):
        best, best_score = None, np.inf
        for c, context in enumerate(contexts):
            if np.sqrt(np.sum((context - task) ** 2)) > width + 1e-6:
                continue
            ends = [0.7 * context + [0.1 + 0.01 * shift[c, r], -0.05] for r in range(3)]
            score = np.mean([np.sqrt(np.sum((e - task) ** 2)) for e in ends])
            if score < best_score - 1e-12:
                best, best_score = c, score
        assert sel.chosen[t] == best, t
        np.testing.assert_allclose(sel.best_score[t], best_score, rtol=1e-5)
    # Every task's candidates lie within `width` of it, its own context among them.
    mask = filtering.candidate_mask(contexts, tasks, width, (-1.0, 1.0))
    for t, c in itertools.product(range(len(tasks)), range(len(contexts))):
        assert mask[t, c] == (np.linalg.norm(contexts[c] - tasks[t]) <= width + 1e-6)
    chosen = filtering.evaluate_chosen(program, None, sel.contexts[sel.chosen], tasks, 2, jax.random.key(1), block=4)
    assert chosen["final_position"].shape == (3, 2, 2)
    # Successive halving keeps its first rung's final positions, (C, rungs[0], 2): NaN where a
    # context is no task's candidate.
    halved = filtering.filter_policy(
        program, None, contexts, tasks, width, 3, jax.random.key(0), task_range=(-1.0, 1.0), block=16,
        rungs=(2, 3), **filtering.scoring(env),
    )  # fmt: skip
    assert halved.distance.shape == (len(contexts), 2, 2) and halved.valid.shape == (len(contexts), 2)
    seen = mask.any(axis=0)
    assert np.isfinite(halved.distance[seen]).all() and np.isnan(halved.distance[~seen]).all()
    np.testing.assert_allclose(halved.distance[seen], sel.distance[seen][:, :2], rtol=1e-6)


def test_the_tiny_pipeline_filters_better_than_doing_nothing(tmp_path):
    nets = {f"meta.nets.{name}": (2, 64) for name in ("meta_4x256", "meta_11x128")}
    cfg = config.make_config("tiny", {
        "task": "point_goal", **nets,
        "experts.ppo.total_env_steps": 32 * 30 * 20,  # 20 updates reach the goals within cm
        "meta.train.epochs": 100,
        "filter.context_step": 0.5,  # 25 + 3 contexts
        "filter.high_context_step": 0.25,
    })  # fmt: skip
    pipeline.run_pipeline(("experts", "meta", "filter"), cfg, tmp_path, say=lambda *a, **k: None)
    experts = json.loads((tmp_path / "experts" / "experts.json").read_text())
    assert experts["tasks_m"] == [list(t) for t in cfg.experts.tasks]
    table2 = json.loads((tmp_path / "filter" / "table2.json").read_text())
    assert table2["tasks"] == [list(t) for t in cfg.filter.tasks]
    # Doing nothing leaves the mass at the start: its error is each goal's distance from there.
    env = registry.make_env("point_goal", cfg.env)
    tasks = np.asarray(cfg.filter.tasks, np.float32)
    episode = rollout.over_reps(rollout.episode_fn(env, lambda p, obs: jnp.zeros(2)))
    keys = rollout.repetition_keys(0, len(tasks), 4)
    idle = jax.jit(jax.vmap(episode, in_axes=(None, 0, 0, 0)))(None, tasks, tasks, keys)["final_error"]
    idle_error = float(np.mean(idle))
    assert experts["error_mean_all_m"] < 0.1 * idle_error
    for name, row in table2["rows"].items():
        assert row["error_mean_m"] < 0.5 * idle_error, (name, row["error_mean_m"], idle_error)
        for context, task in zip(table2["chosen_contexts"].get(name, []), table2["tasks"], strict=False):
            assert np.linalg.norm(np.subtract(context, task)) <= cfg.filter.width + 1e-6
    assert "BUMPS on point_goal" in (tmp_path / "report.md").read_text()


@pytest.mark.parametrize(
    ("key", "value", "refused"),
    [
        ("experts.tasks", (0.5, 0.5), r"experts.tasks must be a list of contexts of 2 numbers each \(m\)"),
        ("filter.tasks", (0.3, -0.2), r"filter.tasks must be a list of contexts of 2 numbers each \(m\)"),
    ],
)
def test_two_dimensional_contexts_are_a_list_of_pairs(key, value, refused):
    """A flat list where (x, y) pairs belong is one line, not read as one context."""
    with pytest.raises(ValueError, match=refused):
        config.make_config("tiny", {"task": "point_goal", key: value})
