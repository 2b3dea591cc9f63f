"""Stage 4: policy filtering of the meta-policies, and Table 2 (BUMPS step 3).

Table 2's four variants: the (4, 256) and the (11, 128) net filtered over the grid of
`filter.context_step`; their ensemble (per task, the net whose best candidate scored lower);
the (4, 256) net over the finer grid of `filter.high_context_step`. Every net is the seed
`filter.net_seed` of its meta-training run; episodes are split over every device.

Writes run_dir/filter/: table2.json, table2.md, error_vs_target.png, context_map.png.
"""

from __future__ import annotations

import time
from pathlib import Path

import jax
import numpy as np

from bumps_jax import config, resumable, runio
from bumps_jax import records as env_records
from bumps_jax.algo import bc, evaluate, filtering, sharding
from bumps_jax.envs import base as task_env
from bumps_jax.pipeline import programs as meta_programs
from bumps_jax.pipeline.stages import meta as meta_stage
from bumps_jax.report import tables
from bumps_jax.tasks import registry as tasks

OUTPUT = "table2.json"
# Variant -> (net, context grid): "low" steps by filter.context_step, "high" by high_context_step.
VARIANTS = {
    "filtered_4x256": ("meta_4x256", "low"),
    "high_sample_rate_4x256": ("meta_4x256", "high"),
    "filtered_11x128": ("meta_11x128", "low"),
}
ENSEMBLE = ("filtered_ensemble", "filtered_4x256", "filtered_11x128")  # name, its two nets' variants


def inputs(cfg, run_dir: Path) -> dict:
    """Table 1 of the meta stage and each paper net's checkpoint folder; ValueError naming a
    missing one, or a meta run made under another env or meta config than cfg's."""
    meta_dir = Path(run_dir) / "meta"
    table1 = meta_dir / meta_stage.OUTPUT
    record = runio.read_json(table1, "the meta-policies' record: run meta-train first")
    env_records.check_same_env(record.get("env"), config.resolved_env(cfg), f"the meta record {table1}")
    if "config" not in record:
        raise ValueError(f"{table1} does not record its meta config: rerun meta-train")
    wanted = {k: cfg.meta[k].to_dict() for k in ("nets", "train")}
    diff = env_records.differing_keys({k: record["config"].get(k) for k in wanted}, wanted)
    if diff:
        shown = ", ".join(f"meta.{k}" for k in diff)
        raise ValueError(f"{table1} was trained under other meta settings ({shown}): rerun meta-train")
    out = {"table1": table1}
    for net in meta_stage.NETS:
        if net not in cfg.meta.nets:
            raise ValueError(f"filtering needs meta.nets.{net} (Table 2 filters the paper's two nets)")
        out[net] = meta_dir / net / "checkpoints"
        if not out[net].is_dir():
            raise ValueError(f"{out[net]}: no checkpoint folder: run meta-train first")
    return out


def filter_variant(cfg, grid, params, contexts, ways: int):
    """Selection over `contexts` (C,) (vectors: (C, K)) and the fresh evaluation of each task's
    choice: (filtering.Selection, metrics of (T, R), Table 2 row, timings)."""
    f = cfg.filter
    env = meta_programs.stage_env(cfg.env, cfg.task)
    targets = task_env.as_contexts(f.tasks, env.CONTEXT_SIZE)
    sel_key, eval_key = filtering.noise_keys(f.seed)
    t0 = time.perf_counter()
    rungs = tuple(f.halving_rungs) if f.selection == "halving" else None
    scoring = filtering.scoring(env)
    sel = filtering.filter_policy(
        grid, params, contexts, targets, f.width, f.selection_repetitions, sel_key,
        task_range=tuple(cfg.env.task_range), block=f.block, multiple=ways, rungs=rungs, keep=f.halving_keep,
        **scoring,
    )  # fmt: skip
    chosen = sel.contexts[sel.chosen]
    # Fresh episodes: the evaluation key is independent of every selection rollout's (`noise_keys`).
    metrics = filtering.evaluate_chosen(grid, params, chosen, targets, f.eval_repetitions, eval_key, f.block, ways)
    row = filtering.table2_row(metrics, len(contexts), sel.best_score, sel.rollouts)
    rollouts = sel.rollouts + len(targets) * f.eval_repetitions
    wall = time.perf_counter() - t0  # selection and fresh evaluation, compiling included
    return sel, metrics, row, {"wall_s": wall, "rollouts": rollouts, "rollouts_per_s": rollouts / wall}


def run(cfg, run_dir: Path, say=print) -> dict:
    """The stage: every variant of Table 2; writes table2.json, table2.md and the two plots
    under run_dir/filter and returns the record."""
    t_start = time.perf_counter()
    run_dir = Path(run_dir)
    inputs(cfg, run_dir)
    f, stage_dir = cfg.filter, run_dir / "filter"
    env = meta_programs.stage_env(cfg.env, cfg.task)
    targets = task_env.as_contexts(f.tasks, env.CONTEXT_SIZE)  # (T,), or (T, K) for a vector context
    mesh = sharding.device_mesh(impl=cfg.env.impl)  # a mesh of one on a single device: the same program
    grids = {  # a vector context's grid spans the box context_range^K
        name: filtering.candidate_contexts(targets, filtering.context_grid(*f.context_range, step, env.CONTEXT_SIZE))
        for name, step in (("low", f.context_step), ("high", f.high_context_step))
    }
    selections, evals, rows, timings = {}, {}, {}, {}
    unit, sizes = env.UNIT, (env.context_observation_size, env.action_size)
    obs_norm = meta_stage.run_obs_norm(run_dir)
    pace, done = resumable.Clock(len(VARIANTS)), 0  # progress over the variants, with an ETA from their pace
    for net in meta_stage.NETS:
        depth, width = cfg.meta.nets[net]
        _, params = bc.load_policy(run_dir / "meta" / net, depth, width, cfg.meta.train, *sizes, obs_norm)
        params = jax.tree.map(lambda a: a[f.net_seed : f.net_seed + 1], params)
        grid = meta_programs.meta_grid(cfg.env, depth, width, mesh, cfg.task, obs_norm)  # one program per architecture
        for name in (v for v, (n, _) in VARIANTS.items() if n == net):
            contexts = grids[VARIANTS[name][1]]
            say(f"filter: variant {done + 1}/{len(VARIANTS)} {name} ({len(contexts)} contexts x {len(targets)} "
                f"tasks){'' if done == 0 else ', ' + pace.tick(done)}", flush=True)  # fmt: skip
            out = filter_variant(cfg, grid, params, contexts, sharding.ways(mesh))
            done += 1
            if done == 1:
                pace.tick(done)  # the first variant compiles: the ETA counts from the second
            selections[name], evals[name], rows[name], timings[name] = out
            rel = rows[name]["rel_error_mean"]
            say(
                f"{name}: {len(contexts)} contexts, error {rows[name]['error_mean_m']:.2f} {unit}"
                + ("" if rel is None else f" ({100 * rel:.1f}%)")
                + f", at selection {rows[name]['selection_error_m']:.2f} {unit}"
                f" ({rows[name]['rollouts']} selection rollouts), in {timings[name]['wall_s']:.1f} s"
            )
    name, a, b = ENSEMBLE
    ens = filtering.ensemble_choice(selections[a], selections[b], evals[a], evals[b])
    n_contexts, rollouts = (rows[a][k] + rows[b][k] for k in ("n_contexts", "rollouts"))
    rows[name] = filtering.table2_row(ens.metrics, n_contexts, ens.best_score, rollouts)
    evals[name] = ens.metrics
    rows = {k: rows[k] for k in tables.PAPER_TABLE2}
    selection_scores = {n: sel.best_score.tolist() for n, sel in selections.items()}
    selection_scores[name] = ens.best_score.tolist()
    chosen = {n: sel.contexts[sel.chosen].tolist() for n, sel in selections.items()}
    chosen["filtered_ensemble_uses_11x128"] = ens.use_b.tolist()
    payload = {
        "rows": rows,
        "paper": {k: dict(zip(tables.TABLE2_COLUMNS, v, strict=True)) for k, v in tables.PAPER_TABLE2.items()},
        "tasks": targets.tolist(),
        "chosen_contexts": chosen,
        "per_task_error_m": {k: evaluate.summarise_tasks(v)["error_mean_m"].tolist() for k, v in evals.items()},
        # Each task's chosen context's score on the selection rollouts, beside its fresh error above.
        "per_task_selection_error_m": selection_scores,
        "config": cfg.filter.to_dict(),
        "meta_run": str(run_dir / "meta"),
        "timings": timings,
        **runio.provenance(cfg.preset, time.perf_counter() - t_start, config.resolved_env(cfg)),
    }
    report = tasks.get(cfg.task).report
    if not report.paper_rows:  # the paper's numbers are of its own task only
        del payload["paper"]
    payload.update(task=cfg.task, unit=unit)
    runio.write_json(stage_dir / OUTPUT, payload)
    runio.write_text(stage_dir / "table2.md", report.table2(rows, unit))
    write_plots(stage_dir, run_dir / "meta" / meta_stage.OUTPUT, payload, selections, tuple(cfg.env.task_range),
                report.axes)  # fmt: skip
    return runio.json_safe(payload)


# -- plots --------------------------------------------------------------------------------------


def write_plots(stage_dir: Path, table1: Path, payload: dict, selections: dict, task_range, labels) -> None:
    """error_vs_target.png (experts, unfiltered nets, the filtered ensemble) and context_map.png.
    labels: the task's (context, error, achieved) axis names (`Report.axes`)."""
    curves = unfiltered_curves(runio.read_json(table1))
    curves["BUMPS filtered ensemble"] = (payload["tasks"], payload["per_task_error_m"]["filtered_ensemble"])
    plot_error_vs_target(stage_dir / "error_vs_target.png", curves, labels[:2])
    maps = {n: (s.contexts, s.distance) for n, s in selections.items() if n != "high_sample_rate_4x256"}
    context_label = labels[0].replace("target", "context")
    plot_context_map(stage_dir / "context_map.png", maps, task_range, (context_label, labels[2]))


def unfiltered_curves(table1: dict) -> dict:
    """name -> (targets, mean error) of the experts (and their starts, where the record has them)
    and the unfiltered nets from Table 1's record."""
    per_task = table1.get("per_task", {})
    curves = {}
    for row, entry in per_task.items():  # the experts' rows: those with tasks of their own
        if isinstance(entry, dict) and "tasks" in entry:
            curves[tables.ROW_LABELS.get(row, row)] = (entry["tasks"], entry["error_mean_m"])
    for net in meta_stage.NETS:
        if net in per_task:
            curves[f"{net} unfiltered"] = (per_task["tasks"], per_task[net]["error_mean_m"])
    return curves


def plot_error_vs_target(path, curves: dict, labels=("target", "mean final error")) -> Path:
    """Final error vs target. curves: name -> (targets (n,), mean error (n,)); labels: (x, y) axis
    names. Vector targets (n, K) are placed by their Euclidean norm."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, ax = plt.subplots(figsize=(7, 4))
    vector = False
    for name, (targets, err) in curves.items():
        x, style = np.asarray(targets, dtype=float), "-"
        if x.ndim > 1:  # points, not a curve: targets of one norm lie apart
            x, vector, style = np.linalg.norm(x, axis=-1), True, "none"
        ax.plot(x, np.asarray(err, dtype=float), marker=".", linestyle=style, label=name)
    ax.set_xlabel(f"|{labels[0]}|" if vector else labels[0])
    ax.set_ylabel(labels[1])
    ax.grid(alpha=0.3)
    ax.legend()
    return runio.save_figure(fig, path)


def plot_context_map(path, maps: dict, task_range, labels=("context (m)", "achieved distance (m)")) -> Path:
    """Achieved distance (or the task's achieved quantity) vs context. maps: name -> (contexts (C,),
    achieved (C, R)); labels: (x, y) axis names. Vector contexts (C, K) with achieved (C, R, K), in
    their first two coordinates: each context's mean achieved point, coloured by the context's
    direction from the range's middle (hue) and sized by its distance from it; the contexts in grey.
    A family that reaches its contexts redraws their pattern."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, ax = plt.subplots(figsize=(6, 5))
    lo, hi = task_range
    if any(np.ndim(c) > 1 for c, _ in maps.values()):
        middle = (lo + hi) / 2.0
        for i, (name, (contexts, achieved)) in enumerate(maps.items()):
            c, a = np.asarray(contexts)[:, :2], np.nanmean(np.asarray(achieved, dtype=float), axis=1)[:, :2]
            rel = c - middle
            hue = (np.arctan2(rel[:, 1], rel[:, 0]) / (2 * np.pi)) % 1.0
            size = 4 + 30 * np.linalg.norm(rel, axis=1) / max(hi - middle, 1e-9)
            if i == 0:
                ax.scatter(c[:, 0], c[:, 1], s=2, c="0.8", label="contexts")
            ax.scatter(a[:, 0], a[:, 1], s=size, c=hue, cmap="hsv", vmin=0.0, vmax=1.0, alpha=0.7,
                       marker="os^"[i % 3], label=f"{name}: mean {labels[1]}")  # fmt: skip
        ax.set(xlim=(lo, hi), ylim=(lo, hi), aspect="equal", title=f"mean {labels[1]} by {labels[0]}")
        ax.grid(alpha=0.3)
        ax.legend()
        return runio.save_figure(fig, path)
    ax.plot([lo, hi], [lo, hi], "k--", lw=1, label="achieved = context")
    for name, (contexts, distance) in maps.items():
        d = np.asarray(distance)
        ax.errorbar(contexts, d.mean(axis=1), yerr=d.std(axis=1), fmt=".", capsize=2, label=name)
    ax.set_xlabel(labels[0])
    ax.set_ylabel(labels[1])
    ax.grid(alpha=0.3)
    ax.legend()
    return runio.save_figure(fig, path)
