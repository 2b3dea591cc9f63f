"""Policy filtering: selection on known context -> distance maps, scores against a slow reference,
noise independence, bad inputs, and one tiny MJX run with the stand-in contextual policy."""

import jax
import numpy as np
import pytest
from rollout_memo import EpisodeMemo

from bumps_jax import config
from bumps_jax.algo import evaluate, filtering
from bumps_jax.tasks.kick import env as kick_env

TASK_RANGE = (7.0, 18.0)


def _resting(contexts, achieved, reps=3, spread=0.0, seed=0):
    """(distance, lateral) (C, R) of a family that kicks `achieved(c)` m along the kick line, +- spread."""
    rng = np.random.default_rng(seed)
    d = achieved(np.asarray(contexts))[:, None] + spread * rng.standard_normal((len(contexts), reps))
    return d, np.zeros_like(d)


def score_matrix(distance, lateral, blown_up, tasks) -> np.ndarray:
    """Mean final error (T, C) of each context's kicks (C, R) against each task (T,), by the kick's rule."""
    return kick_env.error_against(distance, lateral, blown_up, np.asarray(tasks, np.float64)[:, None, None]).mean(-1)


def _no_blow_up(distance):
    return np.zeros(distance.shape, bool)


def test_selection_picks_the_context_that_lands_on_the_target():
    """The family overshoots by 0.5 m: task t is best served by context t - 0.5."""
    contexts = filtering.context_grid(7.1, 18.0, 0.1)
    tasks = np.array([8.0, 11.3, 17.5])
    contexts = filtering.candidate_contexts(tasks, contexts)
    distance, lateral = _resting(contexts, lambda c: c + 0.5)
    scores = score_matrix(distance, lateral, _no_blow_up(distance), tasks)
    assert scores.shape == (3, len(contexts))
    chosen = contexts[filtering.select_contexts(scores, contexts, tasks, 1.0, TASK_RANGE)]
    np.testing.assert_allclose(chosen, tasks - 0.5, atol=1e-6)
    # A narrower neighbourhood stops at its edge, the closest it may go.
    chosen = contexts[filtering.select_contexts(scores, contexts, tasks, 0.3, TASK_RANGE)]
    np.testing.assert_allclose(chosen, tasks - 0.3, atol=1e-6)


def test_scores_equal_a_slow_reference():
    """Each score is the mean over repetitions of the Euclidean distance from the resting point
    (distance along, lateral across the kick line) to the task's target; a blown-up episode
    scores the task's distance."""
    rng = np.random.default_rng(3)
    distance = rng.uniform(6.0, 19.0, size=(4, 5))
    lateral = rng.normal(scale=0.7, size=(4, 5))
    blown = rng.uniform(size=(4, 5)) < 0.2
    tasks = np.array([7.5, 12.0, 16.3])
    expected = np.zeros((3, 4))
    for t, task in enumerate(tasks):
        for c in range(4):
            errs = [np.sqrt((distance[c, r] - task) ** 2 + lateral[c, r] ** 2) for r in range(5)]
            expected[t, c] = sum(task if blown[c, r] else errs[r] for r in range(5)) / 5
    np.testing.assert_allclose(score_matrix(distance, lateral, blown, tasks), expected, rtol=1e-12)


def test_context_grids_have_the_papers_sizes():
    assert len(filtering.context_grid(7.1, 18.0, 0.1)) == 110
    assert len(filtering.context_grid(7.1, 18.0, 0.01)) == 1091
    tasks = np.array([7.15, 12.0])
    grid = filtering.candidate_contexts(tasks, filtering.context_grid(7.1, 18.0, 0.1))
    assert len(grid) == 111 and 7.15 in grid


def test_a_perfect_family_keeps_each_task_on_its_own_context():
    tasks = np.array([7.1, 12.0, 18.0])
    contexts = filtering.candidate_contexts(tasks, filtering.context_grid(7.1, 18.0, 0.5))
    distance, lateral = _resting(contexts, lambda c: c)
    scores = score_matrix(distance, lateral, _no_blow_up(distance), tasks)
    np.testing.assert_allclose(contexts[filtering.select_contexts(scores, contexts, tasks, 2.0, TASK_RANGE)], tasks)


def test_blown_up_rollouts_score_as_the_target_distance():
    contexts = np.array([10.0, 10.5])
    distance, lateral = _resting(contexts, lambda c: c, reps=2)
    blown = np.array([[True, True], [False, False]])
    scores = score_matrix(distance, lateral, blown, [10.0])
    np.testing.assert_allclose(scores, [[10.0, 0.5]])
    assert filtering.select_contexts(scores, contexts, [10.0], 1.0, TASK_RANGE)[0] == 1


def test_ensemble_takes_the_better_net_per_task():
    def sel(best):
        best = np.asarray(best, float)
        return filtering.Selection(np.array([10.0]), None, None, None, np.zeros(2, int), best, 2)

    eval_a = {"final_error": np.array([[1.0, 1.0], [2.0, 2.0]])}
    eval_b = {"final_error": np.array([[3.0, 3.0], [0.5, 0.5]])}
    ens = filtering.ensemble_choice(sel([0.2, 0.9]), sel([0.4, 0.1]), eval_a, eval_b)
    assert ens.use_b.tolist() == [False, True]
    np.testing.assert_array_equal(ens.best_score, [0.2, 0.1])
    np.testing.assert_array_equal(ens.metrics["final_error"], [[1.0, 1.0], [0.5, 0.5]])


def test_table2_row_by_hand():
    """Two tasks (10 and 12 m), two fresh kicks each."""
    metrics = {
        "final_error": np.array([[0.2, 0.4], [1.0, 0.0]]),
        "rel_error": np.array([[0.02, 0.04], [1.0 / 12, 0.0]]),
        "valid": np.array([[1.0, 1.0], [1.0, 0.0]]),
    }
    row = filtering.table2_row(metrics, n_contexts=7, best_score=np.array([0.1, 0.4]), rollouts=14)
    assert row["error_mean_m"] == pytest.approx(0.4)  # per-task means 0.3 and 0.5
    assert row["error_std_m"] == pytest.approx(0.1)
    assert row["rel_error_mean"] == pytest.approx((0.03 + 1.0 / 24) / 2)
    assert row["accuracy_mean"] == pytest.approx(0.75)
    assert row["selection_error_m"] == pytest.approx(0.25)
    assert (row["n_contexts"], row["rollouts"], row["n_tasks"]) == (7, 14, 2)


def test_selection_and_evaluation_noise_are_independent():
    sel_key, eval_key = filtering.noise_keys(0)
    a = np.asarray(jax.random.key_data(filtering.stage_keys(sel_key, 110, 10)))
    b = np.asarray(jax.random.key_data(filtering.stage_keys(eval_key, 110, 100)))
    assert not ({tuple(k) for k in a} & {tuple(k) for k in b})
    assert len({tuple(k) for k in a}) == len(a)


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: filtering.check_contexts([], TASK_RANGE), "no contexts"),
        (lambda: filtering.check_contexts([8.0, 19.5], TASK_RANGE), "19.5"),
        (lambda: filtering.check_contexts([6.2], TASK_RANGE), "6.2"),
        (lambda: filtering.check_width(0.0), "width .* 0.0"),
        (lambda: filtering.check_width(-0.5), "-0.5"),
        (lambda: filtering.select_contexts(np.zeros((1, 2)), [8.0, 9.0], [8.5], 1.0, TASK_RANGE), "8.5"),
        (lambda: filtering.select_contexts(np.zeros((1, 2)), [8.0, 9.0], [8.0, 9.0], 1.0, TASK_RANGE), r"\(2, 2\)"),
        # The range is the env config's, passed in: a context outside a narrower one is named.
        (lambda: filtering.select_contexts(np.zeros((1, 2)), [8.0, 13.0], [8.0], 1.0, (7.0, 12.0)), "13.0"),
        (lambda: config.make_config("tiny", {"filter.width": 0.0}), "filter.width"),
        (lambda: config.make_config("tiny", {"filter.tasks": (3.0,)}), "3.0"),
        (lambda: config.make_config("tiny", {"filter.context_range": (7.0, 25.0)}), "25.0"),
        (lambda: config.make_config("tiny", {"filter.net_seed": 1}), "net_seed 1"),
    ],
)
def test_bad_inputs_name_the_value(call, match):
    with pytest.raises(ValueError, match=match):
        call()


# -- one tiny MJX run ---------------------------------------------------------------------------

BLOCK = 8  # every stage below runs as batches of 8 episodes: one compiled program (conftest's)


def test_filtering_end_to_end_in_mjx(env, contextual, monkeypatch):
    grid, params = contextual
    memo = EpisodeMemo()  # a call asking only for episodes played before gets their metrics
    memo.patch(monkeypatch, filtering)
    task_range = tuple(env.config.task_range)
    # Inside the prior family's monotone part (its sweep rises up to the main kick, 12 m).
    tasks = np.array([9.0, 10.0])
    contexts = filtering.candidate_contexts(tasks, [7.5, 11.5])
    sel_key, eval_key = filtering.noise_keys(0)
    sel = filtering.filter_policy(
        grid, params, contexts, tasks, 2.0, 2, sel_key, task_range=task_range, block=BLOCK, **filtering.scoring(env)
    )
    assert sel.scores.shape == (2, 4) and sel.distance.shape == (4, 2)
    chosen = sel.contexts[sel.chosen]
    assert np.all(np.abs(chosen - tasks) <= 2.0 + 1e-6)
    own = np.searchsorted(sel.contexts, tasks)
    assert np.all(sel.best_score <= sel.scores[np.arange(2), own])
    # The contextual family kicks further for a larger context (the map filtering corrects).
    assert np.all(np.diff(sel.distance.mean(axis=1)) > 0)
    # Rescoring: the env's own final error for a rollout whose target is the task equals the
    # selection score computed from the resting points (the dynamics ignore the target). The
    # selection's 8 episodes replayed in one call: the first two contexts' against the first task,
    # the last two's against the second (each call costs its physics steps, whatever its targets).
    flat = np.repeat(contexts, 2)
    keys = filtering.stage_keys(sel_key, 4, 2)
    m = filtering.run_blocked(grid, params, flat, np.repeat(tasks, 4), keys, BLOCK)
    rescored = m["final_error"].reshape(4, 2).mean(1)
    np.testing.assert_allclose(rescored[:2], sel.scores[0, :2], atol=1e-4)
    np.testing.assert_allclose(rescored[2:], sel.scores[1, 2:], atol=1e-4)
    m = filtering.evaluate_chosen(grid, params, chosen, tasks, 4, eval_key, block=BLOCK)
    assert m["final_error"].shape == (2, 4)
    row = filtering.table2_row(m, len(contexts), sel.best_score, len(contexts) * 2)
    assert row["n_contexts"] == 4 and np.isfinite(row["error_mean_m"]) and row["rollouts"] == 8
    assert row["selection_error_m"] == pytest.approx(sel.best_score.mean())
    assert row["rel_error_mean"] == pytest.approx(np.mean(m["final_error"] / tasks[:, None]), rel=1e-5)
    # Successive halving draws rollout j of context c from the same key as the fixed selection:
    # one rung of 2 replays it; rungs (1, 2) keeping half spend 4 + 2 x 1 (each task keeps one
    # of its 3 candidates: contexts 9 and 10 m, or one shared) rollouts or fewer, each of them one
    # of the selection's episodes (so the memo replays both rungs; an episode of another key
    # would be played and land elsewhere).
    kw = dict(task_range=task_range, block=BLOCK, **filtering.scoring(env))
    one = filtering.filter_policy(grid, params, contexts, tasks, 2.0, 2, sel_key, rungs=(2,), **kw)
    assert memo.hits == 1  # the one rung asked for the fixed selection's episodes, no others
    assert one.chosen.tolist() == sel.chosen.tolist() and one.rollouts == sel.rollouts == 8
    np.testing.assert_allclose(one.scores, sel.scores, rtol=1e-6)
    runs = memo.runs
    halved = filtering.filter_policy(grid, params, contexts, tasks, 2.0, 2, sel_key, rungs=(1, 2), keep=0.3, **kw)
    assert memo.runs == runs and memo.hits == 3  # both rungs asked for the selection's episodes only
    assert halved.distance.shape == (4, 1) and halved.rollouts <= 4 + 2
    np.testing.assert_allclose(halved.distance[:, 0], sel.distance[:, 0], rtol=1e-6)
    assert np.all(np.abs(halved.contexts[halved.chosen] - tasks) <= 2.0 + 1e-6)


# -- successive halving (pure) ------------------------------------------------------------------


def _errors_from(matrix, calls):
    """errors_of for `successive_halving` reading a known (T, C, R) matrix, logging each call."""

    def errors_of(index, start, stop):
        calls.append((index.tolist(), start, stop))
        return matrix[:, index, start:stop]

    return errors_of


def test_halving_by_hand():
    """One task, four candidates, rungs (1, 3), keep 0.5. After one rollout the scores are
    0.2, 0.5, 0.1, 0.9: contexts 2 and 0 go on. Their two more rollouts make their means over
    three 0.6 (0.2, 0.8, 0.8) and 0.4 (0.1, 0.5, 0.6): context 2 wins at 0.4. Context 1, whose
    later rollouts would have been best, is never rolled out again. Cost 4 + 2 x 2 = 8."""
    matrix = np.array([[[0.2, 0.8, 0.8], [0.5, 0.0, 0.0], [0.1, 0.5, 0.6], [0.9, 0.9, 0.9]]])
    calls = []
    out = filtering.successive_halving(_errors_from(matrix, calls), np.ones((1, 4), bool), (1, 3), 0.5)
    assert calls == [([0, 1, 2, 3], 0, 1), ([0, 2], 1, 3)]
    assert out.chosen.tolist() == [2] and out.best_score[0] == pytest.approx(0.4)
    assert out.reached.tolist() == [3, 1, 3, 1] and out.rollouts == 8
    np.testing.assert_allclose(out.scores[0], [0.6, 0.5, 0.4, 0.9])


def test_halving_shares_rollouts_between_tasks_and_keeps_to_candidates():
    """Two tasks, three contexts; task 0's candidates are contexts 0 and 1, task 1's are 1 and 2.
    Rungs (2, 4), keep 0.5: each task keeps one. Task 0: means 0.3 vs 0.5 -> context 0; task 1:
    1.0 vs 0.2 -> context 2 (context 0 scores lower for task 1 but is not its candidate). Then
    contexts 0 and 2 get rollouts 2..3 once each, whichever task asked."""
    matrix = np.zeros((2, 3, 4))
    matrix[0] = [[0.2, 0.4, 0.9, 0.9], [0.5, 0.5, 0.0, 0.0], [0.1, 0.1, 0.1, 0.1]]
    matrix[1] = [[0.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0], [0.2, 0.2, 0.4, 0.4]]
    candidates = np.array([[True, True, False], [False, True, True]])
    calls = []
    out = filtering.successive_halving(_errors_from(matrix, calls), candidates, (2, 4), 0.5)
    assert calls == [([0, 1, 2], 0, 2), ([0, 2], 2, 4)]
    assert out.chosen.tolist() == [0, 2]
    np.testing.assert_allclose(out.best_score, [0.6, 0.3])  # (0.2 + 0.4 + 0.9 + 0.9) / 4, (0.2 + 0.2 + 0.4 + 0.4) / 4
    assert out.rollouts == 3 * 2 + 2 * 2


def test_one_rung_is_the_fixed_selection():
    rng = np.random.default_rng(5)
    tasks = np.array([8.0, 9.0, 11.0])
    contexts = filtering.candidate_contexts(tasks, filtering.context_grid(7.5, 12.0, 0.5))
    errors = rng.uniform(0.0, 2.0, size=(len(tasks), len(contexts), 6))
    mask = filtering.candidate_mask(contexts, tasks, 1.0, TASK_RANGE)
    out = filtering.successive_halving(_errors_from(errors, []), mask, (6,), 0.25)
    fixed = filtering.select_contexts(errors.mean(axis=2), contexts, tasks, 1.0, TASK_RANGE)
    assert out.chosen.tolist() == fixed.tolist()
    np.testing.assert_allclose(out.best_score, errors.mean(axis=2)[np.arange(3), fixed])


@pytest.mark.parametrize(
    ("rungs", "keep", "match"),
    [((), 0.5, "increasing"), ((2, 2), 0.5, r"\(2, 2\)"), ((0, 2), 0.5, "positive"), ((1, 2), 1.0, "keep")],
)
def test_bad_halving_settings_name_the_value(rungs, keep, match):
    with pytest.raises(ValueError, match=match):
        filtering.successive_halving(lambda i, a, b: None, np.ones((1, 2), bool), rungs, keep)


def test_bad_halving_config_names_the_key():
    with pytest.raises(ValueError, match=r"filter.halving_rungs .*\(4, 2\)"):
        config.make_config("tiny", {"filter.halving_rungs": (4, 2)})
    with pytest.raises(ValueError, match="filter.selection .* 'best'"):
        config.make_config("tiny", {"filter.selection": "best"})


def test_rows_carry_the_mean_return_where_the_env_keeps_one():
    """Table rows (Table 1's and Table 2's) report the mean episode return over tasks beside the
    error when the metrics hold one, and no such key otherwise."""
    metrics = {
        "final_error": np.ones((2, 3)),
        "valid": np.ones((2, 3)),
        "return": np.array([[-1.0, -2, -3], [-5, -5, -5]]),
    }
    assert evaluate.table_row(evaluate.summarise_tasks(metrics))["return_mean"] == -3.5
    assert filtering.table2_row(metrics, 4, np.zeros(2), 10)["return_mean"] == -3.5
    del metrics["return"]
    assert "return_mean" not in evaluate.table_row(evaluate.summarise_tasks(metrics))
    assert "return_mean" not in filtering.table2_row(metrics, 4, np.zeros(2), 10)


def test_blocked_episodes_report_their_progress_call_by_call():
    def grid(params, contexts, targets, keys):  # a stand-in program: an episode "lands" at its context
        return {"distance": np.asarray(contexts)[None, :, None]}

    contexts = np.arange(10.0)
    keys = filtering.stage_keys(filtering.noise_keys(0)[1], 1, 10)
    calls = []
    m = filtering.run_blocked(grid, None, contexts, contexts, keys, 2, multiple=2, progress=lambda *a: calls.append(a))
    assert calls == [(4, 10), (8, 10), (10, 10)]  # blocks of 2 x 2 devices, the last one padded
    np.testing.assert_array_equal(m["distance"], contexts)
