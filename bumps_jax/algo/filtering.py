"""Policy filtering (the paper's Algorithm 2): candidate contexts, their scores against every test
task, each task's choice, and the blocked rollouts that feed them.

A meta-policy asked for context c does not kick exactly c metres. Filtering fixes the map:
sample contexts over the task range, roll every sampled contextual policy out R times, and
for each test task deploy the context whose rollouts rest closest to the task's target,
among candidates within +- `width` m of the task (the task's own context is always one). A
vector context (a goal position, K numbers) samples a K-D grid over the box of the task range,
and a task's candidates are the contexts within Euclidean distance `width` of it.

The dynamics do not depend on the target, only the scoring does: each candidate context is
rolled out once (C x R episodes) and its resting points, as the env reports them (`distance`
along the kick line, `lateral`), are scored against every task at once by the env's own rule
(`env.error_against`: `scoring`): a (tasks, contexts) matrix, no rollout per (task, context) pair.

Selection and the final evaluation draw independent noise (`noise_keys`): each task's chosen
context is evaluated afresh. The ensemble of two nets takes, per task, the net whose best
candidate scored lower: the argmin over the union of candidates.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax.algo import evaluate

# -- candidates ---------------------------------------------------------------------------------


def check_width(width) -> float:
    """The neighbourhood's radius (m) as a float, or ValueError naming it."""
    if not np.isfinite(width) or width <= 0:
        raise ValueError(f"width must be > 0 m, got {width!r}")
    return float(width)


def check_contexts(contexts, task_range) -> np.ndarray:
    """Contexts (C,) as a float array, or ValueError: empty, or naming one outside `task_range`.
    Vector contexts (C, K) stay (C, K), each coordinate checked against the range (a box)."""
    arr = np.atleast_1d(np.asarray(contexts, np.float64))
    if arr.size == 0:
        raise ValueError("no contexts: give at least one context to filter over")
    lo, hi = task_range
    bad = ~np.isfinite(arr) | (arr < lo - 1e-9) | (arr > hi + 1e-9)
    if bad.any():
        first = arr[bad.reshape(len(arr), -1).any(axis=1)][0]
        raise ValueError(f"context {first!r} m is outside the task range [{lo}, {hi}] m")
    return arr


def context_grid(low: float, high: float, step: float, size: int = 1) -> np.ndarray:
    """low, low + step, ..., up to high (inclusive within rounding): (n,) m. size K > 1: the
    K-D grid of those values along every axis of the box [low, high]^K, row-major: (n^K, K)."""
    n = int(np.floor((high - low) / step + 1e-6)) + 1
    axis = np.round(low + step * np.arange(n), 6)
    if size == 1:
        return axis
    return np.stack(np.meshgrid(*[axis] * size, indexing="ij"), axis=-1).reshape(-1, size)


def candidate_contexts(tasks, sampled) -> np.ndarray:
    """The sampled contexts plus every task's own context, sorted and unique: (C,) m; vector
    contexts (C, K), sorted row by row."""
    sampled = np.asarray(sampled, np.float64)
    both = np.concatenate([sampled, np.asarray(tasks, np.float64).reshape(-1, *sampled.shape[1:])])
    if both.ndim == 1:
        return np.unique(np.round(both, 6))
    return np.unique(np.round(both, 6), axis=0)


def context_gaps(contexts, tasks) -> np.ndarray:
    """(T, C) distance of each context from each task: |c - t| for scalars (C,) and (T,), the
    Euclidean distance for vectors (C, K) and (T, K)."""
    contexts, tasks = np.asarray(contexts, np.float64), np.asarray(tasks, np.float64)
    if contexts.ndim == 1:
        return np.abs(contexts[None, :] - tasks[:, None])
    return np.linalg.norm(contexts[None, :, :] - tasks.reshape(-1, 1, contexts.shape[1]), axis=-1)


def noise_keys(seed: int) -> tuple[jax.Array, jax.Array]:
    """(selection key, evaluation key): independent streams from one seed."""
    selection, evaluation = jax.random.split(jax.random.key(seed))
    return selection, evaluation


def stage_keys(key, n: int, reps: int) -> jax.Array:
    """(n * reps,) keys, row-major over (n, reps)."""
    return jax.random.split(key, n * reps)


# -- scores and choices (pure, no simulation) -----------------------------------------------------


def candidate_mask(contexts, tasks, width, task_range) -> np.ndarray:
    """(T, C) bool: context c is a candidate of task t (within distance `width` of it: +- width
    for scalars, a ball for vectors; `context_gaps`). Every task's own context must be among
    `contexts` (`candidate_contexts`)."""
    width = check_width(width)
    contexts = check_contexts(contexts, task_range)
    tasks = np.asarray(tasks, np.float64)
    gap = context_gaps(contexts, tasks)
    own = (gap < 1e-6).any(axis=1)
    if not own.all():
        raise ValueError(f"task {tasks[~own][0]!r} m has no own context among the candidates")
    return gap <= width + 1e-6


def select_contexts(scores, contexts, tasks, width, task_range) -> np.ndarray:
    """Index (T,) into `contexts` (C,) of each task's best candidate: lowest score within +- width.

    scores: (T, C). Every task's own context must be among `contexts` (`candidate_contexts`).
    """
    mask = candidate_mask(contexts, tasks, width, task_range)
    scores = np.asarray(scores, np.float64)
    if scores.shape != mask.shape:
        raise ValueError(f"scores must have shape (tasks, contexts) = {mask.shape}, got {scores.shape}")
    return np.argmin(np.where(mask, np.nan_to_num(scores, nan=np.inf), np.inf), axis=1)


class Halving(NamedTuple):
    """Successive halving's choice (`successive_halving`)."""

    chosen: np.ndarray  # (T,) index into the contexts
    best_score: np.ndarray  # (T,) the chosen context's score on all its rollouts (m)
    scores: np.ndarray  # (T, C) each context's score on all its rollouts against each task (inf: none)
    reached: np.ndarray  # (C,) rollouts each context got
    rollouts: int  # rollouts spent: reached.sum()


def check_rungs(rungs, keep) -> tuple[tuple[int, ...], float]:
    """Successive halving's rungs (increasing positive ints) and keep fraction in (0, 1), or
    ValueError naming the bad one."""
    rungs = tuple(rungs)
    if (
        not rungs
        or any(isinstance(r, bool) or int(r) != r or r < 1 for r in rungs)
        or any(b <= a for a, b in zip(rungs, rungs[1:], strict=False))
    ):
        raise ValueError(f"halving rungs must be increasing positive integers, got {rungs}")
    if not 0.0 < keep < 1.0:
        raise ValueError(f"halving keep must be in (0, 1), got {keep!r}")
    return tuple(int(r) for r in rungs), float(keep)


def successive_halving(errors_of, candidates, rungs, keep: float) -> Halving:
    """Each task's context by successive halving over its candidates (pure: the rollouts come
    from `errors_of`).

    errors_of(index (n,), start, stop) -> errors (T, n, stop - start): rollouts start .. stop-1
    of contexts `index`, each scored against every task (m). candidates: (T, C) bool
    (`candidate_mask`). Rung k: every context that is still a candidate of some task is rolled
    out up to rungs[k] times in all; each task's score of a context is the mean over all its
    rollouts so far; after every rung but the last, each task keeps its best ceil(keep x n) of
    its n surviving candidates (at least one; ties to the lower index). After the last rung each
    task takes its best survivor.
    """
    rungs, keep = check_rungs(rungs, keep)
    alive = np.array(candidates, bool)
    if alive.ndim != 2 or not alive.any(axis=1).all():
        raise ValueError(f"candidates must be (tasks, contexts) bool with one candidate per task at least, "
                         f"got shape {alive.shape}")  # fmt: skip
    n_tasks, n_contexts = alive.shape
    sums, reached, done = np.zeros(alive.shape), np.zeros(n_contexts, int), 0
    for k, rung in enumerate(rungs):
        index = np.flatnonzero(alive.any(axis=0))
        errors = np.asarray(errors_of(index, done, rung), np.float64)
        if errors.shape != (n_tasks, len(index), rung - done):
            raise ValueError(f"errors_of gave shape {errors.shape}, expected {(n_tasks, len(index), rung - done)}")
        sums[:, index] += np.nan_to_num(errors, nan=np.inf).sum(axis=2)
        reached[index], done = rung, rung
        scores = np.where(reached > 0, sums / np.maximum(reached, 1), np.inf)
        if k == len(rungs) - 1:
            break
        for t in range(n_tasks):
            mine = np.flatnonzero(alive[t])
            kept = mine[np.argsort(scores[t, mine], kind="stable")[: max(1, math.ceil(keep * len(mine) - 1e-9))]]
            alive[t] = False
            alive[t, kept] = True
    chosen = np.argmin(np.where(alive, scores, np.inf), axis=1)
    return Halving(chosen, scores[np.arange(n_tasks), chosen], scores, reached, int(reached.sum()))


def scoring(env) -> dict:
    """`filter_policy`'s scoring by `env`'s own rule: {"errors": errors(metrics of (C, R, ...), tasks
    (T,)) -> (T, C, R) by `env.error_against`, "achieved": the metric holding what an episode achieved}."""

    def errors(metrics: dict, tasks) -> np.ndarray:
        tasks = np.asarray(tasks, np.float64)  # (T,) or (T, K)
        return env.error_against(metrics, tasks.reshape(len(tasks), 1, 1, *tasks.shape[1:]))

    return {"errors": errors, "achieved": env.ACHIEVED}


class Selection(NamedTuple):
    """One net's filtering: candidates, their rollouts, and each task's choice."""

    contexts: np.ndarray  # (C,) candidate contexts (m); (C, K) for a vector context
    # (C, R) what each rollout achieved: the env's `ACHIEVED` metric (the kick's resting distance
    # along the kick line, m; the cheetah's mean velocity, m/s)
    distance: np.ndarray
    valid: np.ndarray  # (C, R)
    scores: np.ndarray  # (T, C) mean final error of context c against task t (m)
    chosen: np.ndarray  # (T,) index into contexts
    best_score: np.ndarray  # (T,) the chosen context's selection score (m)
    rollouts: int  # selection rollouts spent


class Ensemble(NamedTuple):
    """The filtered ensemble of two nets (a, b)."""

    use_b: np.ndarray  # (T,) bool: net b's best candidate scored lower
    best_score: np.ndarray  # (T,) the winning candidate's selection score (m)
    metrics: dict  # fresh evaluation of (T, R): the winning net's, task by task


def ensemble_choice(sel_a: Selection, sel_b: Selection, eval_a: dict, eval_b: dict) -> Ensemble:
    """Per task, the net whose best candidate scored lower; eval_*: metrics of (T, R).

    The argmin over the union of candidates is the better of the two nets' argmins, so its
    fresh evaluation is that net's evaluation of the same (net, context) for the task.
    """
    use_b = sel_b.best_score < sel_a.best_score
    # use_b (T,) against metrics of (T, R, ...): a metric may carry per-step values (the cheetah's).
    metrics = {k: np.where(use_b.reshape(-1, *[1] * (np.ndim(eval_a[k]) - 1)), eval_b[k], eval_a[k]) for k in eval_a}
    return Ensemble(use_b, np.where(use_b, sel_b.best_score, sel_a.best_score), metrics)


def table2_row(metrics: dict, n_contexts: int, best_score, rollouts: int) -> dict:
    """One Table 2 row: errors over tasks of each task's mean fresh error (m and relative), from
    metrics of (T, R); beside them the chosen contexts' mean selection score best_score (T,) (m),
    the gap (fresh minus selection: what the selection overrated) and the selection's cost in
    rollouts."""
    per_task = evaluate.summarise_tasks(metrics)
    selection = float(np.mean(best_score))
    rel = per_task.get("rel_error_mean")  # None: the task reports no relative error
    return {
        "error_mean_m": float(per_task["error_mean_m"].mean()),
        "error_std_m": float(per_task["error_mean_m"].std()),
        "rel_error_mean": None if rel is None else float(rel.mean()),
        "rel_error_std": None if rel is None else float(rel.std()),
        "accuracy_mean": float(per_task["accuracy"].mean()),
        "selection_error_m": selection,
        "selection_gap_m": float(per_task["error_mean_m"].mean()) - selection,
        "n_contexts": int(n_contexts),
        "rollouts": int(rollouts),
        "n_tasks": int(len(per_task["accuracy"])),
        **evaluate.mean_return(per_task),
    }


# -- rollouts -------------------------------------------------------------------------------------


def run_blocked(grid, params, contexts, targets, keys, block: int | None, multiple: int = 1, progress=None) -> dict:
    """Episodes of one policy (a `rollout.grid_fn` program, params a stack of P = 1) for flat
    contexts (B,), targets (B,), keys (B,): metrics of (B,). Vector contexts and targets: (B, K).

    block None: one program call for the batch, rounded up to a multiple of `multiple` (the
    devices a sharded grid splits over); else calls of exactly `block` x `multiple` episodes,
    `block` per device (the last call padded by repeating its first episode), so one compiled
    program serves any B and each device's share stays the same whatever their number.
    progress: called (episodes done, B) after each call, if given.
    """
    n = len(contexts)
    size = -(-n // multiple) * multiple if block is None else int(block) * multiple
    out = []
    for start in range(0, n, size):
        idx = np.arange(start, start + size)
        idx = np.where(idx < n, idx, start)
        m = grid(
            params, jnp.asarray(contexts[idx], jnp.float32), jnp.asarray(targets[idx], jnp.float32), keys[idx][:, None]
        )
        out.append({k: np.asarray(v)[0, :, 0] for k, v in m.items()})
        if progress is not None:
            progress(min(start + size, n), n)
    return {k: np.concatenate([o[k] for o in out])[:n] for k in out[0]}


def filter_policy(
    grid, params, contexts, tasks, width, repetitions: int, key, *, task_range, block=None, multiple: int = 1,
    rungs=None, keep: float = 0.25, errors, achieved: str,
) -> Selection:  # fmt: skip
    """Roll every candidate context (C,) out `repetitions` times and choose one per task (T,);
    with `rungs`, successive halving instead (`successive_halving`, keeping `keep`).

    The env needs a target to score against; the episode does not depend on it, so each rollout
    uses its own context as target, and `errors(metrics of (C, R), tasks (T,)) -> (T, C, R)`
    scores it against every task; `achieved`: the metric a Selection keeps of each rollout (both
    from `scoring(env)`).
    """
    contexts = check_contexts(contexts, task_range)
    check_width(width)
    if rungs is not None:
        return _halving_policy(grid, params, contexts, tasks, width, key, task_range, block, multiple, rungs, keep,
                               errors, achieved)  # fmt: skip
    C, R = len(contexts), int(repetitions)
    flat_ctx = np.repeat(contexts, R, axis=0)
    m = run_blocked(grid, params, flat_ctx, flat_ctx, stage_keys(key, C, R), block, multiple)
    m = {k: v.reshape(C, R, *v.shape[1:]) for k, v in m.items()}
    scores = errors(m, tasks).mean(axis=-1)  # (T, C)
    chosen = select_contexts(scores, contexts, tasks, width, task_range)
    return Selection(
        contexts=contexts,
        distance=m[achieved],
        valid=m["valid"],
        scores=scores,
        chosen=chosen,
        best_score=scores[np.arange(len(chosen)), chosen],
        rollouts=C * R,
    )


def _halving_policy(grid, params, contexts, tasks, width, key, task_range, block, multiple, rungs, keep,
                    errors, achieved: str) -> Selection:  # fmt: skip
    """`filter_policy` by successive halving. Rollout j of context c has key (c, j) of a
    (C, rungs[-1]) grid from `key` (`stage_keys`), whatever rung it is drawn in: one rung of R
    rollouts replays the fixed selection's episodes. distance and valid hold the first rung (NaN
    for a context that is no task's candidate)."""
    rungs, keep = check_rungs(rungs, keep)
    tasks = np.asarray(tasks, np.float64)
    keys = stage_keys(key, len(contexts), rungs[-1]).reshape(len(contexts), rungs[-1])
    first = {}  # the first rung's (C, rungs[0], ...) achieved outcome (a vector for some tasks) and valid

    def errors_of(index, start, stop):
        r = stop - start
        flat_ctx = np.repeat(contexts[index], r, axis=0)
        m = run_blocked(grid, params, flat_ctx, flat_ctx, keys[index, start:stop].reshape(-1), block, multiple)
        m = {k: v.reshape(len(index), r, *v.shape[1:]) for k, v in m.items()}
        if start == 0:
            for k in (achieved, "valid"):
                first.setdefault(k, np.full((len(contexts), *m[k].shape[1:]), np.nan))[index] = m[k]
        return errors(m, tasks)

    out = successive_halving(errors_of, candidate_mask(contexts, tasks, width, task_range), rungs, keep)
    return Selection(contexts, first[achieved], first["valid"], out.scores, out.chosen, out.best_score, out.rollouts)


def evaluate_chosen(
    grid, params, chosen_contexts, tasks, repetitions, key, block=None, multiple: int = 1, progress=None
) -> dict:
    """Fresh noisy episodes of each task's chosen context (T,) (vectors: (T, K)): metrics of (T,
    repetitions). progress: as `run_blocked`'s."""
    tasks = np.asarray(tasks, np.float64)
    T, R = len(tasks), int(repetitions)
    flat_ctx, flat_tasks = np.repeat(np.asarray(chosen_contexts), R, axis=0), np.repeat(tasks, R, axis=0)
    m = run_blocked(grid, params, flat_ctx, flat_tasks, stage_keys(key, T, R), block, multiple, progress)
    return {k: v.reshape(T, R, *v.shape[1:]) for k, v in m.items()}
