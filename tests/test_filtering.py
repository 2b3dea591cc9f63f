"""Policy filtering: selection on known context -> distance maps, noise independence, bad inputs,
and one tiny MJX end-to-end run with the synthetic contextual policy."""

import jax
import numpy as np
import pytest

from bumps_jax import filtering

BALL = np.array([0.3, -0.05])


def _rest_points(contexts, achieved, reps=3, spread=0.0, seed=0):
    """Resting points (C, R, 2) of a family that kicks `achieved(c)` m along +x, +- spread."""
    rng = np.random.default_rng(seed)
    d = achieved(np.asarray(contexts))[:, None] + spread * rng.standard_normal((len(contexts), reps))
    return np.stack([BALL[0] + d, np.full_like(d, BALL[1])], axis=-1)


def test_selection_picks_the_context_that_lands_on_the_target():
    """The family overshoots by 0.5 m: task t is best served by context t - 0.5."""
    contexts = filtering.context_grid(7.1, 18.0, 0.1)
    tasks = np.array([8.0, 11.3, 17.5])
    contexts = filtering.candidate_contexts(tasks, contexts)
    rest = _rest_points(contexts, lambda c: c + 0.5)
    scores = filtering.score_matrix(rest, np.zeros(rest.shape[:2], bool), tasks, BALL)
    assert scores.shape == (3, len(contexts))
    chosen = contexts[filtering.select_contexts(scores, contexts, tasks, width=1.0)]
    np.testing.assert_allclose(chosen, tasks - 0.5, atol=1e-6)
    # A narrower neighbourhood stops at its edge, the closest it may go.
    chosen = contexts[filtering.select_contexts(scores, contexts, tasks, width=0.3)]
    np.testing.assert_allclose(chosen, tasks - 0.3, atol=1e-6)


def test_context_grids_have_the_papers_sizes():
    assert len(filtering.context_grid(7.1, 18.0, 0.1)) == 110
    assert len(filtering.context_grid(7.1, 18.0, 0.01)) == 1091
    tasks = np.array([7.15, 12.0])
    grid = filtering.candidate_contexts(tasks, filtering.context_grid(7.1, 18.0, 0.1))
    assert len(grid) == 111 and 7.15 in grid


def test_a_perfect_family_keeps_each_task_on_its_own_context():
    tasks = np.array([7.1, 12.0, 18.0])
    contexts = filtering.candidate_contexts(tasks, filtering.context_grid(7.1, 18.0, 0.5))
    rest = _rest_points(contexts, lambda c: c)
    scores = filtering.score_matrix(rest, np.zeros(rest.shape[:2], bool), tasks, BALL)
    np.testing.assert_allclose(contexts[filtering.select_contexts(scores, contexts, tasks, 2.0)], tasks)


def test_blown_up_rollouts_score_as_the_target_distance():
    contexts = np.array([10.0, 10.5])
    rest = _rest_points(contexts, lambda c: c, reps=2)
    blown = np.array([[True, True], [False, False]])
    scores = filtering.score_matrix(rest, blown, [10.0], BALL)
    np.testing.assert_allclose(scores, [[10.0, 0.5]])
    assert filtering.select_contexts(scores, contexts, [10.0], 1.0)[0] == 1


def test_ensemble_takes_the_better_net_per_task():
    def sel(best):
        best = np.asarray(best, float)
        return filtering.Selection(np.array([10.0]), None, None, None, np.zeros(2, int), best)

    eval_a = {"final_error": np.array([[1.0, 1.0], [2.0, 2.0]])}
    eval_b = {"final_error": np.array([[3.0, 3.0], [0.5, 0.5]])}
    use_b, m = filtering.ensemble_metrics(sel([0.2, 0.9]), sel([0.4, 0.1]), eval_a, eval_b)
    assert use_b.tolist() == [False, True]
    np.testing.assert_array_equal(m["final_error"], [[1.0, 1.0], [0.5, 0.5]])


def test_selection_and_evaluation_noise_are_independent():
    sel_key, eval_key = filtering.noise_keys(0)
    a = np.asarray(jax.random.key_data(filtering.stage_keys(sel_key, 110, 10)))
    b = np.asarray(jax.random.key_data(filtering.stage_keys(eval_key, 110, 100)))
    assert not ({tuple(k) for k in a} & {tuple(k) for k in b})
    assert len({tuple(k) for k in a}) == len(a)


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: filtering.check_contexts([], (7.0, 18.0)), "no contexts"),
        (lambda: filtering.check_contexts([8.0, 19.5], (7.0, 18.0)), "19.5"),
        (lambda: filtering.check_contexts([6.2], (7.0, 18.0)), "6.2"),
        (lambda: filtering.check_width(0.0), "width .* 0.0"),
        (lambda: filtering.check_width(-0.5), "-0.5"),
        (lambda: filtering.select_contexts(np.zeros((1, 2)), [8.0, 9.0], [8.5], 1.0), "8.5"),
        (lambda: filtering.make_config("tiny", {"width": 0.0}), "width"),
        (lambda: filtering.make_config("tiny", {"tasks": (3.0,)}), "3.0"),
        (lambda: filtering.make_config("tiny", {"context_range": (7.0, 25.0)}), "25.0"),
    ],
)
def test_bad_inputs_name_the_value(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_plots_write_pngs(tmp_path):
    t = np.linspace(7.1, 18.0, 5)
    filtering.plot_error_vs_target(tmp_path / "e.png", {"experts": (t, t * 0.05), "BUMPS": (t, t * 0.03)})
    filtering.plot_context_map(tmp_path / "c.png", {"net": (t, np.stack([t, t + 0.2], 1))})
    for name in ("e.png", "c.png"):
        assert (tmp_path / name).read_bytes()[:4] == b"\x89PNG"


# -- one tiny MJX end-to-end run ---------------------------------------------------------------

BLOCK = 8  # every stage below runs as batches of 8 episodes: one compiled program (conftest's)


def test_filtering_end_to_end_in_mjx(env, contextual):
    grid, params = contextual
    tasks = np.array([11.0, 13.0])
    contexts = filtering.candidate_contexts(tasks, [9.0, 15.0])
    sel_key, eval_key = filtering.noise_keys(0)
    ball = filtering.ball_start_xy(env)
    sel = filtering.filter_policy(grid, params, contexts, tasks, 2.0, 2, sel_key, ball, block=BLOCK)
    assert sel.scores.shape == (2, 4) and sel.distance.shape == (4, 2)
    chosen = sel.contexts[sel.chosen]
    assert np.all(np.abs(chosen - tasks) <= 2.0 + 1e-6)
    own = np.searchsorted(sel.contexts, tasks)
    assert np.all(sel.best_score <= sel.scores[np.arange(2), own])
    # Rescoring: the env's own final error for a rollout whose target is the task equals the
    # selection score computed from resting points (the dynamics ignore the target).
    flat = np.repeat(contexts, 2)
    keys = filtering.stage_keys(sel_key, 4, 2)
    for t_index, task in enumerate(tasks):
        m = filtering.run_blocked(grid, params, flat, np.full(8, task), keys, BLOCK)
        np.testing.assert_allclose(m["final_error"].reshape(4, 2).mean(1), sel.scores[t_index], atol=2e-3)
    m = filtering.evaluate_chosen(grid, params, chosen, tasks, 4, eval_key, block=BLOCK)
    assert m["final_error"].shape == (2, 4)
    row = filtering.table2_row(m, len(contexts))
    assert row["n_contexts"] == 4 and np.isfinite(row["error_mean_m"])
    assert row["rel_error_mean"] == pytest.approx(np.mean(m["final_error"] / tasks[:, None]), rel=1e-5)
