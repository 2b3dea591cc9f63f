"""The CMA-ES driver (bumps_jax.tasks.kick.cmaes): a toy cost for its bookkeeping, then the kick searches."""

import csv
import json

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

from bumps_jax import config, resumable
from bumps_jax.algo import sharding
from bumps_jax.tasks.kick import cmaes
from bumps_jax.tasks.kick import keyframes as kick_model
from bumps_jax.tasks.kick import scoring as kick_scoring

FITNESS = config.make_config("tiny").prior.fitness


def _toy_search(population=8):
    """Searches whose cost is the squared distance of the first two params from (target, extra)."""

    def cost_fn(params, keys, target, extra):
        cost = (params[:, 0] - target) ** 2 + (params[:, 1] - extra) ** 2
        return cost, {"valid": jnp.ones(keys.shape)}

    return cmaes.make_search(cost_fn, population, 2, 1.0, sharding.device_mesh())


def test_searches_reach_their_own_targets_and_keep_the_rest_fixed():
    x0 = np.tile(kick_model.DEFAULT_PARAMS, (2, 1)).astype(np.float32)  # lean 13, support_hip 0
    free = np.zeros((2, kick_model.N_PARAMS), bool)
    free[:, :2] = True
    free[1, 1] = False  # the second search may not move support_hip
    calls = []
    result = cmaes.run_search(_toy_search(), x0, [15.0, 10.0], free, 60, seed=0, extra=[5.0, 5.0],
                              say=lambda msg: None, on_generation=lambda g, s: calls.append(g))  # fmt: skip
    assert calls == list(range(60))
    assert result.mean.shape == result.best.shape == (2, kick_model.N_PARAMS)
    np.testing.assert_allclose(result.best[:, 0], [15.0, 10.0], atol=0.1)
    np.testing.assert_allclose(result.best[0, 1], 5.0, atol=0.1)
    np.testing.assert_allclose(result.mean[:, 0], [15.0, 10.0], atol=0.25)
    # Fixed parameters stay exactly at the start, in the mean and in the best candidate.
    for params in (result.mean, result.best):
        np.testing.assert_array_equal(params[:, 2:], x0[:, 2:])
        assert params[1, 1] == x0[1, 1]
    # The best candidate so far is the lowest cost any generation drew, and it is that candidate's cost.
    np.testing.assert_allclose(result.best_cost, result.history["best"].min(axis=0), rtol=1e-6)
    expected = (result.best[:, 0] - [15.0, 10.0]) ** 2 + (result.best[:, 1] - 5.0) ** 2
    np.testing.assert_allclose(result.best_cost, expected, rtol=1e-4, atol=1e-6)
    assert result.history["valid"].shape == (60, 2) and (result.history["valid"] == 1).all()


def test_a_leash_holds_a_search_near_its_start():
    """leash x mean z^2 over the free parameters joins the cost: with two free parameters, lean
    from 13 toward 15 and support_hip at its optimum 0, the optimum of (13 + z - 15)^2 + 2 z^2 / 2
    is z = 1; without a leash the search goes all the way."""
    x0 = np.tile(kick_model.DEFAULT_PARAMS, (2, 1)).astype(np.float32)
    free = np.zeros((2, kick_model.N_PARAMS), bool)
    free[:, :2] = True
    result = cmaes.run_search(_toy_search(), x0, [15.0, 15.0], free, 60, seed=0, extra=x0[:, 1],
                              leash=[0.0, 2.0], say=lambda msg: None)  # fmt: skip
    np.testing.assert_allclose(result.mean[:, 0], [15.0, 14.0], atol=0.25)
    np.testing.assert_allclose(result.mean[:, 1], x0[:, 1], atol=0.25)


def test_a_neighbour_leash_pulls_tasks_into_a_chain():
    """Three searches of lean toward 13, 17, 13 m, each leashed (weight 1) to the midpoint of its
    neighbours' means (the ends: their one neighbour): best responses x = (t + centre) / 2 meet at
    14.33, 15.67, 14.33; the midpoints follow the targets' order, not the input order."""
    params = jnp.arange(4.0)[:, None] * jnp.ones((4, 14))
    mids = cmaes.neighbour_midpoints(params, [9.0, 7.0, 8.0, 10.0])  # order: rows 1, 2, 0, 3
    np.testing.assert_allclose(mids[:, 0], [(2 + 3) / 2, 2, (1 + 0) / 2, 0])
    x0 = np.tile(kick_model.DEFAULT_PARAMS, (3, 1)).astype(np.float32)
    free = np.zeros((3, kick_model.N_PARAMS), bool)
    free[:, 0] = True
    targets = [13.0, 17.0, 13.0]
    leash, centre_fn = cmaes.tuning_leash([7.0, 8.0, 9.0], 1.0)
    result = cmaes.run_search(_toy_search(), x0, targets, free, 80, seed=0, extra=x0[:, 1],
                              leash=leash, centre_fn=centre_fn, say=lambda msg: None)  # fmt: skip
    np.testing.assert_allclose(result.mean[:, 0], [14.33, 15.67, 14.33], atol=0.3)
    np.testing.assert_array_equal(result.mean[:, 1:], x0[:, 1:])
    with pytest.raises(ValueError, match="experts.tune.neighbour_leash must be a number >= 0, got -0.5"):
        config.make_config("tiny", {"experts.tune.neighbour_leash": -0.5})
    assert cmaes.tuning_leash([7.0, 8.0, 9.0], 0.0) == (0.0, None)


def test_a_generation_whose_physics_dropped_contacts_stops_the_search():
    """Warp marks the episodes of a physics call that ran out of contact slots: their costs are
    wrong, so the search stops in one line instead of ranking them."""

    def cost_fn(params, keys, target, extra):
        return (params[:, 0] - target) ** 2, {"valid": jnp.ones(keys.shape), "overflow": jnp.ones(keys.shape)}

    search = cmaes.make_search(cost_fn, 4, 2, 1.0, sharding.device_mesh())
    x0 = np.asarray(kick_model.DEFAULT_PARAMS, np.float32)[None]
    with pytest.raises(RuntimeError, match="toy gen 1: the physics ran out of contact slots in 100%") as err:
        cmaes.run_search(search, x0, [14.0], np.ones((1, 14), bool), 3, 0, say=lambda m: None, label="toy")
    assert "\n" not in str(err.value)


def test_a_search_is_reproducible_from_its_seed():
    search = _toy_search()
    x0 = np.asarray(kick_model.DEFAULT_PARAMS, np.float32)[None]
    free = np.ones((1, kick_model.N_PARAMS), bool)
    a, b = (cmaes.run_search(search, x0, [14.0], free, 3, seed=4, say=lambda m: None) for _ in range(2))
    np.testing.assert_array_equal(a.mean, b.mean)
    np.testing.assert_array_equal(a.best, b.best)
    c = cmaes.run_search(search, x0, [14.0], free, 3, seed=5, say=lambda m: None)
    assert not np.array_equal(a.mean, c.mean)


def test_progress_reports_an_eta():
    lines = []
    x0 = np.asarray(kick_model.DEFAULT_PARAMS, np.float32)[None]
    cmaes.run_search(_toy_search(), x0, [14.0], np.ones((1, 14), bool), 3, 0, say=lines.append, label="toy")
    assert len(lines) == 3 and lines[0].startswith("toy gen 1/3") and "ETA" in lines[-1]


TUNE = ml_collections.ConfigDict(
    {
        "population_size": 4,
        "repetitions": 2,
        "eval_repetitions": 2,
        "seed": 0,
        "neighbour_leash": 0.0,
        "restarts": 1,
    }
)


def test_tuning_for_tasks_rejects_bad_inputs_before_compiling(env):
    starts = np.tile(kick_model.DEFAULT_PARAMS, (2, 1))
    with pytest.raises(ValueError, match="starts"):
        cmaes.tune_for_tasks(env, [8.0, 12.0], starts[:1], TUNE, 1, 0.5, fitness=FITNESS)
    with pytest.raises(ValueError, match="generations"):
        cmaes.tune_for_tasks(env, [8.0, 12.0], starts, TUNE, -1, 0.5, fitness=FITNESS)
    with pytest.raises(ValueError, match="40.0"):
        cmaes.tune_for_tasks(env, [8.0, 40.0], starts, TUNE, 1, 0.5, fitness=FITNESS)
    with pytest.raises(ValueError, match="sigma_init"):
        cmaes.tune_for_tasks(env, [8.0, 12.0], starts, TUNE, 1, 0.0, fitness=FITNESS)
    one = ml_collections.ConfigDict({**TUNE.to_dict(), "population_size": 1})
    with pytest.raises(ValueError, match="population_size"):
        cmaes.tune_for_tasks(env, [8.0, 12.0], starts, one, 1, 0.5, fitness=FITNESS)
    none = ml_collections.ConfigDict({**TUNE.to_dict(), "restarts": 0})
    with pytest.raises(ValueError, match="restarts must be a positive integer, got 0"):
        cmaes.tune_for_tasks(env, [8.0, 12.0], starts, none, 1, 0.5, fitness=FITNESS)


def test_the_run_kept_is_the_one_whose_kept_kicks_cost_least():
    """Fresh costs of 3 tasks: the start, then 3 runs. Run 0 is best on task 0 alone, run 2 on
    average; each task of a run keeps the better of start and kick, so run 1's one bad task (9.0)
    costs it only its start's 2.0."""
    costs = [[1.0, 0.2, 0.9, 0.5], [2.0, 3.0, 9.0, 1.5], [2.0, 2.5, 1.0, 1.5]]
    run, improved, run_costs = cmaes.keep_best_run(costs)
    np.testing.assert_allclose(run_costs, [(0.2 + 2.0 + 2.0) / 3, (0.9 + 2.0 + 1.0) / 3, (0.5 + 1.5 + 1.5) / 3])
    assert run == 2 and improved.tolist() == [True, True, True]
    run, improved, _ = cmaes.keep_best_run([[1.0, 0.5, 0.5], [1.0, 2.0, 2.0]])  # a tie keeps the first run
    assert run == 0 and improved.tolist() == [True, False]
    with pytest.raises(ValueError, match=r"\(tasks, 1 \+ runs\), got \(2, 1\)"):
        cmaes.keep_best_run([[1.0], [2.0]])


LEAN = kick_model.PARAM_NAMES.index("lean")
MOVES = {0: [+0.5, -1.0], 1: [+1.0, +1.0], 2: [-1.0, +0.5]}  # run -> each task's change of lean


def _stand_in_tuning(monkeypatch, during_run=None, moves=MOVES):
    """Stand-ins for the search and the scoring, so nothing compiles: run k (told by its key)
    moves every task's kick by MOVES[k], and a kick's fresh cost is |lean - 14|. Returns the list
    of keys the runs were started from; during_run(k) is called inside run k."""
    keys = []

    def run_search(search, x0, targets, free, generations, seed, **kwargs):
        mean = np.array(x0, np.float32)
        tasks = len(targets) // len(seed)  # seed: one key per run, the runs' tasks one block each
        ran = []
        for block, run_key in enumerate(seed):
            keys.append(np.asarray(jax.random.key_data(run_key)))
            k = next(i for i in moves if (jax.random.key_data(_run_key(i)) == keys[-1]).all())
            if during_run is not None:
                during_run(k)
            mean[block * tasks : (block + 1) * tasks, LEAN] += moves[k]
            ran += [k] * tasks
        hist = {name: np.tile(np.float32(ran), (generations, 1)) for name in cmaes.Stats._fields}
        return cmaes.Result(mean, mean, np.zeros(len(targets)), hist, jnp.stack([jax.random.key(7)] * len(seed)))

    def cost_program(env, mesh, fitness_json):
        def costs(params, fresh, targets):
            assert fresh.shape[0] == params.shape[1]  # one row of fresh keys per kick scored
            assert (np.asarray(jax.random.key_data(fresh)) == np.asarray(jax.random.key_data(fresh[:1]))).all()
            return jnp.abs(params[..., LEAN] - 14.0)

        return costs

    monkeypatch.setattr(cmaes, "kick_search", lambda *args, **kwargs: None)
    monkeypatch.setattr(cmaes, "run_search", run_search)
    monkeypatch.setattr(cmaes.kick_scoring, "cost_program", cost_program)
    return keys


def _run_key(k, seed=5):  # the key run k of a tuning with tune.seed = seed starts from
    return jax.random.key(seed) if k == 0 else jax.random.fold_in(jax.random.key(seed), k)


STARTS = np.tile(kick_model.DEFAULT_PARAMS, (2, 1)).astype(np.float32)  # lean 13: cost 1 each
RESTARTS_3 = ml_collections.ConfigDict({**TUNE.to_dict(), "restarts": 3, "seed": 5})


def test_restarts_run_the_tuning_from_independent_keys_in_one_batch(env, monkeypatch):
    """restarts = 3: three runs of the search in one batch (the first from the key restarts = 1
    uses), then the start and every run's kick scored on the same fresh episodes; each task's kick
    is chosen among them (`chain_choice`; leash 0 here: each task its cheapest)."""
    keys = _stand_in_tuning(monkeypatch)
    said = []
    out = cmaes.tune_for_tasks(env, [8.0, 12.0], STARTS, RESTARTS_3, 2, 0.5, fitness=FITNESS, say=said.append)
    assert not said  # one batch: no run waits for another
    # run 0: tasks 0.5 | 2.0 -> kept 0.5, 1.0; run 1: 0.0, 0.0; run 2: 2.0, 0.5 -> kept 1.0, 0.5
    np.testing.assert_allclose(out["restart_costs"], [0.75, 0.0, 0.75])
    assert out["keep"] == "chain" and out["restart"] is None and out["runs_kept"].tolist() == [2, 2]
    assert out["improved"].tolist() == [True, True] and len(out["run_seconds"]) == 3
    np.testing.assert_allclose(out["params"][:, LEAN], [14.0, 14.0])
    np.testing.assert_allclose(out["start_cost"], [1.0, 1.0])
    np.testing.assert_array_equal(keys[0], jax.random.key_data(jax.random.key(5)))  # run 0: restarts = 1's key
    assert len({k.tobytes() for k in keys}) == 3  # independent keys
    assert out["episodes"] == 2 * (3 * 2 * TUNE.population_size * TUNE.repetitions + 4 * TUNE.eval_repetitions)


def test_one_run_is_kept_whole_and_the_polish_needs_several():
    """restarts = 1: each task the better of its start and its tuned kick ("keep" "run"); the
    polish applies only where kicks are chosen among several runs."""
    assert cmaes.keep_best_run([[1.0, 0.5], [1.0, 2.0]])[1].tolist() == [True, False]
    with pytest.raises(ValueError, match=r"polish_generations applies with experts.tune.restarts > 1"):
        config.make_config("tiny", {"experts.tune.polish_generations": 5})
    with pytest.raises(ValueError, match="polish_generations must be an integer >= 0, got -1"):
        config.make_config("tiny", {"experts.tune.restarts": 2, "experts.tune.polish_generations": -1})


def _brute_force_chain(costs, kicks, targets, leash):
    """The chain objective of every assignment (C ** T of them), its least one."""
    import itertools  # noqa: PLC0415

    order = np.argsort(targets)
    z = kicks / kick_model.PARAM_SCALE
    best, best_total = None, np.inf
    for choice in itertools.product(range(costs.shape[1]), repeat=len(targets)):
        x = z[np.arange(len(targets)), choice]
        total = costs[np.arange(len(targets)), choice].sum()
        for rank, t in enumerate(order):
            lower = order[max(rank - 1, 0)] if rank > 0 else order[1]
            upper = order[rank + 1] if rank + 1 < len(order) else order[rank - 1]
            total += leash * np.mean((x[t] - 0.5 * (x[lower] + x[upper])) ** 2)
        if total < best_total - 1e-12:
            best, best_total = np.array(choice), total
    return best


def test_the_chain_choice_is_the_least_cost_of_every_assignment():
    """`chain_choice` against brute force: fresh costs plus the neighbour leash of the chosen kicks
    (the tuning's own), tasks given out of target order; leash 0 is each task's cheapest."""
    rng = np.random.default_rng(3)
    for T, C, leash in ((2, 3, 1.0), (4, 3, 0.5), (5, 4, 2.0), (6, 2, 1.0)):
        targets = rng.permutation(np.arange(T) * 0.5 + 7.0)
        costs = rng.uniform(0.3, 0.8, (T, C))
        kicks = kick_model.DEFAULT_PARAMS + rng.normal(size=(T, C, kick_model.N_PARAMS)) * kick_model.PARAM_SCALE
        kept = cmaes.chain_choice(costs, kicks, targets, leash)
        np.testing.assert_array_equal(kept, _brute_force_chain(costs, kicks, targets, leash))
        np.testing.assert_array_equal(cmaes.chain_choice(costs, kicks, targets, 0.0), np.argmin(costs, 1))
    with pytest.raises(ValueError, match=r"need costs \(T, C\), kicks \(T, C, 14\) and targets \(T,\)"):
        cmaes.chain_choice(np.ones((3, 2)), np.ones((3, 2, 13)), [7.0, 7.5, 8.0], 1.0)


def test_the_chain_takes_a_dearer_kick_where_the_cheapest_breaks_it(env, monkeypatch):
    """Several runs, kicks chosen as a chain (fresh cost |lean - 14|, start lean 13): the middle
    task's cheapest kick (run 2's, lean 14, cost 0) sits 0.8 from its neighbours' (lean 13.2 in
    every run), which at neighbour leash 10 costs 10 x 3 x 0.8**2 / 14 = 1.37 over the three tasks'
    leashes; the chain takes its run-1 kick (lean 13.25, cost 0.75) instead, at leash 0 the cheapest."""
    moves = {0: [+0.2, +0.25, +0.2], 1: [+0.2, +1.0, +0.2], 2: [+0.2, +0.25, +0.2]}  # from lean 13
    _stand_in_tuning(monkeypatch, moves=moves)
    starts = np.tile(kick_model.DEFAULT_PARAMS, (3, 1)).astype(np.float32)
    targets, quiet = [8.0, 10.0, 12.0], dict(fitness=FITNESS, say=lambda *a, **k: None)

    def tune(leash):
        cfg = ml_collections.ConfigDict({**RESTARTS_3.to_dict(), "neighbour_leash": leash})
        return cmaes.tune_for_tasks(env, targets, starts, cfg, 2, 0.5, **quiet)

    by_task, chain = tune(0.0), tune(10.0)
    assert by_task["runs_kept"][1] == 2 and chain["runs_kept"][1] == 1 and chain["restart"] is None
    np.testing.assert_allclose(chain["params"][:, LEAN], [13.2, 13.25, 13.2], rtol=1e-6)
    np.testing.assert_allclose(by_task["params"][1, LEAN], 14.0)


def test_the_polish_tunes_the_mixed_kicks_once_more_from_a_key_of_its_own(env, monkeypatch):
    """`starting_kicks.polish`: one run of `polish_generations` from the mixed kicks, from a key
    no tuning run uses, each task keeping the better of its kick and the polished one."""
    from bumps_jax.tasks.kick import starting_kicks  # noqa: PLC0415

    seen = []

    def run_search(search, x0, targets, free, generations, seed, **kwargs):
        (key,) = seed  # the polish is one run
        seen.append((generations, np.asarray(jax.random.key_data(key))))
        mean = np.array(x0, np.float32)
        mean[:, LEAN] = 14.0 - 0.5 * (np.arange(len(x0)) == 1)  # task 1's polished kick worse than its own
        hist = {name: np.zeros((generations, len(targets)), np.float32) for name in cmaes.Stats._fields}
        return cmaes.Result(mean, mean, np.zeros(len(targets)), hist, jnp.stack([jax.random.key(7)]))

    _stand_in_tuning(monkeypatch)
    monkeypatch.setattr(cmaes, "run_search", run_search)
    steps = []  # the initial CMA-ES step each search is made with
    monkeypatch.setattr(cmaes, "kick_search", lambda env, mesh, pop, reps, sigma, *a, **k: steps.append(sigma))
    cfg = config.make_config("tiny", {"experts.tune.polish_generations": 3, "experts.tune.restarts": 2,
                                      "experts.tune.seed": 5})  # fmt: skip
    mixed = np.tile(kick_model.DEFAULT_PARAMS, (2, 1)).astype(np.float32)
    mixed[:, LEAN] = [13.0, 14.0]  # fresh costs 1.0 and 0.0
    kicks, record, episodes = starting_kicks.polish(env, [8.0, 12.0], mixed, cfg, say=lambda *a, **k: None)
    assert [g for g, _ in seen] == [3] and record["generations"] == 3
    assert steps == [0.25] and record["sigma"] == starting_kicks.POLISH_SIGMA == 0.25  # not tune.sigma_init
    assert all((seen[0][1] != np.asarray(jax.random.key_data(_run_key(k)))).any() for k in range(2))
    np.testing.assert_allclose(kicks[:, LEAN], [14.0, 14.0])  # task 0 polished, task 1 kept its own
    assert record["improved"] == [True, False]
    tune = cfg.experts.tune
    assert episodes == 2 * (3 * tune.population_size * tune.repetitions + 2 * tune.eval_repetitions)


def test_a_stopped_tuning_resumes_with_the_runs_not_kept(env, monkeypatch, tmp_path):
    """With keep_dir, each finished run is kept: Ctrl-C during the batch stops the tuning once its
    runs are written; a rerun reads them and ends as an uninterrupted tuning does; with runs 2 and
    3 gone it plays only those, as one batch, each from its own run's key. Runs kept from other
    starts are not read. A batch larger than the contact pool is refused before anything runs."""
    import os  # noqa: PLC0415
    import signal  # noqa: PLC0415

    common = dict(fitness=FITNESS, say=lambda *a, **k: None)
    _stand_in_tuning(monkeypatch)
    whole = cmaes.tune_for_tasks(env, [8.0, 12.0], STARTS, RESTARTS_3, 2, 0.5, **common)

    keys = _stand_in_tuning(monkeypatch, during_run=lambda k: k == 0 and os.kill(os.getpid(), signal.SIGINT))
    with pytest.raises(resumable.Interrupted):
        cmaes.tune_for_tasks(env, [8.0, 12.0], STARTS, RESTARTS_3, 2, 0.5, keep_dir=tmp_path, **common)
    assert len(keys) == 3 and sorted(p.name for p in tmp_path.iterdir()) == [f"tuning_run_{k}.json" for k in (1, 2, 3)]

    keys = _stand_in_tuning(monkeypatch)
    said = []
    out = cmaes.tune_for_tasks(env, [8.0, 12.0], STARTS, RESTARTS_3, 2, 0.5, keep_dir=tmp_path,
                               **{**common, "say": said.append})  # fmt: skip
    assert not keys and said[0].startswith("tuning run 1/3: read from")
    first = json.loads((tmp_path / "tuning_run_1.json").read_text())["seconds"]
    assert out["run_seconds"][0] == first and len(out["run_seconds"]) == 3  # run 1's time as it ran
    for name in ("params", "start_cost", "tuned_cost", "improved", "history", "restart", "restart_costs"):
        np.testing.assert_array_equal(out[name], whole[name])

    (tmp_path / "tuning_run_2.json").unlink()
    (tmp_path / "tuning_run_3.json").unlink()
    keys = _stand_in_tuning(monkeypatch)
    resumed = cmaes.tune_for_tasks(env, [8.0, 12.0], STARTS, RESTARTS_3, 2, 0.5, keep_dir=tmp_path, **common)
    assert [k.tobytes() for k in keys] == [np.asarray(jax.random.key_data(_run_key(k))).tobytes() for k in (1, 2)]
    np.testing.assert_array_equal(resumed["params"], whole["params"])
    assert len(list(tmp_path.iterdir())) == 3

    keys = _stand_in_tuning(monkeypatch)  # other starts: every run again
    other = STARTS.copy()
    other[:, LEAN] += 0.25
    cmaes.tune_for_tasks(env, [8.0, 12.0], other, RESTARTS_3, 2, 0.5, keep_dir=tmp_path, **common)
    assert len(keys) == 3

    class SmallPool:  # the env with a contact pool of 2 x 4 x 2 episodes: one run's tuning, not three
        max_episodes, contacts_per_episode = 16, 12

        def __getattr__(self, name):
            return getattr(env, name)

    keys = _stand_in_tuning(monkeypatch)
    one = ml_collections.ConfigDict({**RESTARTS_3.to_dict(), "restarts": 1})
    cmaes.tune_for_tasks(SmallPool(), [8.0, 12.0], STARTS, one, 2, 0.5, **common)  # one run: fits
    with pytest.raises(ValueError, match="the 3 tuning runs batched .* plays 48 in one physics call"):
        cmaes.tune_for_tasks(SmallPool(), [8.0, 12.0], STARTS, RESTARTS_3, 2, 0.5, **common)


def test_runs_batched_in_one_search_draw_each_runs_own_random_numbers():
    """run_search over a list of seeds: each run (a block of searches) ends bit for bit where it
    ends alone from its seed, its neighbour leash (`per_run`) leaning on its own block only."""
    search = _toy_search()
    targets = np.array([10.0, 12.0, 14.0], np.float32)
    x0 = np.tile(kick_model.DEFAULT_PARAMS, (3, 1)).astype(np.float32)
    free = np.ones((3, kick_model.N_PARAMS), bool)
    leash, centre_fn = cmaes.tuning_leash(targets, 0.5)
    extra = np.array([1.0, 2.0, 3.0], np.float32)
    quiet = dict(say=lambda m: None, leash=leash)
    alone = [cmaes.run_search(search, x0, targets, free, 3, s, extra=extra, centre_fn=centre_fn, **quiet)
             for s in (4, 9)]  # fmt: skip
    both = cmaes.run_search(search, np.tile(x0, (2, 1)), np.tile(targets, 2), np.tile(free, (2, 1)), 3, [4, 9],
                            extra=np.tile(extra, 2), centre_fn=cmaes.per_run(centre_fn, 2, 3), **quiet)  # fmt: skip
    for one, run in zip(alone, cmaes.split_runs(both, 2), strict=True):
        np.testing.assert_array_equal(run.mean, one.mean)
        np.testing.assert_array_equal(run.best_cost, one.best_cost)
        np.testing.assert_array_equal(run.history["best"], one.history["best"])
        np.testing.assert_array_equal(jax.random.key_data(run.key), jax.random.key_data(one.key))
    assert not np.array_equal(alone[0].mean, alone[1].mean)
    assert cmaes.per_run(None, 2, 3) is None
    with pytest.raises(ValueError, match="6 searches do not split into 4 runs"):
        cmaes.run_search(search, np.tile(x0, (2, 1)), np.tile(targets, 2), np.tile(free, (2, 1)), 1, [1, 2, 3, 4])


def test_best_starts_rejects_bad_inputs_before_compiling(env):
    candidates = np.tile(kick_model.DEFAULT_PARAMS, (2, 3, 1))
    with pytest.raises(ValueError, match="candidates"):
        kick_scoring.best_starts(env, [8.0, 12.0], candidates[0], FITNESS)
    with pytest.raises(ValueError, match="repetitions"):
        kick_scoring.best_starts(env, [8.0, 12.0], candidates, FITNESS, repetitions=0)
    with pytest.raises(ValueError, match="40.0"):
        kick_scoring.best_starts(env, [8.0, 40.0], candidates, FITNESS)


def test_optimise_rejects_bad_inputs_before_compiling(env):
    cfg = config.make_config("tiny").prior
    with pytest.raises(ValueError, match="no_such_param"):
        cmaes.optimise(env, kick_model.DEFAULT_PARAMS, 12.0, ("lean", "no_such_param"), cfg)
    with pytest.raises(ValueError, match="30.0"):
        cmaes.optimise(env, kick_model.DEFAULT_PARAMS, 30.0, ("lean",), cfg)
    with pytest.raises(ValueError, match="strengths"):
        kick_scoring.sweep(env, np.tile(kick_model.DEFAULT_PARAMS, (3, 1)), [0.5, 1.5], 12.0)


def test_tiny_optimisation_improves(tmp_path, env):
    # Start from a poor kick (swing too weak for 12 m) so there is something to improve.
    start = kick_model.load_record()["params"].copy()
    start[kick_model.PARAM_NAMES.index("strength")] = 0.45
    # Two generations: each is a physics call of seconds on a CPU; the best of the second is
    # compared with the first generation's mean.
    cfg = config.make_config("tiny", {"prior.population_size": 6, "prior.generations": 2, "prior.repetitions": 1,
                                      "prior.sigma_init": 1.5}).prior  # fmt: skip
    free = ("strength", "swing_hip", "back_knee")
    out = cmaes.optimise(env, start, 12.0, free, cfg, csv_path=tmp_path / "progress.csv", say=lambda m: None)
    with open(tmp_path / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["generation"]) for r in rows] == [0, 1]
    assert float(rows[-1]["best_so_far"]) < float(rows[0]["mean_fitness"])
    assert out["best_cost"] == pytest.approx(float(rows[-1]["best_so_far"]))
    moved = [kick_model.PARAM_NAMES.index(n) for n in free]
    fixed = np.setdiff1d(np.arange(kick_model.N_PARAMS), moved)
    np.testing.assert_array_equal(out["params"][fixed], np.asarray(kick_model.clip_params(start))[fixed])


def test_committed_prior_kicks_the_ball(env):
    record = kick_model.load_record()
    assert record["params"].shape == (kick_model.N_PARAMS,)
    result = kick_scoring.evaluate_kick(env, record["params"], 12.0, FITNESS, 4)
    assert result["repetitions"] == 4 and np.isfinite(result["mean_error"])
    assert result["struck_fraction"] == 1.0
    assert result["fallen_fraction"] == 0.0
    assert result["mean_distance"] > 3.0


def test_best_starts_picks_the_candidate_that_kicks_nearest(env):
    # Per target, the committed 12 m kick against the same kick at a tenth of its swing speed
    # (a few metres at most): the 12 m kick must win at 12 m, whichever order they come in.
    main = kick_model.load_record()["params"]
    slow = main.copy()
    slow[kick_model.PARAM_NAMES.index("strength")] = 0.1
    slow[kick_model.PARAM_NAMES.index("t_swing")] = kick_model.PARAM_HIGH[kick_model.PARAM_NAMES.index("t_swing")]
    candidates = np.stack([[slow, main], [main, slow]])
    params, index, costs = kick_scoring.best_starts(env, [12.0, 12.0], candidates, FITNESS, repetitions=2)
    assert index.tolist() == [1, 0] and costs.shape == (2, 2)
    np.testing.assert_allclose(params, np.stack([main, main]), atol=1e-6)
    assert costs[0, 1] < costs[0, 0] and costs[1, 0] < costs[1, 1]


def test_the_batched_tuning_is_handed_a_contact_pool_for_every_run(monkeypatch):
    """starting_kicks gives the tuning an env whose pool holds restarts x env.warp_contacts (built
    once per size); the pool's size is no part of a kept run's fingerprint, so a run kept alone is
    read in a batch and the other way round."""
    from bumps_jax.tasks.kick import starting_kicks  # noqa: PLC0415

    cfg = config.make_config("tiny", {"experts.tune.restarts": 3})
    targets = np.asarray(cfg.experts.tasks, np.float32)
    starts = np.tile(kick_model.DEFAULT_PARAMS, (len(targets), 1)).astype(np.float32)
    monkeypatch.setattr(starting_kicks, "kept_starts", lambda *a, **k: (starts, {}, 0))
    pools = []

    def tune_for_tasks(env, targets, starts, tune_cfg, *args, **kwargs):
        pools.append(env.config.warp_contacts)
        n = len(targets)
        return {"params": starts, "start_cost": np.ones(n), "tuned_cost": np.ones(n), "improved": np.zeros(n, bool),
                "history": np.zeros((1, n)), "restart": None, "restart_costs": [1.0] * 3, "keep": "chain",
                "runs_kept": np.zeros(n, int), "run_seconds": [0.0] * 3, "episodes": 0}  # fmt: skip

    monkeypatch.setattr(cmaes, "tune_for_tasks", tune_for_tasks)
    starting_kicks.starting_kicks(cfg, {}, say=lambda *a, **k: None)
    starting_kicks.starting_kicks(config.make_config("tiny"), {}, say=lambda *a, **k: None)  # one run
    assert pools == [3 * cfg.env.warp_contacts, cfg.env.warp_contacts]
    assert starting_kicks.tune_env(cfg, 3) is starting_kicks.tune_env(cfg, 3)
    fingerprints = {
        cmaes.tuning_fingerprint(starting_kicks.tune_env(cfg, runs), targets, starts, cfg.experts.tune, 1, 0.5, "{}", 1)
        for runs in (1, 3)
    }
    assert len(fingerprints) == 1
