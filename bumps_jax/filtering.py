"""Policy filtering (the paper's Algorithm 2) and the final BUMPS results (Table 2).

A meta-policy asked for context c does not kick exactly c metres. Filtering fixes the map:
sample contexts over the task range, roll every sampled contextual policy out R times, and
for each test task deploy the context whose rollouts rest closest to the task's target,
among candidates within +- `width` m of the task (the task's own context is always one).

Efficiency: the dynamics do not depend on the target, only the scoring does. So each
candidate context is rolled out once (C x R episodes, one vmapped MJX program) and its
resting points are scored against every test task at once (a (tasks, contexts) matrix); no
rollout per (task, context) pair.

Selection and final evaluation use independent noise (`noise_keys`): the chosen policy of
every task is evaluated afresh with 100 repetitions under different keys.

Table 2's four variants: filtered 4 x 256; filtered 11 x 128; the filtered ensemble (candidates
from both nets: the argmin over the union is the better of the two nets' choices, so its
evaluation is the matching net's evaluation, task by task); 4 x 256 at a high sample rate.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from bumps_jax import evaluate, kick_env, meta, results, scene, sharding

# The paper's Table 2: (error mean m, error std m, relative error mean, relative error std).
PAPER_TABLE2 = {
    "filtered_4x256": (0.45, 0.10, 0.038, 0.011),
    "filtered_11x128": (0.43, 0.13, 0.036, 0.013),
    "filtered_ensemble": (0.40, 0.11, 0.033, 0.011),
    "high_sample_rate_4x256": (0.40, 0.09, 0.033, 0.009),
}
TABLE2_COLUMNS = ("error_mean_m", "error_std_m", "rel_error_mean", "rel_error_std")


# -- configuration ----------------------------------------------------------------------------


def default_config() -> ml_collections.ConfigDict:
    """The paper preset."""
    cfg = ml_collections.ConfigDict()
    cfg.preset = "paper"
    cfg.tasks = kick_env.meta_test_tasks()
    cfg.context_range = (7.1, 18.0)  # sampled contexts: a grid over this range ...
    cfg.context_step = 0.1  # ... 110 contexts (the paper's ~110)
    cfg.high_context_step = 0.01  # 1091 contexts: the "high sample rate" variant
    cfg.width = 1.0  # m: only contexts within +- width of a task are its candidates
    cfg.selection_repetitions = 10  # noisy rollouts per sampled context
    cfg.eval_repetitions = 100  # fresh noisy rollouts of each task's chosen policy
    cfg.seed = 0  # split into independent selection and evaluation noise
    cfg.net_seed = 0  # which network of a seed ensemble is filtered
    # Episodes per device per program call: None runs each stage as one batch (a compile per
    # batch size); an int pads and blocks every stage to that size times the devices, so one
    # compiled program per net serves all of them. 4096 episodes keep a GPU busy (the env
    # runs at ~0.4M steps/s from a batch of 4096 on an H200) and compile once instead of six.
    cfg.block = ml_collections.config_dict.FieldReference(4096, field_type=int)
    return cfg


def tiny_config() -> ml_collections.ConfigDict:
    cfg = default_config()
    cfg.preset = "tiny"
    cfg.tasks = kick_env.meta_test_tasks()[9::10]
    cfg.context_step = 1.0
    cfg.high_context_step = 0.5
    cfg.selection_repetitions = 2
    cfg.eval_repetitions = 2
    cfg.block = 24
    return cfg


PRESETS = {"paper": default_config, "tiny": tiny_config}


def make_config(preset: str = "paper", overrides: dict | None = None) -> ml_collections.ConfigDict:
    cfg = kick_env.make_preset_config(PRESETS, preset, overrides)
    validate_config(cfg)
    return cfg


def validate_config(cfg) -> None:
    """ValueError naming the first bad value; called before anything compiles."""
    check_width(cfg.width)
    task_range = kick_env.default_config().task_range
    kick_env.check_targets(cfg.tasks, task_range)
    check_contexts(cfg.context_range, task_range)
    for key in ("context_step", "high_context_step"):
        if not cfg[key] > 0:
            raise ValueError(f"{key} must be > 0, got {cfg[key]!r}")
    for key in ("selection_repetitions", "eval_repetitions"):
        if not isinstance(cfg[key], int) or cfg[key] < 1:
            raise ValueError(f"{key} must be a positive integer, got {cfg[key]!r}")
    if cfg.block is not None and (not isinstance(cfg.block, int) or cfg.block < 1):
        raise ValueError(f"block must be None or a positive integer, got {cfg.block!r}")


def check_width(width) -> float:
    if not np.isfinite(width) or width <= 0:
        raise ValueError(f"width must be > 0 m, got {width!r}")
    return float(width)


def check_contexts(contexts, task_range) -> np.ndarray:
    """Contexts as a 1-d float array, or ValueError: empty, or naming one outside the range."""
    arr = np.atleast_1d(np.asarray(contexts, np.float64))
    if arr.size == 0:
        raise ValueError("no contexts: give at least one context to filter over")
    lo, hi = task_range
    bad = ~np.isfinite(arr) | (arr < lo - 1e-9) | (arr > hi + 1e-9)
    if bad.any():
        raise ValueError(f"context {arr[bad][0]!r} m is outside the task range [{lo}, {hi}] m")
    return arr


def context_grid(low: float, high: float, step: float) -> np.ndarray:
    """low, low + step, ..., up to high (inclusive within rounding)."""
    n = int(np.floor((high - low) / step + 1e-6)) + 1
    return np.round(low + step * np.arange(n), 6)


def candidate_contexts(tasks, sampled) -> np.ndarray:
    """The sampled contexts plus every task's own context, sorted and unique."""
    both = np.concatenate([np.asarray(sampled, np.float64), np.asarray(tasks, np.float64)])
    return np.unique(np.round(both, 6))


# -- selection (pure, no simulation) ----------------------------------------------------------


def noise_keys(seed: int) -> tuple[jax.Array, jax.Array]:
    """(selection key, evaluation key): independent streams from one seed."""
    selection, evaluation = jax.random.split(jax.random.key(seed))
    return selection, evaluation


def ball_start_xy(env: kick_env.KickEnv) -> np.ndarray:
    """The ball's nominal start (2,): targets lie `target` m ahead of it along +x."""
    q = env.ids.ball_qpos
    return np.asarray(scene.stance_qpos(env.mj_model)[q : q + 2], np.float64)


def score_matrix(rest_xy, blown_up, tasks, ball_xy) -> np.ndarray:
    """Mean resting error (T, C) of each context's rollouts against each task.

    rest_xy: (C, R, 2) resting points; blown_up: (C, R) (such an episode scores as the env
    scores it: the target distance); tasks: (T,) m; ball_xy: (2,) the ball's nominal start.
    """
    rest_xy = np.asarray(rest_xy, np.float64)
    tasks = np.asarray(tasks, np.float64)
    target_xy = np.asarray(ball_xy, np.float64) + tasks[:, None] * np.array([1.0, 0.0])  # (T, 2)
    err = np.linalg.norm(rest_xy[None] - target_xy[:, None, None], axis=-1)  # (T, C, R)
    err = np.where(np.asarray(blown_up, bool)[None], tasks[:, None, None], err)
    return err.mean(axis=-1)


def select_contexts(scores, contexts, tasks, width) -> np.ndarray:
    """Index (T,) into `contexts` of each task's best candidate: lowest score within +- width.

    scores: (T, C). Every task's own context must be among `contexts` (`candidate_contexts`).
    """
    width = check_width(width)
    contexts = check_contexts(contexts, kick_env.default_config().task_range)
    tasks = np.asarray(tasks, np.float64)
    scores = np.asarray(scores, np.float64)
    if scores.shape != (len(tasks), len(contexts)):
        raise ValueError(
            f"scores must have shape (tasks, contexts) = {(len(tasks), len(contexts))}, got {scores.shape}"
        )
    gap = np.abs(contexts[None, :] - tasks[:, None])
    own = (gap < 1e-6).any(axis=1)
    if not own.all():
        raise ValueError(f"task {tasks[~own][0]!r} m has no own context among the candidates")
    masked = np.where(gap <= width + 1e-6, np.nan_to_num(scores, nan=np.inf), np.inf)
    return np.argmin(masked, axis=1)


# -- rollouts ---------------------------------------------------------------------------------


class Selection(NamedTuple):
    """One net's filtering: candidates, their rollouts, and each task's choice."""

    contexts: np.ndarray  # (C,) candidate contexts (m)
    distance: np.ndarray  # (C, R) achieved distance along the kick line (m)
    valid: np.ndarray  # (C, R)
    scores: np.ndarray  # (T, C) mean resting error of context c against task t
    chosen: np.ndarray  # (T,) index into contexts
    best_score: np.ndarray  # (T,) the chosen context's selection score (m)


def run_blocked(grid, params, contexts, targets, keys, block: int | None, multiple: int = 1) -> dict:
    """Episodes (policy params shared, P = 1 stack) for flat (B,) contexts, targets, keys.

    block None: one program call for the batch, rounded up to a multiple of `multiple` (the
    devices a sharded grid splits over); else calls of exactly `block` x `multiple` episodes,
    `block` per device (the last call padded by repeating its first episode), so one compiled
    program serves any B and each device's share stays the same whatever their number.
    Returns metrics of (B,).
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
        out.append({k: np.asarray(v)[0, :, 0] for k, v in sharding.gather(m).items()})
    return {k: np.concatenate([o[k] for o in out])[:n] for k in out[0]}


def stage_keys(key, n: int, reps: int) -> jax.Array:
    """(n * reps,) keys, row-major over (n, reps)."""
    return jax.random.split(key, n * reps)


def filter_policy(
    grid, params, contexts, tasks, width, repetitions, key, ball_xy, block=None, multiple: int = 1
) -> Selection:
    """Roll every candidate context out `repetitions` times and choose one per task.

    The env needs a target to score against; any in-range one gives the same resting points,
    so each rollout uses its own context as target.
    """
    contexts = check_contexts(contexts, kick_env.default_config().task_range)
    check_width(width)
    C, R = len(contexts), int(repetitions)
    flat_ctx = np.repeat(contexts, R)
    m = run_blocked(grid, params, flat_ctx, flat_ctx, stage_keys(key, C, R), block, multiple)
    m = {k: v.reshape(C, R) for k, v in m.items()}
    rest = np.stack([m["rest_x"], m["rest_y"]], axis=-1)
    scores = score_matrix(rest, m["blown_up"] > 0, tasks, ball_xy)
    chosen = select_contexts(scores, contexts, tasks, width)
    return Selection(
        contexts=contexts,
        distance=m["rest_x"] - ball_xy[0],
        valid=m["valid"],
        scores=scores,
        chosen=chosen,
        best_score=scores[np.arange(len(chosen)), chosen],
    )


def evaluate_chosen(grid, params, chosen_contexts, tasks, repetitions, key, block=None, multiple: int = 1) -> dict:
    """Fresh noisy episodes of each task's chosen context: metrics of (T, repetitions)."""
    tasks = np.asarray(tasks, np.float64)
    T, R = len(tasks), int(repetitions)
    flat_ctx, flat_tasks = np.repeat(np.asarray(chosen_contexts), R), np.repeat(tasks, R)
    m = run_blocked(grid, params, flat_ctx, flat_tasks, stage_keys(key, T, R), block, multiple)
    return {k: v.reshape(T, R) for k, v in m.items()}


def ensemble_metrics(sel_a: Selection, sel_b: Selection, eval_a: dict, eval_b: dict):
    """The ensemble over two nets' candidates: per task, the net whose best candidate scored lower.

    The argmin over the union of candidates is the better of the two nets' argmins, so its
    fresh evaluation is that net's evaluation of the same (net, context) for the task.
    Returns (use_b (T,) bool, metrics of (T, R)).
    """
    use_b = sel_b.best_score < sel_a.best_score
    return use_b, {k: np.where(use_b[:, None], eval_b[k], eval_a[k]) for k in eval_a}


def table2_row(metrics: dict, n_contexts: int) -> dict:
    """Errors over tasks of each task's mean error (m and relative), from metrics of (T, R)."""
    per_task = evaluate.summarise_tasks(metrics)
    return {
        "error_mean_m": float(per_task["error_mean_m"].mean()),
        "error_std_m": float(per_task["error_mean_m"].std()),
        "rel_error_mean": float(per_task["rel_error_mean"].mean()),
        "rel_error_std": float(per_task["rel_error_mean"].std()),
        "accuracy_mean": float(per_task["accuracy"].mean()),
        "n_contexts": int(n_contexts),
        "n_tasks": int(len(per_task["accuracy"])),
    }


def table2_markdown(rows: dict) -> str:
    lines = [
        "# Table 2: BUMPS after policy filtering (this run vs the paper)",
        "",
        "| variant | contexts | error m | paper error m | rel. error | paper rel. error |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        p = PAPER_TABLE2.get(name)
        paper_err = f"{p[0]:.2f} +- {p[1]:.2f}" if p else "-"
        paper_rel = f"{100 * p[2]:.1f}% +- {100 * p[3]:.1f}" if p else "-"
        lines.append(
            f"| {name} | {r['n_contexts']} | {r['error_mean_m']:.2f} +- {r['error_std_m']:.2f} | "
            f"{paper_err} | {100 * r['rel_error_mean']:.1f}% +- {100 * r['rel_error_std']:.1f} | "
            f"{paper_rel} |"
        )
    return "\n".join(lines) + "\n"


# -- plots ------------------------------------------------------------------------------------


def plot_error_vs_target(path, curves: dict) -> Path:
    """Final error vs target distance. curves: name -> (targets (n,), mean error (n,) m)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for name, (targets, err) in curves.items():
        ax.plot(targets, err, marker=".", label=name)
    ax.set_xlabel("target distance (m)")
    ax.set_ylabel("mean final error (m)")
    ax.grid(alpha=0.3)
    ax.legend()
    return results.save_figure(fig, path)


def plot_context_map(path, maps: dict) -> Path:
    """Achieved distance vs context. maps: name -> (contexts (C,), distance (C, R) m)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 5))
    lo, hi = kick_env.default_config().task_range
    ax.plot([lo, hi], [lo, hi], "k--", lw=1, label="achieved = context")
    for name, (contexts, distance) in maps.items():
        d = np.asarray(distance)
        ax.errorbar(contexts, d.mean(axis=1), yerr=d.std(axis=1), fmt=".", capsize=2, label=name)
    ax.set_xlabel("context (m)")
    ax.set_ylabel("achieved distance (m)")
    ax.grid(alpha=0.3)
    ax.legend()
    return results.save_figure(fig, path)


# -- the stage --------------------------------------------------------------------------------


def run(cfg, meta_dir, out_dir, verbose: bool = True) -> dict:
    """Filter the meta-policies of a meta-training run (`meta_dir`); write Table 2 and plots."""
    t_start = time.perf_counter()
    say = print if verbose else (lambda *a, **k: None)
    meta_dir, out_dir = Path(meta_dir), Path(out_dir)
    meta_cfg = ml_collections.ConfigDict(json.loads((meta_dir / "config.json").read_text()))
    env = kick_env.KickEnv()
    ball_xy = ball_start_xy(env)
    tasks = np.asarray(cfg.tasks, np.float64)
    sel_key, eval_key = noise_keys(cfg.seed)
    # Episodes are split over every device (a mesh of one on a single GPU: the same program).
    mesh = sharding.device_mesh()
    n_dev = mesh.size
    low = candidate_contexts(tasks, context_grid(*cfg.context_range, cfg.context_step))
    high = candidate_contexts(tasks, context_grid(*cfg.context_range, cfg.high_context_step))

    selections, evals, rows, timings = {}, {}, {}, {}
    for net in meta.NETS:
        depth, width = meta_cfg.nets[net]
        apply_fn, params = meta.load_policy(meta_dir / net, depth, width, meta_cfg.train)
        params = jax.tree.map(lambda a: a[cfg.net_seed : cfg.net_seed + 1], params)
        grid = evaluate.grid_fn(env, apply_fn, mesh)
        variants = [(f"filtered_{net[5:]}", low)]
        if net == "meta_4x256":
            variants.append(("high_sample_rate_4x256", high))
        for name, contexts in variants:
            t0 = time.perf_counter()
            sel = filter_policy(
                grid, params, contexts, tasks, cfg.width, cfg.selection_repetitions, sel_key, ball_xy, cfg.block, n_dev
            )
            chosen = sel.contexts[sel.chosen]
            m = evaluate_chosen(grid, params, chosen, tasks, cfg.eval_repetitions, eval_key, cfg.block, n_dev)
            selections[name], evals[name] = sel, m
            rows[name] = table2_row(m, len(contexts))
            rollouts = len(contexts) * cfg.selection_repetitions + len(tasks) * cfg.eval_repetitions
            wall = time.perf_counter() - t0  # selection + fresh evaluation, compiling included
            timings[name] = {"wall_s": wall, "rollouts": rollouts, "rollouts_per_s": rollouts / wall}
            say(
                f"{name}: {len(contexts)} contexts, error {rows[name]['error_mean_m']:.2f} m"
                f" ({100 * rows[name]['rel_error_mean']:.1f}%) in {time.perf_counter() - t0:.1f} s"
            )
    a, b = selections["filtered_4x256"], selections["filtered_11x128"]
    use_b, m = ensemble_metrics(a, b, evals["filtered_4x256"], evals["filtered_11x128"])
    rows["filtered_ensemble"] = table2_row(m, len(a.contexts) + len(b.contexts))
    evals["filtered_ensemble"] = m
    rows = {k: rows[k] for k in PAPER_TABLE2}

    chosen = {name: sel.contexts[sel.chosen].tolist() for name, sel in selections.items()}
    chosen["filtered_ensemble_uses_11x128"] = use_b.tolist()
    payload = {
        "rows": rows,
        "paper": {k: dict(zip(TABLE2_COLUMNS, v, strict=True)) for k, v in PAPER_TABLE2.items()},
        "tasks": tasks.tolist(),
        "chosen_contexts": chosen,
        "per_task_error_m": {k: evaluate.summarise_tasks(v)["error_mean_m"].tolist() for k, v in evals.items()},
        "config": json.loads(cfg.to_json()),
        "meta_run": str(meta_dir),
        "timings": timings,
        **results.provenance(cfg.preset, time.perf_counter() - t_start, physics_dt_s=env.physics_dt),
    }
    results.write_json(out_dir / "table2.json", meta.json_safe(payload))
    (out_dir / "table2.md").write_text(table2_markdown(rows))

    curves = _unfiltered_curves(meta_dir)
    curves["BUMPS filtered ensemble"] = (tasks, np.asarray(payload["per_task_error_m"]["filtered_ensemble"]))
    plot_error_vs_target(out_dir / "error_vs_target.png", curves)
    maps = {n: (s.contexts, s.distance) for n, s in selections.items() if n != "high_sample_rate_4x256"}
    plot_context_map(out_dir / "context_map.png", maps)
    return payload


def _unfiltered_curves(meta_dir: Path) -> dict:
    """Experts' and unfiltered meta-policies' per-task errors from the meta run's table1.json."""
    path = meta_dir / "table1.json"
    if not path.exists():
        return {}
    per_task = json.loads(path.read_text()).get("per_task", {})
    curves = {}
    if "experts" in per_task:
        curves["experts"] = (per_task["experts"]["tasks"], per_task["experts"]["error_mean_m"])
    for net in meta.NETS:
        if net in per_task:
            curves[f"{net} unfiltered"] = (per_task["tasks"], per_task[net]["error_mean_m"])
    return curves
