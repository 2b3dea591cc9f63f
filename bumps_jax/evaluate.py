"""Rolling out deterministic kick policies and scoring them as the paper does (Table 1).

A policy here is `apply_fn(params, obs) -> action (22,)`. Observations are the env's
(phase, context); the context a policy sees may differ from the task the env scores, which is
what policy filtering needs (a meta-policy asked for 11.3 m may kick best for 11.0 m).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax import kick_env, sharding

# The paper counts a meta-policy's error only on tasks where it kicks validly this often.
ACCURACY_THRESHOLD = 0.7


def episode_fn(env: kick_env.KickEnv, apply_fn):
    """A pure fn (params, context, target, key) -> final metrics of one noisy episode.

    context, target: scalars (m). The policy sees `context` in its observation; the env
    scores the kick against `target`. vmap it over whatever varies (experts, contexts, reps).
    """
    lo, hi = env.config.task_range

    def episode(params, context, target, key):
        state = env.reset(key, target)
        ctx = (context - lo) / (hi - lo)

        def body(state, _):
            obs = state.obs.at[1].set(ctx)
            state = env.step(state, apply_fn(params, obs))
            return state, None

        state, _ = jax.lax.scan(body, state, None, env.n_steps)
        return state.metrics

    return episode


def summarise_tasks(metrics: dict) -> dict:
    """Per-task statistics from metrics of shape (n_tasks, n_reps): arrays of (n_tasks,).

    accuracy = fraction of valid kicks; error = final error over all repetitions (an invalid
    kick still leaves the ball somewhere, and its distance to the target is its error).
    """
    err = np.asarray(metrics["final_error"], np.float64)
    return {
        "accuracy": np.asarray(metrics["valid"], np.float64).mean(axis=1),
        "error_mean_m": err.mean(axis=1),
        "error_std_m": err.std(axis=1),
        "rel_error_mean": np.asarray(metrics["rel_error"], np.float64).mean(axis=1),
    }


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
        "error_mean_m": float(err[kept].mean()) if kept.any() else float("nan"),
        "error_std_m": float(err[kept].std()) if kept.any() else float("nan"),
        "error_mean_all_m": float(err.mean()),
        "tasks_above_threshold": int(kept.sum()),
        "n_tasks": int(len(acc)),
    }


def repetition_keys(seed: int, n_tasks: int, n_reps: int) -> jax.Array:
    """(n_tasks, n_reps) independent episode keys."""
    return jax.random.split(jax.random.key(seed), n_tasks * n_reps).reshape(n_tasks, n_reps)


def _recording_step(env, apply_fn, params, ctx, state, _):
    """One control step that also returns what the policy saw and did: (obs (2,), action (22,))."""
    obs = state.obs.at[1].set(ctx)
    action = apply_fn(params, obs)
    return env.step(state, action), (obs, action)


def trajectory_fn(env: kick_env.KickEnv, apply_fn):
    """A pure fn (params, context, target, key) -> (obs (T, obs_size), actions (T, 22), metrics).

    Like `episode_fn`, but it also records each step's observation (with the context in
    obs[1], as the policy saw it) and the policy's action: the behaviour-cloning data.
    """
    lo, hi = env.config.task_range

    def trajectory(params, context, target, key):
        ctx = (context - lo) / (hi - lo)
        body = functools.partial(_recording_step, env, apply_fn, params, ctx)
        state, (obs, actions) = jax.lax.scan(body, env.reset(key, target), None, env.n_steps)
        return obs, actions, state.metrics

    return trajectory


def grid_fn(env: kick_env.KickEnv, apply_fn, mesh=None, method: str = "jit"):
    """Jitted (params (P, ...), contexts (n,), targets (n,), keys (n, R)) -> metrics of (P, n, R).

    Every policy of a stack (seeds, networks of one architecture) on every (context, target)
    pair, R noisy repetitions each: one XLA program. With a `mesh` the pairs are split over
    its devices (n must then be a multiple of the mesh size; `filtering.run_blocked` pads).
    """
    episode = episode_fn(env, apply_fn)
    over_reps = jax.vmap(episode, in_axes=(None, None, None, 0))
    over_pairs = jax.vmap(over_reps, in_axes=(None, 0, 0, 0))
    over_policies = jax.vmap(over_pairs, in_axes=(0, None, None, None))
    if mesh is None:
        return jax.jit(over_policies)
    return sharding.over_batch(over_policies, mesh, (False, True, True, True), out_axis=1, method=method)


def _return_step(env, apply_fn, params, ctx, carry, _):
    """One control step that adds the reward to the carried return: ((state, ret), None)."""
    state, ret = carry
    state = env.step(state, apply_fn(params, state.obs.at[1].set(ctx)))
    return (state, ret + state.reward), None


def return_fn(env: kick_env.KickEnv, apply_fn):
    """A pure fn (params, target, key) -> (undiscounted return, final metrics) of one episode.

    The policy sees its own target as context; what PPO maximises, for learning curves.
    """
    lo, hi = env.config.task_range

    def episode(params, target, key):
        body = functools.partial(_return_step, env, apply_fn, params, (target - lo) / (hi - lo))
        (state, ret), _ = jax.lax.scan(body, (env.reset(key, target), jnp.zeros(())), None, env.n_steps)
        return ret, state.metrics

    return episode


# -- single-task experts (Table 1, first row) ------------------------------------------------


def evaluate_experts(env: kick_env.KickEnv, apply_fn, params, tasks, n_reps: int = 100, seed: int = 0) -> dict:
    """Each expert on its own task, `n_reps` noisy kicks each, in one vmapped program.

    params: a pytree with a leading task axis (N, ...); tasks: (N,) m. Returns the final
    metrics as numpy arrays of shape (N, n_reps).
    """
    tasks = np.asarray(tasks, np.float32)
    if tasks.ndim != 1 or len(tasks) == 0:
        raise ValueError(f"tasks must be a non-empty 1-d list of distances, got {tasks!r}")
    if n_reps < 1:
        raise ValueError(f"n_reps must be >= 1, got {n_reps!r}")
    kick_env.check_targets(tasks, env.config.task_range)
    # Expert i on task i only (grid_fn would score every expert on every task).
    over_reps = jax.vmap(episode_fn(env, apply_fn), in_axes=(None, None, None, 0))
    program = jax.jit(jax.vmap(over_reps, in_axes=(0, 0, 0, 0)))
    targets = jnp.asarray(tasks)
    metrics = program(params, targets, targets, repetition_keys(seed, len(tasks), n_reps))
    return jax.tree_util.tree_map(np.asarray, metrics)


def experts_record(tasks, metrics: dict, env_steps: int) -> dict:
    """The results-contract record of `results/experts.json` (without provenance).

    metrics: final metrics of shape (n_tasks, n_reps) from `evaluate_experts`; env_steps:
    PPO env steps per expert.
    """
    per_task = summarise_tasks(metrics)
    row = table_row(per_task)
    return {
        "tasks_m": [float(t) for t in tasks],
        "per_task": [
            {
                "target_m": float(t),
                "accuracy": float(per_task["accuracy"][i]),
                "error_mean_m": float(per_task["error_mean_m"][i]),
                "error_std_m": float(per_task["error_std_m"][i]),
                "rel_error_mean": float(per_task["rel_error_mean"][i]),
            }
            for i, t in enumerate(tasks)
        ],
        **row,
        "rel_error_mean": float(per_task["rel_error_mean"].mean()),
        "n_reps": int(np.asarray(metrics["valid"]).shape[1]),
        "env_steps": int(env_steps),
    }


def experts_markdown(record: dict) -> str:
    """Table 1's first row (and the per-task numbers) as markdown."""
    lines = [
        "| model | accuracy | error mean (m) | error std (m) | rel. error |",
        "|---|---|---|---|---|",
        f"| single-task experts | {record['accuracy_mean']:.2f} +- {record['accuracy_std']:.2f} "
        f"| {record['error_mean_m']:.2f} | {record['error_std_m']:.2f} | {100 * record['rel_error_mean']:.1f}% |",
        "",
        f"{record['tasks_above_threshold']}/{record['n_tasks']} tasks above accuracy {ACCURACY_THRESHOLD} "
        f"(the error columns count only those); {record['n_reps']} kicks per task, "
        f"{record['env_steps']} PPO env steps per expert.",
        "",
        "| target (m) | accuracy | error mean (m) | error std (m) |",
        "|---|---|---|---|",
    ]
    for row in record["per_task"]:
        lines.append(
            f"| {row['target_m']:.1f} | {row['accuracy']:.2f} | {row['error_mean_m']:.2f} | {row['error_std_m']:.2f} |"
        )
    return "\n".join(lines) + "\n"


def write_experts_table(record: dict, out_dir) -> tuple:
    """Write out_dir/experts.json (atomically) and out_dir/experts.md. Returns both paths."""
    from pathlib import Path

    from bumps_jax import results

    out_dir = Path(out_dir)
    json_path = results.write_json(out_dir / "experts.json", record)
    md_path = out_dir / "experts.md"
    tmp = md_path.with_suffix(".md.tmp")
    tmp.write_text(experts_markdown(record))
    tmp.replace(md_path)
    return json_path, md_path
