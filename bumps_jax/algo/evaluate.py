"""Scoring policies as the paper does: per-task statistics and Table 1 rows from final metrics.

Metrics come from `rollout` programs as arrays of (n_tasks, n_reps).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax.algo import rollout
from bumps_jax.envs import base as task_env

# The paper counts a meta-policy's error only on tasks where it kicks validly this often.
ACCURACY_THRESHOLD = 0.7


def summarise_tasks(metrics: dict) -> dict:
    """Per-task statistics from metrics of shape (n_tasks, n_reps): arrays of (n_tasks,).

    accuracy = fraction of valid kicks; error = final error over all repetitions (an invalid
    kick still leaves the ball somewhere, and its distance to the target is its error). A task
    whose env reports no relative error (`rel_error`: the cheetah's targets include 0) has none.
    """
    err = np.asarray(metrics["final_error"], np.float64)
    out = {
        "accuracy": np.asarray(metrics["valid"], np.float64).mean(axis=1),
        "error_mean_m": err.mean(axis=1),
        "error_std_m": err.std(axis=1),
    }
    if "rel_error" in metrics:
        out["rel_error_mean"] = np.asarray(metrics["rel_error"], np.float64).mean(axis=1)
    if "return" in metrics:  # the episode's undiscounted return, where the env keeps it: what meta-RL papers report
        out["return_mean"] = np.asarray(metrics["return"], np.float64).mean(axis=1)
    return out


def table_row(per_task: dict, threshold: float = ACCURACY_THRESHOLD) -> dict:
    """One row of the paper's Table 1 from `summarise_tasks` output.

    accuracy mean/std over tasks; error mean/std over tasks whose accuracy exceeds
    `threshold` (the paper's rule), and the error mean over all tasks.
    """
    acc = per_task["accuracy"]
    err = per_task["error_mean_m"]
    kept = acc > threshold
    return {
        "accuracy_mean": float(acc.mean()),
        "accuracy_std": float(acc.std()),
        "error_mean_m": float(err[kept].mean()) if kept.any() else None,  # no task above the threshold
        "error_std_m": float(err[kept].std()) if kept.any() else None,
        "error_mean_all_m": float(err.mean()),
        "tasks_above_threshold": int(kept.sum()),
        "n_tasks": int(len(acc)),
        **mean_return(per_task),
    }


def mean_return(per_task: dict) -> dict:
    """{"return_mean": the mean over tasks of their mean episode return} where the env keeps one, else {}."""
    return {"return_mean": float(per_task["return_mean"].mean())} if "return_mean" in per_task else {}


# -- single-task experts (Table 1, first row) ------------------------------------------------


def evaluate_experts(env: task_env.ContextualEnv, apply_fn, params, tasks, n_reps: int = 100, seed: int = 0,
                     keys=None) -> dict:  # fmt: skip
    """Each expert on its own task, `n_reps` noisy kicks each, in one vmapped program.

    params: a pytree with a leading task axis (N, ...); tasks: (N,) m, or (N, K) for a vector
    context (`env.CONTEXT_SIZE` K > 1); keys: (N, n_reps) episode keys (default:
    `rollout.repetition_keys(seed, N, n_reps)`). Returns the final metrics as numpy arrays of
    shape (N, n_reps).
    """
    tasks = np.asarray(tasks, np.float32)
    if tasks.ndim != len(task_env.context_shape(getattr(env, "CONTEXT_SIZE", 1))) + 1 or len(tasks) == 0:
        raise ValueError(f"tasks must be a non-empty 1-d list of distances, got {tasks!r}")
    if n_reps < 1:
        raise ValueError(f"n_reps must be >= 1, got {n_reps!r}")
    env.check_targets(tasks)
    # Expert i on task i only (grid_fn would score every expert on every task).
    program = rollout.matched_fn(env, apply_fn)
    targets = jnp.asarray(tasks)
    if keys is None:
        keys = rollout.repetition_keys(seed, len(tasks), n_reps)
    if keys.shape != (len(tasks), n_reps):
        raise ValueError(f"keys must have shape ({len(tasks)}, {n_reps}), got {keys.shape}")
    metrics = program(params, targets, targets, keys)
    return jax.tree_util.tree_map(np.asarray, metrics)


def experts_record(tasks, metrics: dict, env_steps: int) -> dict:
    """The results-contract record of `results/experts.json` (without provenance).

    metrics: final metrics of shape (n_tasks, n_reps) from `evaluate_experts`; env_steps:
    PPO env steps per expert.
    """
    return {**tasks_record(tasks, metrics), "env_steps": int(env_steps)}


def tasks_record(tasks, metrics: dict) -> dict:
    """A Table 1 row of one policy per task (`table_row`) with its per-task list, from final
    metrics of shape (n_tasks, n_reps) (`evaluate_experts`). A vector context is a list."""
    per_task = summarise_tasks(metrics)
    row = table_row(per_task)
    rel = per_task.get("rel_error_mean")  # None: the task reports no relative error
    return {
        "tasks_m": [task_env.context_json(t) for t in tasks],
        "per_task": [
            {
                "target_m": task_env.context_json(t),
                "accuracy": float(per_task["accuracy"][i]),
                "error_mean_m": float(per_task["error_mean_m"][i]),
                "error_std_m": float(per_task["error_std_m"][i]),
                "rel_error_mean": None if rel is None else float(rel[i]),
            }
            for i, t in enumerate(tasks)
        ],
        **row,
        "rel_error_mean": None if rel is None else float(rel.mean()),
        "n_reps": int(np.asarray(metrics["valid"]).shape[1]),
    }


# -- one family of experts ----------------------------------------------------------------------


def nearest_others(tasks, k: int = 2) -> list[list[int]]:
    """For each context, the indices of the `k` nearest other contexts (Euclidean; ties by index)."""
    t = np.asarray(tasks, np.float64).reshape(len(tasks), -1)
    dist = np.linalg.norm(t[:, None] - t[None], axis=-1)
    np.fill_diagonal(dist, np.inf)
    return [sorted(np.argsort(row, kind="stable")[: min(k, len(t) - 1)].tolist()) for row in dist]


# An expert (or a centre candidate) runs on its back where a posture's `flipped_fraction`, the
# share of its steps flipped, is above this.
FLIPPED = 0.5


def family_check(env: task_env.ContextualEnv, tasks, metrics: dict, posture: dict | None = None) -> dict:
    """Whether the experts are one family, before any net is cloned from them: per expert, what
    its episodes achieved (`env.ACHIEVED`), its error on its own context and at its nearest
    neighbours' (`nearest_others`), and the env's `posture` statistics ({name: (E,)}); in all,
    whether what they achieve rises with the context (a scalar one) and how many spend most
    of their steps flipped (a posture's `flipped_fraction` above `FLIPPED`).
    metrics: final metrics of (E, R) (`evaluate_experts`)."""
    posture = posture or {}
    tasks = np.asarray(tasks, np.float64)
    achieved = np.asarray(metrics[env.ACHIEVED], np.float64).mean(axis=1)
    rows = []
    for i, others in enumerate(nearest_others(tasks)):
        episodes = {k: np.asarray(v)[i] for k, v in metrics.items()}
        rows.append({
            "target_m": task_env.context_json(tasks[i]),
            "achieved": task_env.context_json(achieved[i]),
            "error_m": float(np.asarray(metrics["final_error"])[i].mean()),
            "neighbours_m": [task_env.context_json(tasks[j]) for j in others],
            "error_at_neighbours_m": [float(np.mean(env.error_against(episodes, tasks[j]))) for j in others],
            **{k: float(v[i]) for k, v in posture.items()},
        })  # fmt: skip
    out = {"per_task": rows}
    if tasks.ndim == 1:
        order = np.argsort(tasks)
        out["achieved_rises"] = bool(np.all(np.diff(achieved[order]) > 0))
    if "flipped_fraction" in posture:
        out["flipped_experts"] = int((np.asarray(posture["flipped_fraction"]) > FLIPPED).sum())
    return out


def family_table(check: dict, unit: str) -> str:
    """`family_check` as a markdown table, one row per expert, and its verdicts."""
    fmt = task_env.format_context
    extra = [k for k in check["per_task"][0] if k not in FAMILY_ROW_KEYS]
    head = [f"target ({unit})", "achieved", "error", "error at the nearest neighbours", *extra]
    lines = ["## Family check", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in check["per_task"]:
        near = ", ".join(
            f"{fmt(c)}: {e:.2f}" for c, e in zip(r["neighbours_m"], r["error_at_neighbours_m"], strict=True)
        )
        cells = [fmt(r["target_m"]), fmt(r["achieved"]), f"{r['error_m']:.3f}", near, *(f"{r[k]:.2f}" for k in extra)]
        lines.append("| " + " | ".join(cells) + " |")
    verdicts = {k: v for k, v in check.items() if k != "per_task"}
    return "\n".join([*lines, "", ", ".join(f"{k}: {v}" for k, v in verdicts.items()), ""])


FAMILY_ROW_KEYS = ("target_m", "achieved", "error_m", "neighbours_m", "error_at_neighbours_m")
