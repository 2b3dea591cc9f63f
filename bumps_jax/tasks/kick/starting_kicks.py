"""The keyframe kicks the kick's experts start from, before behaviour cloning and PPO.

`starting_kicks` makes each task's kick from the kick prior's record (`prior_kicks`), tuned by
CMA-ES per task; `evaluate_starting_kicks` scores them (and the kicks halfway between neighbours)
as the experts are scored; `read_starting_kicks` reads them back from a run's starting_kicks.json.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax import runio
from bumps_jax.algo import evaluate, rollout
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model
from bumps_jax.tasks.kick import scoring as kick_scoring

# Without `bc.per_task_strength`: the prior's anchor every task starts from.
COMMON_START = "long"
# The strengths that anchor is swept over to place each task's copy.
COMMON_START_STRENGTHS = np.linspace(0.1, 1.0, 19)
# The polish's initial CMA-ES step (PARAM_SCALE units; `tune.polish_generations`).
POLISH_SIGMA = 0.25


def prior_kicks(cfg, record: dict, targets, env, say=print) -> tuple[np.ndarray, dict, int]:
    """The prior family's kick (N, 14) for each of `targets` (N,) m, what was chosen, and the
    episodes the choice cost.

    The family at each target's calibrated strength, or with `tune.anchor_starts` the best of
    that and the prior's anchors on `tune.eval_repetitions` noisy kicks at the target. Without
    `bc.per_task_strength`: the anchor `COMMON_START` for every target, each copy at the strength
    where that kick rests nearest its target.
    """
    e = cfg.experts
    targets = np.asarray(targets, np.float32)
    info = {"start_targets_m": targets.tolist()}
    if not e.bc.per_task_strength:
        kick = np.asarray(record["anchors"][kick_model.ANCHORS.index(COMMON_START)], np.float32)
        starts = np.tile(kick, (len(targets), 1))
        info["common_start"] = COMMON_START
        reps = int(e.tune.eval_repetitions)
        rows = kick_scoring.strength_sweep(env, kick, COMMON_START_STRENGTHS, float(cfg.prior.target), reps)
        table = kick_model.calibration({"sweep": rows})
        starts[:, kick_model.PARAM_NAMES.index("strength")] = np.interp(targets, table[:, 1], table[:, 0])
        info["common_start_sweep"] = rows
        return starts, info, len(COMMON_START_STRENGTHS) * reps
    anchors = np.asarray(record["anchors"], np.float32)
    starts = kick_model.family_kicks(record, targets)
    if not e.tune.anchor_starts:
        return starts, info, 0
    candidates = np.concatenate([starts[:, None], np.broadcast_to(anchors, (len(targets), *anchors.shape))], 1)
    starts, chosen, costs = kick_scoring.best_starts(
        env, targets, candidates, cfg.prior.fitness, e.tune.eval_repetitions, seed=3
    )
    names = ("blend", *kick_model.ANCHORS)
    info.update(candidates=list(names), candidate_costs=costs.tolist(), chosen=[names[i] for i in chosen])
    say(f"starting kicks chosen from blend and anchors: {dict(zip(targets.tolist(), info['chosen'], strict=True))}")
    return starts, info, int(candidates.shape[0] * candidates.shape[1] * e.tune.eval_repetitions)


_TUNE_ENVS: dict = {}


def tune_env(cfg, runs: int = 1) -> kick_env.KickEnv:
    """The env the starting kicks are chosen and tuned in (cfg.env over the prior's task range),
    built once per process and env config: cmaes keeps its programs per env, so a second tuning
    in the same process (a resumed or repeated run) compiles nothing again. runs > 1: its contact
    pool `runs` times env.warp_contacts, for that many tuning runs in one batch."""
    task_range = tuple(float(t) for t in cfg.prior.task_range)
    overrides = {"task_range": task_range, "warp_contacts": int(cfg.env.warp_contacts) * int(runs)}
    key = (json.dumps(kick_env.resolved(cfg.env), sort_keys=True), task_range, int(runs))
    if key not in _TUNE_ENVS:
        _TUNE_ENVS[key] = kick_env.KickEnv(cfg.env, overrides)
    return _TUNE_ENVS[key]


def starting_kicks(cfg, record: dict, say=print, keep_dir=None) -> tuple[np.ndarray, dict]:
    """The keyframe kick (T, 14) each expert clones, and a record of how it was made.

    Each task's `prior_kicks` start, then with `tune.generations` > 0 one CMA-ES per task
    (`cmaes.tune_for_tasks`, its `tune.restarts` runs in one batch), then with
    `tune.polish_generations` > 0 the `polish`. The record counts every episode the kicks cost
    (`episodes`) and the largest jump between neighbouring tasks' kicks (`smoothness`,
    `kick_model.largest_jump`).

    keep_dir: where the starts and each finished tuning run are kept, so that a stopped tuning
    resumes at its next run (`cmaes.tune_for_tasks`); None keeps nothing.
    """
    from bumps_jax.tasks.kick import cmaes  # noqa: PLC0415

    e = cfg.experts
    targets = np.asarray(e.tasks, np.float32)
    env = tune_env(cfg)
    info = {"tasks_m": targets.tolist(), "tuned": False}
    starts, start_info, episodes = kept_starts(cfg, record, targets, env, say, keep_dir)
    info.update(start_info)
    if e.tune.generations > 0:
        t0 = time.perf_counter()
        out = cmaes.tune_for_tasks(tune_env(cfg, int(e.tune.restarts)), targets, starts, e.tune, e.tune.generations,
                                   e.tune.sigma_init, keep_dir=keep_dir, fitness=cfg.prior.fitness,
                                   say=say)  # fmt: skip
        starts = out["params"]
        episodes += out["episodes"]
        info.update(tuned=True, start_cost=out["start_cost"], tuned_cost=out["tuned_cost"],
                    improved=np.asarray(out["improved"]).tolist(), history_best_cost=out["history"],
                    restart=out["restart"], restart_costs=out["restart_costs"], keep=out["keep"],
                    runs_kept=np.asarray(out["runs_kept"]).tolist(), run_seconds=out["run_seconds"])  # fmt: skip
        if e.tune.polish_generations > 0:
            starts, info["polish"], polish_episodes = polish(env, targets, starts, cfg, keep_dir, say)
            episodes += polish_episodes
        # this call's tuning time; with runs read back from keep_dir, `run_seconds` has each run's own
        info["wall_s"] = time.perf_counter() - t0
    info["episodes"] = int(episodes)  # every episode the starting kicks cost: choice of starts and tuning
    info["smoothness"] = smoothness(starts, targets)
    info["params"] = np.asarray(starts).tolist()
    return np.asarray(starts, np.float32), info


def polish(env, targets, kicks, cfg, keep_dir=None, say=print) -> tuple[np.ndarray, dict, int]:
    """`tune.polish_generations` of one more per-task tuning from `kicks` (T, 14), chosen among the
    runs (`tune.restarts` > 1), at the initial step `POLISH_SIGMA`: the same neighbour leash, so the
    chain re-joins where neighbours came from different runs; one run from its own key, each task
    keeping the better of its kick and the polished one on fresh episodes. Returns (kicks, record,
    episodes)."""
    import ml_collections  # noqa: PLC0415

    from bumps_jax.tasks.kick import cmaes  # noqa: PLC0415

    tune = cfg.experts.tune
    # its own CMA-ES key: the seed moved far past any run's (runs fold their index into tune.seed)
    seed = int(tune.seed) + 1_000_003
    one = ml_collections.ConfigDict({**tune.to_dict(), "restarts": 1, "seed": seed})
    out = cmaes.tune_for_tasks(env, targets, kicks, one, int(tune.polish_generations), POLISH_SIGMA,
                               fitness=cfg.prior.fitness, say=say,
                               keep_dir=None if keep_dir is None else Path(keep_dir) / "polish")  # fmt: skip
    record = {
        "generations": int(tune.polish_generations),
        "sigma": POLISH_SIGMA,
        "start_cost": out["start_cost"],
        "tuned_cost": out["tuned_cost"],
        "improved": np.asarray(out["improved"]).tolist(),
        "history_best_cost": out["history"],
        "seconds": out["run_seconds"][0],
    }
    return out["params"], record, out["episodes"]


def kept_starts(cfg, record: dict, targets, env, say=print, keep_dir=None) -> tuple[np.ndarray, dict, int]:
    """`prior_kicks` at `targets`, kept in keep_dir/starts.json under a fingerprint of the config
    and prior they come from: a rerun reads them back bit for bit (scoring them again on a GPU
    can pick other starts by a last bit, and the tuning runs kept from them would not match)."""
    if keep_dir is None:
        return prior_kicks(cfg, record, targets, env, say)
    payload = {"env": kick_env.resolved(cfg.env), "experts": cfg.experts.to_dict(), "prior": cfg.prior.to_dict(),
               "record": record, "targets": np.asarray(targets, np.float32).tolist()}  # fmt: skip
    fingerprint, path = runio.fingerprint(payload), Path(keep_dir) / "starts.json"
    kept = runio.read_kept(path, fingerprint)
    if kept is not None:
        say(f"starting kicks' starts: read from {runio.shown(path)}")
        return np.asarray(kept["starts"], np.float32), kept["info"], int(kept["episodes"])
    starts, info, episodes = prior_kicks(cfg, record, targets, env, say)
    runio.write_kept(path, fingerprint, {"starts": np.asarray(starts, np.float32).tolist(), "info": info,
                                         "episodes": int(episodes)})  # fmt: skip
    return np.asarray(starts, np.float32), info, episodes


def smoothness(kicks, targets) -> dict | None:
    """`kick_model.largest_jump` of the tasks' kicks (T, 14), or None for fewer than two tasks."""
    return kick_model.largest_jump(kicks, targets) if len(set(np.asarray(targets).tolist())) > 1 else None


def evaluate_starting_kicks(cfg, env: kick_env.KickEnv, kicks) -> tuple[dict, dict | None]:
    """The tasks' starting kicks (T, 14) scored exactly as their experts are (the same tasks,
    `experts.eval` noisy kicks and seed, `evaluate`'s statistics): Table 1's "starting kicks
    (before PPO)" row, with its per-task list; and in the same program the kicks halfway between
    neighbouring tasks (None for fewer than two distinct tasks): each pair's joint trajectories
    mixed 50/50, played at the midpoint of their targets on noise of their own, with
    "targets_above_2m". A meta-policy between two training tasks does at best about this: a miss
    there means the neighbours are different kicks (`experiments/interpolation.py` replays the
    same at any target)."""
    e = cfg.experts
    targets = np.asarray(e.tasks, np.float32)
    reps, seed = int(e.eval.repetitions), int(e.eval.seed)
    tables_ = kick_model.action_tables(jnp.asarray(kicks, jnp.float32), env.n_steps, env.dt)
    order = np.argsort(targets, kind="stable")
    pairs = [(a, b) for a, b in zip(order[:-1], order[1:], strict=True) if targets[a] != targets[b]]
    lower, upper = (np.array([pair[i] for pair in pairs], int) for i in (0, 1))
    midpoints = 0.5 * (targets[lower] + targets[upper])
    mid_keys = jax.random.split(jax.random.fold_in(jax.random.key(seed), 1), len(pairs) * reps)
    keys = jnp.concatenate([rollout.repetition_keys(seed, len(targets), reps), mid_keys.reshape(len(pairs), reps)])
    params = jnp.concatenate([tables_, 0.5 * (tables_[lower] + tables_[upper])])
    metrics = evaluate.evaluate_experts(env, rollout.table_policy, params, np.concatenate([targets, midpoints]),
                                        reps, keys=keys)  # fmt: skip
    kicks_record = evaluate.tasks_record(e.tasks, {k: v[: len(targets)] for k, v in metrics.items()})
    if not pairs:
        return kicks_record, None
    mid_record = evaluate.tasks_record(midpoints, {k: v[len(targets) :] for k, v in metrics.items()})
    mid_record["targets_above_2m"] = int(sum(t["error_mean_m"] > 2.0 for t in mid_record["per_task"]))
    return kicks_record, mid_record


def read_starting_kicks(path, targets) -> dict[float, np.ndarray]:
    """Each of `targets`' (m) kick params (14,) from a run's starting_kicks.json; ValueError naming
    the path and the targets the record lacks."""
    if not targets:
        return {}
    record = runio.read_json(path, "starting kicks of an experts run")
    tasks = [float(t) for t in record["tasks_m"]]
    missing = [t for t in targets if t not in tasks]
    if missing:
        raise ValueError(f"{path}: targets {missing} not among the kicks' tasks {tasks}")
    return {t: np.asarray(record["params"][tasks.index(t)], np.float32) for t in targets}
