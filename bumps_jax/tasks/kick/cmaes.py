"""CMA-ES on keyframe kicks: one driver for the prior's anchors, the experts' per-task tuning and
the strike search. What a candidate costs, and the replays that score finished kicks, are in
`kick_scoring`.

A search moves a kick's 14 parameters as params = clip(x0 + scale * z), z drawn by evosax's
CMA-ES in units of `kick_model.PARAM_SCALE`; a parameter left out of the search's free mask has
scale 0 and stays at x0. Many independent searches (T of them, each with its start x0, target,
free mask and one extra number for its cost) run as one generation program, vmapped over
searches and split over a device mesh (`sharding.over_batch`):

    ask (P candidates) -> P x R noisy episodes -> mean cost per candidate -> tell

All candidates of one search's generation meet the same R episodes (common random numbers), so
the ranking compares kicks, not luck. The driver keeps each search's best candidate so far
beside CMA-ES's own state; the host loop between generations prints progress with an ETA.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax import resumable, runio
from bumps_jax.algo import sharding
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model
from bumps_jax.tasks.kick import scoring as kick_scoring

PROGRESS_FIELDS = ("generation", "best_fitness", "mean_fitness", "best_so_far", "valid_fraction", "seconds")


class Carry(NamedTuple):
    """What one generation hands to the next, every leaf with a leading (T,) search axis."""

    es: Any  # evosax CMA-ES state
    best_cost: jax.Array  # (T,) lowest mean cost of any candidate so far
    best_params: jax.Array  # (T, 14) that candidate


class Stats(NamedTuple):
    """One generation's summary per search, (T,) each."""

    best: jax.Array  # lowest mean cost among this generation's candidates
    mean: jax.Array  # mean cost over the population
    valid: jax.Array  # fraction of valid kicks over the population's episodes
    overflow: jax.Array  # fraction of episodes whose physics ran out of contact slots (Warp; else 0)


class Search(NamedTuple):
    """A compiled CMA-ES generation over T searches (`make_search`)."""

    es: Any
    es_params: Any
    # jitted (Carry, keys (T,), x0 (T, 14), targets (T,), scale (T, 14), extra (T,), leash (T,),
    # centre (T, 14)) -> (Carry, Stats)
    step: Any
    mesh: Any


class Result(NamedTuple):
    """Where T searches ended (host arrays, padding dropped)."""

    mean: np.ndarray  # (T, 14) params at each search's final CMA-ES mean
    best: np.ndarray  # (T, 14) each search's best candidate over all generations
    best_cost: np.ndarray  # (T,) its mean cost in the generation that drew it
    history: dict  # Stats field -> (generations, T)
    key: jax.Array  # the driver's PRNG key after the last generation


# -- the driver --------------------------------------------------------------------------------


def make_search(cost_fn, population: int, repetitions: int, sigma_init: float, mesh) -> Search:
    """One CMA-ES generation of T searches as a jitted program split over `mesh`.

    cost_fn(params (P, 14), keys (P, R), target (), extra ()) -> (mean cost (P,), metrics of
    (..., R) holding "valid"), e.g. `kick_cost`. Searches step in z space of
    `kick_model.PARAM_SCALE` units, starting at z = 0 with step `sigma_init`. A search's `leash` adds leash x the
    mean over its free parameters of the squared distance, in scale units, of the candidate from
    the search's `centre` params to every candidate's cost (0: the cost alone), so that CMA-ES
    ranks candidates far from the centre lower; Stats and the best cost include it.
    """
    from evosax.algorithms import CMA_ES  # noqa: PLC0415 (heavy import, only needed here)

    P, R = int(population), int(repetitions)
    es = CMA_ES(population_size=P, solution=jnp.zeros(kick_model.N_PARAMS))
    es_params = es.default_params.replace(std_init=jnp.asarray(sigma_init))

    def generation(carry: Carry, key, x0, target, scale, extra, leash, centre):
        ask_key, eval_key, tell_key = jax.random.split(key, 3)
        z, es_state = es.ask(ask_key, carry.es, es_params)
        keys = jnp.broadcast_to(jax.random.split(eval_key, R), (P, R) + eval_key.shape)
        params = kick_model.clip_params(x0 + scale * z)
        cost, metrics = cost_fn(params, keys, target, extra)
        free = scale > 0
        off = jnp.where(free, (x0 + scale * z - centre) / jnp.where(free, scale, 1.0), 0.0)
        away = jnp.sum(off * off, axis=1) / jnp.maximum(jnp.sum(free), 1)
        cost = cost + leash * away
        es_state, _ = es.tell(tell_key, z, cost, es_state, es_params)
        i = jnp.argmin(cost)
        better = cost[i] < carry.best_cost
        carry = Carry(
            es_state,
            jnp.where(better, cost[i], carry.best_cost),
            jnp.where(better, params[i], carry.best_params),
        )
        overflow = jnp.mean(metrics["overflow"]) if "overflow" in metrics else jnp.zeros(())
        return carry, Stats(jnp.min(cost), jnp.mean(cost), jnp.mean(metrics["valid"]), overflow)

    step = sharding.over_batch(jax.vmap(generation), mesh, (True,) * 8)
    return Search(es, es_params, step, mesh)


@functools.lru_cache(maxsize=8)
def kick_search(env, mesh, population: int, repetitions: int, sigma_init: float, fitness_json: str) -> Search:
    """`make_search` of `kick_cost`, kept per settings: the prior's three anchors, or a resumed
    tuning in the same process, compile it once (about a minute on a CPU)."""
    cost = kick_scoring.kick_cost(env, kick_scoring.weights(fitness_json))
    return make_search(cost, population, repetitions, sigma_init, mesh)


def run_search(search: Search, x0, targets, free, generations: int, seed, extra=None, say=print,
               label: str = "cma-es", on_generation=None, leash=None, centre_fn=None,
               resume_path=None, on_resume=None, resume_key: str = "") -> Result:  # fmt: skip
    """Run T searches for `generations` generations from key(seed) (seed: an int or a JAX key).

    seed may also be a list of K seeds: the searches are then K runs of T / K searches each (run
    k the k-th block), and run k draws its keys from seed k exactly as it would alone, so a batch
    of runs plays the random numbers of the runs one after another; `Result.key` is then (K,), the
    runs' keys (`split_runs`).

    x0: (T, 14) starts; targets: (T,) m; free: (T, 14) bool, the parameters each search moves;
    extra: (T,) numbers handed to the cost (default 0); leash: (T,) each search's cost per
    squared scale unit from its centre (`make_search`; default 0).
    centre_fn(means (T, 14)) -> (T, 14): each search's centre for the next generation from every
    search's current CMA-ES mean params (None: each search's start, fixed).
    on_generation(gen, stats) is called on the host after each generation with `Stats` of (T,)
    numpy arrays.
    resume_path: a file (.npz) where the search's state is saved after every generation, and
    from which a rerun of the same search resumes (ending exactly where an uninterrupted one
    would); with it, Ctrl-C stops the search after the generation in flight, its state saved.
    on_resume(done, history) is then called once with the generations already done (0: fresh).
    resume_key: what else the search's path depends on (its cost's settings), as text.
    """
    x0 = kick_model.clip_params(jnp.asarray(x0, jnp.float32))
    if x0.shape[1:] != (kick_model.N_PARAMS,):
        raise ValueError(f"starts must have shape (T, {kick_model.N_PARAMS}), got {x0.shape}")
    n = x0.shape[0]
    targets = jnp.asarray(targets, jnp.float32)
    scale = jnp.where(jnp.asarray(free, bool), jnp.asarray(kick_model.PARAM_SCALE, jnp.float32), 0.0)
    extra = jnp.zeros(n, jnp.float32) if extra is None else jnp.asarray(extra, jnp.float32)
    leash = jnp.zeros(n, jnp.float32) if leash is None else jnp.broadcast_to(jnp.asarray(leash, jnp.float32), (n,))
    x0, targets, scale, extra, leash = sharding.pad(
        (x0, targets, scale, extra, leash), sharding.padded_size(n, search.mesh)
    )
    T = x0.shape[0]
    seeds = list(seed) if isinstance(seed, list | tuple) else [seed]
    runs = len(seeds)
    if runs == 0 or n % runs:
        raise ValueError(f"{n} searches do not split into {runs} runs of equal size")
    key = jnp.stack([jax.random.key(s) if isinstance(s, int | np.integer) else s for s in seeds])

    def draw(key):  # each run's next key, and one key per search from each run's own stream
        pair = jax.vmap(jax.random.split)(key)
        per_search = jax.vmap(lambda k: jax.random.split(k, n // runs))(pair[:, 1]).reshape(n)
        return pair[:, 0], sharding.pad(per_search, T)

    key, init_keys = draw(key)
    init = jax.vmap(lambda k: search.es.init(k, jnp.zeros(kick_model.N_PARAMS), search.es_params))
    carry = Carry(init(init_keys), jnp.full(T, jnp.inf, jnp.float32), x0)
    # CMA-ES starts some fields weakly typed and returns them strongly typed: fix the types now
    # so that the generation program compiles once, not twice.
    carry = jax.tree.map(lambda x: x.astype(x.dtype), carry)
    x0, targets, scale, leash = sharding.place((x0, targets, scale, leash), search.mesh)
    centre, extra = x0, sharding.place(extra, search.mesh)
    history, pace = [], resumable.Clock(generations)

    def follow(fn, carry):  # fn of every search's current CMA-ES mean params, padded and placed
        means = x0[:n] + scale[:n] * carry.es.mean[:n]
        return sharding.place(sharding.pad(jnp.asarray(fn(means), jnp.float32), T), search.mesh)

    first = 0
    if resume_path is not None:
        identity = _search_identity(
            x0,
            targets,
            scale,
            extra,
            leash,
            key,
            generations,
            search.es_params,
            np.frombuffer(resume_key.encode(), np.uint8),
        )
        first, carry, key, history = _read_search_state(resume_path, identity, carry, key, say, label)
        if on_resume is not None:
            on_resume(first, history)
    # With its state saved after every generation, Ctrl-C stops the search after the one in flight.
    guard = contextlib.nullcontext() if resume_path is None else resumable.stop_on_interrupt(say, at="this generation")
    with guard as stop:
        for gen in range(first, generations):
            key, gen_keys = draw(key)
            if centre_fn is not None:
                centre = follow(centre_fn, carry)
            carry, stats = search.step(
                *sharding.place((carry, gen_keys), search.mesh), x0, targets, scale, extra, leash, centre,
            )  # fmt: skip
            stats = Stats(*(np.asarray(s) for s in sharding.unpad(tuple(stats), n)))
            if stats.overflow.max() > 0:  # dropped contacts: every cost of this generation is wrong
                raise RuntimeError(
                    f"{label} gen {gen + 1}: the physics ran out of contact slots in "
                    f"{stats.overflow.max():.0%} of a search's episodes; raise env.warp_contacts"
                )
            history.append(stats)
            if resume_path is not None:
                _write_search_state(resume_path, identity, gen + 1, carry, key, history)
            if on_generation is not None:
                on_generation(gen, stats)
            say(f"{label} gen {gen + 1}/{generations}  best cost {stats.best.mean():.3f} (worst search "
                f"{stats.best.max():.3f})  population mean {stats.mean.mean():.3f}  valid {stats.valid.mean():.2f}  "
                f"{pace.tick(gen + 1)}")  # fmt: skip
            if stop is not None:
                stop.check()
    es, best_cost, best = sharding.unpad(tuple(carry), n)
    mean = kick_model.clip_params(x0[:n] + scale[:n] * es.mean)
    names = Stats._fields
    hist = {k: np.asarray([getattr(s, k) for s in history]).reshape(generations, n) for k in names}
    return Result(np.asarray(mean), np.asarray(best), np.asarray(best_cost), hist,
                  key if isinstance(seed, list | tuple) else key[0])  # fmt: skip


def _search_identity(*parts) -> str:
    """A hash of what a search's path depends on (starts, targets, free mask, costs' extras,
    leash, seed key, generations, CMA-ES settings): a saved state resumes only the same search."""
    h = hashlib.sha256()
    for leaf in jax.tree.leaves(parts):
        if isinstance(leaf, jax.Array) and jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key):
            leaf = jax.random.key_data(leaf)
        arr = np.asarray(leaf)
        h.update(str((arr.dtype, arr.shape)).encode())
        h.update(arr.tobytes())
    return h.hexdigest()


def _state_leaves(carry, key) -> list:
    return [np.asarray(x) for x in jax.tree.leaves(carry)] + [np.asarray(jax.random.key_data(key))]


def _write_search_state(path, identity: str, done: int, carry, key, history) -> None:
    """A search's state after `done` generations, written atomically (temp file + rename)."""
    leaves = {f"leaf_{i}": x for i, x in enumerate(_state_leaves(carry, key))}
    stats = {f"stats_{k}": np.asarray([getattr(s, k) for s in history]) for k in Stats._fields}
    runio.write_npz(path, identity=np.asarray(identity), done=np.asarray(done), **leaves, **stats)


def _read_search_state(path, identity: str, carry, key, say, label) -> tuple:
    """(generations done, carry, key, history) saved at `path` for this search (`identity`), else
    (0, carry, key, []) with the reason said: no file, another search's, or unreadable."""
    path = Path(path)
    if not path.is_file():
        return 0, carry, key, []
    fresh = _state_leaves(carry, key)
    try:
        with np.load(path) as f:
            if str(f["identity"]) != identity:
                say(f"{label}: {runio.shown(path)} holds another search's state; starting from generation 0")
                return 0, carry, key, []
            leaves = [f[f"leaf_{i}"] for i in range(len(fresh))]
            done = int(f["done"])
            stats = {k: f[f"stats_{k}"] for k in Stats._fields}
    except Exception as err:  # noqa: BLE001 (a truncated or damaged file: zip, pickle or key errors)
        say(f"{label}: {runio.shown(path)} is unreadable ({runio.error_reason(err)}); starting from generation 0")
        return 0, carry, key, []
    if any(a.shape != b.shape or a.dtype != b.dtype for a, b in zip(leaves, fresh, strict=True)):
        say(f"{label}: {runio.shown(path)} holds a state of other shapes; starting from generation 0")
        return 0, carry, key, []
    treedef = jax.tree.structure(carry)
    carry = jax.tree.unflatten(treedef, [jnp.asarray(x) for x in leaves[:-1]])
    key = jax.random.wrap_key_data(jnp.asarray(leaves[-1]), impl=jax.random.key_impl(key))
    history = [Stats(*(stats[k][g] for k in Stats._fields)) for g in range(done)]
    say(f"{label}: resumed after generation {done} from {runio.shown(path)}")
    return done, carry, key, history


def split_runs(result: Result, runs: int) -> list[Result]:
    """The `runs` runs of one `run_search` over a list of `runs` seeds, each its own Result as if
    it had run alone (its block of searches, its history, its key)."""
    if result.key.shape != (runs,):
        raise ValueError(f"a result of {result.key.shape} keys is not {runs} runs")
    n = len(result.mean) // runs
    block = [slice(k * n, (k + 1) * n) for k in range(runs)]
    out = []
    for k, b in enumerate(block):
        history = {field: h[:, b] for field, h in result.history.items()}
        out.append(Result(result.mean[b], result.best[b], result.best_cost[b], history, result.key[k]))
    return out


def per_run(fn, runs: int, searches: int):
    """`run_search`'s centre_fn `fn` (of one run's means (searches, 14)) for `runs` runs batched
    as runs x searches: each run's block of means is its own chain, `fn` of that block alone.
    None stays None."""
    if fn is None or runs == 1:
        return fn

    def batched(means):
        out = jax.vmap(fn)(means.reshape(runs, searches, *means.shape[1:]))
        return out.reshape(runs * searches, *out.shape[2:])

    return batched


# -- what the stages call ------------------------------------------------------------------------


def optimise(env, start, target: float, free_params, cfg, csv_path=None, mesh=None, say=print, label="",
             resume_path=None) -> dict:  # fmt: skip
    """One search (T = 1 of the driver) for the kick that rests at `target` m.

    start: params (14,); free_params: names of the parameters it moves (the rest stay at start);
    cfg: population_size, generations, repetitions, sigma_init, seed and fitness weights (the
    prior's config section). csv_path: a per-generation progress CSV (`PROGRESS_FIELDS`), begun
    anew (or, resumed, kept to the generations done). resume_path: the search's state after every
    generation, resumed by a rerun and stopped by Ctrl-C after a generation (`run_search`).
    Returns {"params": best candidate (14,), "best_cost", "mean_params": final mean (14,),
    "history": Stats field -> (generations,)}.
    """
    start = np.asarray(start, np.float32)
    unknown = [n for n in free_params if n not in kick_model.PARAM_NAMES]
    if start.shape != (kick_model.N_PARAMS,) or unknown or not free_params:
        raise ValueError(f"need start ({kick_model.N_PARAMS},) and free_params among PARAM_NAMES, got "
                         f"{start.shape} and {tuple(free_params)!r}")  # fmt: skip
    _check_search(env, [target], cfg.population_size, cfg.repetitions, cfg.sigma_init, cfg.generations)
    mesh = mesh or sharding.device_mesh(impl=env.config.impl)
    _check_pool(env, int(cfg.population_size) * int(cfg.repetitions), "the search")
    search = kick_search(env, mesh, int(cfg.population_size), int(cfg.repetitions), float(cfg.sigma_init),
                         kick_scoring.fitness_json_of(cfg.fitness))  # fmt: skip
    free = np.array([n in free_params for n in kick_model.PARAM_NAMES])
    on_generation = on_resume = None
    if csv_path is not None:
        csv_path = Path(csv_path)
        csv_path.parent.mkdir(parents=True, exist_ok=True)
        on_generation = _progress_writer(csv_path)

        def on_resume(done, history):  # the rows of the generations done stay; later ones are redone
            runio.trim_csv(csv_path, PROGRESS_FIELDS, "generation", done - 1)
            on_generation.best = min([np.inf, *(float(s.best[0]) for s in history)])

        if resume_path is None:
            on_resume(0, [])
    settings = {k: cfg[k] for k in ("population_size", "repetitions", "sigma_init", "seed")}
    resume_key = json.dumps([settings, kick_scoring.fitness_json_of(cfg.fitness), kick_env.resolved(env.config)],
                            sort_keys=True, default=str)  # fmt: skip
    result = run_search(search, start[None], [target], free[None], int(cfg.generations), int(cfg.seed),
                        say=say, label=label or f"kick {target:g} m", on_generation=on_generation,
                        resume_path=resume_path, on_resume=on_resume, resume_key=resume_key)  # fmt: skip
    return {
        "params": result.best[0],
        "best_cost": float(result.best_cost[0]),
        "mean_params": result.mean[0],
        "history": {k: v[:, 0] for k, v in result.history.items()},
    }


def _progress_writer(path: Path):
    """on_generation for one search: appends a row of PROGRESS_FIELDS per generation."""
    state = {"t": time.perf_counter()}

    def write(gen, stats):
        now = time.perf_counter()
        write.best = min(write.best, float(stats.best[0]))
        row = [gen, float(stats.best[0]), float(stats.mean[0]), write.best, float(stats.valid[0]), now - state["t"]]
        state["t"] = now
        runio.append_csv(path, PROGRESS_FIELDS, [dict(zip(PROGRESS_FIELDS, row, strict=True))])

    write.best = np.inf  # the best so far (a resumed search starts it from the generations done)
    return write


def tune_for_tasks(env, targets, starts, tune_cfg, generations: int, sigma_init: float, *, fitness, mesh=None,
                   say=print, keep_dir=None) -> dict:  # fmt: skip
    """CMA-ES on every task's own kick at once: one search per target, every parameter free.

    targets: (T,) m; starts: (T, 14). tune_cfg: population_size, repetitions, eval_repetitions,
    seed (`cfg.experts.tune`); fitness: the cost weights (`cfg.prior.fitness`). Each task keeps
    the better of its start and its final CMA-ES mean on `eval_repetitions` fresh noisy episodes
    shared by both, so a task's kick never gets worse than its start.

    With tune_cfg.neighbour_leash > 0 each search's candidates pay that much per squared scale
    unit of mean distance from the midpoint of their neighbouring tasks' current CMA-ES means (one
    neighbour at either end of the sorted targets; `make_search`), so the tasks move as a chain: a
    kick between two tasks' kicks is near both. The keep-the-better rule compares the kicks' costs
    alone.

    With tune_cfg.restarts = K > 1 the whole tuning runs K times from independent CMA-ES keys
    (the first the one restarts = 1 uses), as one batch of K x T searches (each physics call K
    runs' episodes: `env`'s contact pool must hold them), each run from its own key as alone
    (`run_search`), so batching changes the schedule, not the runs. Each task's kick is then
    chosen among its start and its kick in every run, the tasks' choices made together
    (`chain_choice`, "keep" "chain"): the fresh costs plus the neighbour leash between the chosen
    kicks, the tuning's own objective, so a task takes a slightly dearer kick where the cheapest
    one would break the chain. With K = 1 ("keep" "run") each task keeps the better of its start
    and its tuned kick.

    keep_dir: where each finished run is kept (`tuning_run_<k>.json`, with a fingerprint of
    everything it depends on): a rerun with the same inputs reads the runs it finds there instead
    of running them again (the runs left play as one batch), and Ctrl-C stops after the generation
    in flight. None keeps nothing.

    Returns {"params": (T, 14), "start_cost": (T,), "tuned_cost": (T,), "improved": (T,) bool,
    "history": (generations, T) best cost per generation, "restart": the run kept,
    "restart_costs": (K,) each run's mean cost over tasks (`keep_best_run`), "runs_kept": (T,)
    int, each task's kick from run k (1..K) or its start (0), "run_seconds": (K,) (a batch's time
    shared evenly by its runs), "keep": "run" or "chain", "episodes": int}; with K > 1 "restart"
    is None and "history" the first run's.
    """
    targets = np.asarray(targets, np.float32)
    starts = np.asarray(kick_model.clip_params(jnp.asarray(starts, jnp.float32)))
    if targets.ndim != 1 or starts.shape != (targets.shape[0], kick_model.N_PARAMS):
        raise ValueError(
            f"need targets (T,) and starts (T, {kick_model.N_PARAMS}), got {targets.shape} and {starts.shape}"
        )
    if isinstance(generations, bool) or not isinstance(generations, int | np.integer) or generations < 0:
        raise ValueError(f"generations must be an integer >= 0, got {generations!r}")
    _check_search(env, targets, tune_cfg.population_size, tune_cfg.repetitions, sigma_init, 1)
    kick_scoring.check_count("eval_repetitions", tune_cfg.eval_repetitions)
    mesh = mesh or sharding.device_mesh(impl=env.config.impl)
    P, R, E, T = int(tune_cfg.population_size), int(tune_cfg.repetitions), int(tune_cfg.eval_repetitions), len(targets)
    per_device = sharding.padded_size(T, mesh) // sharding.ways(mesh)  # searches each device plays at once
    _check_pool(env, per_device * P * R, "the tuning (tasks x population x repetitions)")
    fitness_json = kick_scoring.fitness_json_of(fitness)
    kick_scoring.check_count("restarts", tune_cfg.restarts)
    K = int(tune_cfg.restarts)
    keep = "chain" if K > 1 else "run"  # one run kept whole; among several, the chain's choice
    _check_pool(env, per_device * (K + 1) * E, "the tuning's fresh scoring (tasks x (restarts + 1) x eval_repetitions)")
    search = kick_search(env, mesh, P, R, float(sigma_init), fitness_json)
    leash, centre_fn = tuning_leash(targets, float(tune_cfg.neighbour_leash))
    ways = sharding.ways(mesh)
    fingerprint = tuning_fingerprint(env, targets, starts, tune_cfg, generations, sigma_init, fitness_json, ways)
    seed = jax.random.key(int(tune_cfg.seed))
    seeds = [seed if k == 0 else jax.random.fold_in(seed, k) for k in range(K)]  # run k's own key

    def state_path(runs: list[int]) -> Path | None:  # a batch's search state after each generation
        return None if keep_dir is None else Path(keep_dir) / f"tuning_runs_{'_'.join(str(k + 1) for k in runs)}.npz"

    def tune(runs: list[int], label: str) -> list[tuple[Result, float]]:  # the runs `runs` as one batch
        m, t0 = len(runs), time.perf_counter()
        result = run_search(
            search, np.tile(starts, (m, 1)), np.tile(targets, m), np.ones((m * T, kick_model.N_PARAMS), bool),
            int(generations), [seeds[k] for k in runs], say=say, label=label, leash=leash,
            centre_fn=per_run(centre_fn, m, T),
            resume_path=state_path(runs), resume_key=fingerprint,
        )  # fmt: skip
        took = (time.perf_counter() - t0) / m  # a batch's time, shared evenly by its runs
        return [(r, took) for r in split_runs(result, m)]

    paths = [None if keep_dir is None else Path(keep_dir) / f"tuning_run_{k + 1}.json" for k in range(K)]
    done: dict[int, tuple[Result, float]] = {}
    for k, path in enumerate(paths):
        kept = read_tuning_run(path, fingerprint)
        if kept is not None:
            say(f"{'tuning' if K == 1 else f'tuning run {k + 1}/{K}'}: read from {runio.shown(path)}")
            done[k] = kept
    left = [k for k in range(K) if k not in done]
    batched = len(left) > 1
    if batched:
        # every run left in one batch: its searches side by side in each physics call
        most = sharding.padded_size(len(left) * T, mesh) // sharding.ways(mesh) * P * R
        _check_pool(env, most, f"the {len(left)} tuning runs batched (runs x tasks x population x repetitions)")
    # With runs kept, Ctrl-C stops after the generation in flight (the search's state saved, resumed
    # by a rerun) or between runs (their files written).
    guard = contextlib.nullcontext() if keep_dir is None else resumable.stop_on_interrupt(say, at="this generation")
    with guard as stop:
        for batch in [left] if batched else [[k] for k in left]:
            if batched:
                label = f"tuning runs {', '.join(str(k + 1) for k in batch)} of {K} (one batch)"
            else:
                label = "tuning" if K == 1 else f"tuning run {batch[0] + 1}/{K}"
            for k, (result, took) in zip(batch, tune(batch, label), strict=True):
                done[k] = (result, took)
                if paths[k] is not None:
                    write_tuning_run(paths[k], fingerprint, result, took)
            if state_path(batch) is not None:  # its runs are kept whole now
                runio.remove(state_path(batch))
            still = [k for k in left if k not in done]
            if still:  # the later runs compile nothing: each takes about as long as the last
                say(f"{label} done in {took:.0f} s; ETA of the other runs {len(still) * took:.0f} s")
            if stop is not None:
                stop.check()
    results, seconds = [done[k][0] for k in range(K)], [done[k][1] for k in range(K)]
    # The start and every run's tuned kicks on the same fresh episodes (common random numbers).
    key = results[0].key
    keys = jnp.broadcast_to(jax.random.split(jax.random.fold_in(key, 1), E), (K + 1, E) + key.shape)
    kicks = jnp.stack([starts] + [r.mean for r in results], 1)  # (T, K + 1, 14)
    padded = sharding.pad((kicks, jnp.asarray(targets)), sharding.padded_size(T, mesh))
    score = kick_scoring.cost_program(env, mesh, fitness_json)
    costs = np.asarray(sharding.unpad(score(padded[0], keys, padded[1]), T))
    best, improved, run_costs = keep_best_run(costs)
    if keep == "run":
        kept = np.where(improved, best + 1, 0)  # (T,) 0: the start
    else:  # "chain": the choices that cost least with the neighbour leash between them
        kept = chain_choice(costs, np.asarray(kicks), targets, float(tune_cfg.neighbour_leash))
    tasks = np.arange(T)
    return {
        "params": np.asarray(kicks)[tasks, kept],
        "start_cost": costs[:, 0],
        "tuned_cost": costs[:, best + 1] if keep == "run" else costs[:, 1:].min(1),  # the tuned kick kept or not
        "improved": kept > 0,
        "history": results[best if keep == "run" else 0].history["best"],
        "restart": best if keep == "run" else None,
        "restart_costs": run_costs.tolist(),
        "runs_kept": kept,
        "run_seconds": seconds,  # each run's time, the first's compile included, kept runs' as they took
        "keep": keep,
        "episodes": int(T * (K * generations * P * R + (K + 1) * E)),  # every episode played
    }


def tuning_fingerprint(env, targets, starts, tune_cfg, generations, sigma_init, fitness_json, devices) -> str:
    """A hash of everything one tuning run's result depends on (not `restarts`: run k is the same
    whatever the number of runs; nor the contact pool's size, which holds one run or a batch of
    them and stops a search that overflows it): the env, tasks, starts, search settings, cost and
    device count."""
    keys = ("population_size", "repetitions", "seed", "neighbour_leash")
    physics = {k: v for k, v in kick_env.resolved(env.config).items() if k != "warp_contacts"}
    payload = {
        "env": physics,
        "targets": np.asarray(targets, np.float32).tolist(),
        "starts": hashlib.sha256(np.ascontiguousarray(starts, np.float32).tobytes()).hexdigest(),
        "tune": {k: tune_cfg[k] for k in keys},
        "generations": int(generations),
        "sigma_init": float(sigma_init),
        "fitness": fitness_json,
        "devices": int(devices),
    }
    return runio.fingerprint(payload)


def write_tuning_run(path: Path, fingerprint: str, result: Result, seconds: float) -> None:
    """Keep one finished tuning run's `Result` and the seconds it took under its fingerprint,
    written atomically."""
    runio.write_kept(path, fingerprint, {
        "seconds": float(seconds),
        "mean": np.asarray(result.mean).tolist(),
        "best": np.asarray(result.best).tolist(),
        "best_cost": np.asarray(result.best_cost).tolist(),
        "history": {name: np.asarray(v).tolist() for name, v in result.history.items()},
        "key": np.asarray(jax.random.key_data(result.key)).tolist(),
    })  # fmt: skip


def read_tuning_run(path: Path | None, fingerprint: str) -> tuple[Result, float] | None:
    """(Result, seconds) of a run `write_tuning_run` kept at `path` under the same fingerprint,
    else None (no file, an unreadable one, or another config's)."""
    kept = runio.read_kept(path, fingerprint)
    if kept is None:
        return None

    def floats(x):  # strict JSON wrote a non-finite number as null: it reads back as NaN
        return np.array(x, dtype=float).astype(np.float32)

    mean, best, best_cost = (floats(kept[f]) for f in ("mean", "best", "best_cost"))
    history = {name: floats(v).reshape(-1, len(mean)) for name, v in kept["history"].items()}
    key = jax.random.wrap_key_data(np.asarray(kept["key"], np.uint32))
    return Result(mean, best, best_cost, history, key), float(kept["seconds"])


def keep_best_run(costs) -> tuple[int, np.ndarray, np.ndarray]:
    """Which tuning run to keep, from fresh costs (T, 1 + K): column 0 each task's start, column
    1 + k its kick in run k. Each task of a run keeps the better of its start and its kick; the
    run kept is the one whose kept kicks cost least in the mean over tasks (the first on a tie).
    Returns (run, improved (T,) bool: the tasks that keep that run's kick, run_costs (K,))."""
    costs = np.asarray(costs, np.float64)
    if costs.ndim != 2 or costs.shape[1] < 2:
        raise ValueError(f"need fresh costs of shape (tasks, 1 + runs), got {costs.shape}")
    run_costs = np.minimum(costs[:, :1], costs[:, 1:]).mean(0)
    run = int(np.argmin(run_costs))
    return run, costs[:, run + 1] < costs[:, 0], run_costs


def chain_choice(costs, kicks, targets, leash: float) -> np.ndarray:
    """Each task's kick among its candidates, chosen together: (T,) indices into the candidates
    that minimise the sum over tasks of the fresh cost (costs (T, C)) plus `leash` times the
    neighbour leash of the tuning (`tuning_leash`: the mean over parameters of the squared distance,
    in PARAM_SCALE units, of a task's kick from the midpoint of its neighbours' in the order of
    `targets` (T,); the first and last task's one neighbour counts twice). kicks: (T, C, 14).
    Exact, by dynamic programming over pairs of neighbouring choices (T * C**3 terms); leash 0 is
    each task's cheapest."""
    costs, kicks = np.asarray(costs, np.float64), np.asarray(kicks, np.float64)
    T, C = costs.shape
    if kicks.shape != (T, C, kick_model.N_PARAMS) or np.shape(targets) != (T,):
        raise ValueError(f"need costs (T, C), kicks (T, C, {kick_model.N_PARAMS}) and targets (T,), "
                         f"got {costs.shape}, {kicks.shape} and {np.shape(targets)}")  # fmt: skip
    if leash == 0.0 or T == 1:
        return np.argmin(costs, 1)
    order = np.argsort(np.asarray(targets), kind="stable")
    z = kicks[order] / np.asarray(kick_model.PARAM_SCALE, np.float64)  # (T, C, 14) in scale units
    cost = costs[order]

    def away(kick, lower, upper):  # broadcasting (..., 14) -> (...): the leash of `kick`
        return np.mean((kick - 0.5 * (lower + upper)) ** 2, -1)

    # value[a, b]: least total of tasks 0..t with task t-1 at choice a and task t at b, the leash of
    # every task before t counted (task t's waits for task t+1).
    value = cost[0][:, None] + cost[1][None, :] + leash * away(z[0][:, None], z[1][None, :], z[1][None, :])
    back = []
    for t in range(2, T):
        # total[a, b, c]: tasks t-2, t-1, t at a, b, c; task t-1's leash is now known
        total = value[:, :, None] + leash * away(z[t - 1][None, :, None], z[t - 2][:, None, None], z[t][None, None, :])
        back.append(np.argmin(total, 0))  # (b, c) -> best a
        value = np.min(total, 0) + cost[t][None, :]
    value = value + leash * away(z[T - 1][None, :], z[T - 2][:, None], z[T - 2][:, None])  # the last task's leash
    a, b = np.unravel_index(np.argmin(value), value.shape)
    chosen = [b, a]
    for best_a in reversed(back):
        chosen.append(best_a[chosen[-1], chosen[-2]])
    kept = np.empty(T, int)
    kept[order] = chosen[::-1]
    return kept


def neighbours(targets) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each task's lower and upper neighbour in the order of `targets` (T,) (ties keep their
    order): indices (T,) each, and (T,) bool whether it has one; a missing neighbour (the first
    and the last task's) is the task itself."""
    order = np.argsort(np.asarray(targets), kind="stable")
    rank = np.argsort(order, kind="stable")  # each task's place in the sorted order
    has_lower, has_upper = rank > 0, rank < len(order) - 1
    return order[np.maximum(rank - 1, 0)], order[np.minimum(rank + 1, len(order) - 1)], has_lower, has_upper


def neighbour_midpoints(params: jax.Array, targets) -> jax.Array:
    """(T, 14): for each task the mean of its neighbours' params (T, 14) (`neighbours`; the first
    and last task's one neighbour counts twice; a lone task is its own)."""
    lower, upper, has_lower, has_upper = neighbours(targets)
    lower, upper = np.where(has_lower, lower, upper), np.where(has_upper, upper, lower)
    return 0.5 * (params[lower] + params[upper])


def tuning_leash(targets, to_neighbours: float):
    """(leash, centre_fn) of `run_search` for the per-task tuning's neighbour leash: `to_neighbours`
    per squared scale unit from the midpoint of each task's neighbours' current means in the order
    of `targets` (T,); 0: no leash (centre_fn None)."""
    if to_neighbours == 0.0:
        return 0.0, None

    return to_neighbours, lambda means: neighbour_midpoints(means, targets)


def _check_pool(env, episodes: int, what: str) -> None:
    """ValueError when one physics call of a search (on one device) plays more episodes than
    Warp's contact pool holds (`kick_env` config `warp_contacts`): its contacts would be dropped
    and every cost be wrong. A search's program is not split into chunks as rollouts are."""
    most = env.max_episodes  # None: not Warp, no pool
    if most is not None and episodes > most:
        raise ValueError(
            f"env.warp_contacts {env.config.warp_contacts} holds {most} episodes, but {what} plays {episodes} "
            f"in one physics call: set env.warp_contacts to at least {episodes * env.contacts_per_episode}"
        )


def _check_search(env, targets, population, repetitions, sigma_init, generations) -> None:
    """ValueError naming the first bad setting of a search, before anything compiles."""
    kick_scoring.check_count("population_size", population)
    if population < 2:
        raise ValueError(f"population_size must be >= 2 for CMA-ES, got {population}")
    kick_scoring.check_count("repetitions", repetitions)
    kick_scoring.check_count("generations", generations)
    if not np.isfinite(sigma_init) or sigma_init <= 0:
        raise ValueError(f"sigma_init must be > 0, got {sigma_init!r}")
    kick_env.check_targets(np.asarray(targets).tolist(), env.config.task_range)
