"""The held-out stage (`python -m bumps_jax evaluate --heldout`, and part of `reproduce`): a
finished run's policies on target distances off the 0.1 m grid, with noise that no other stage draws.

The meta-test tasks and their seed were also used to choose settings (the learning rate, the
physics step, the starting kicks); the `heldout` config section is used for nothing else. On each
held-out target it scores

    experts_nearest    the expert of the nearest training task, its context set to the target
    meta_<net>         each meta-policy asked for the target itself (unfiltered)
    filtered_<net>     each meta-policy filtered for the target: the filter's context grid and
                       the target within +- filter.width, selected on their own episodes
    filtered_ensemble  per target, the net whose best candidate scored lower

Selection and the fresh evaluation draw independent noise from `heldout.seed`
(`filtering.noise_keys`); every variant's fresh kicks share the same noise, target by target.
Writes run_dir/heldout/heldout.json and heldout.md.

`evaluate --dev` runs the same evaluation from the `dev` section (development targets and noise,
for design choices) into run_dir/dev/dev.json; it is not a stage of the pipeline.
"""

from __future__ import annotations

import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax import config, runio
from bumps_jax import records as env_records
from bumps_jax.algo import bc, evaluate, filtering, rollout, sharding
from bumps_jax.pipeline import programs as meta_programs
from bumps_jax.pipeline.stages import experts as experts_stage
from bumps_jax.pipeline.stages import filter as filter_stage
from bumps_jax.pipeline.stages import meta as meta_stage
from bumps_jax.report import tables
from bumps_jax.tasks import registry as tasks

OUTPUT = "heldout.json"
ENSEMBLE = ("filtered_ensemble", "filtered_4x256", "filtered_11x128")


def filtered_name(net: str) -> str:
    return "filtered_" + net.removeprefix("meta_")


def inputs(cfg, run_dir: Path) -> dict:
    """The finished stages the evaluation reads; ValueError naming the first missing one, or a
    record made under another env config or experts' task list than cfg's."""
    run_dir = Path(run_dir)
    experts_json = run_dir / "experts" / experts_stage.OUTPUT
    record = runio.read_json(experts_json, "the experts' record: run train-experts first")
    resolve = tasks.get(cfg.task).resolved_env
    env_records.check_same_env(
        record.get("env"), config.resolved_env(cfg), f"the experts record {experts_json}", resolve
    )
    if [float(t) for t in record.get("tasks_m", [])] != [float(t) for t in cfg.experts.tasks]:
        made = record.get("preset")
        hint = f" (a run of preset {made!r}: add --preset {made})" if made and made != cfg.preset else ""
        raise ValueError(f"{experts_json} trained the tasks {record.get('tasks_m')}, not experts.tasks of this config"
                         + hint)  # fmt: skip
    final = run_dir / "experts" / "final_params"
    if not final.is_dir():
        raise ValueError(f"{final}: no trained experts: run train-experts first")
    out = {"experts": experts_json, **filter_stage.inputs(cfg, run_dir)}
    table2 = run_dir / "filter" / filter_stage.OUTPUT
    record = runio.read_json(table2, "the filter stage's record: run filter first")
    env_records.check_same_env(record.get("env"), config.resolved_env(cfg), f"the filter record {table2}", resolve)
    return {**out, "filter": table2}


def nearest_tasks(tasks, targets) -> np.ndarray:
    """Index (T,) into tasks (E,) of each target's nearest training task (the lower one on a tie)."""
    return np.argmin(np.abs(np.asarray(tasks, np.float64)[None, :] - np.asarray(targets, np.float64)[:, None]), axis=1)


def row(metrics: dict) -> dict:
    """One held-out row from metrics of (T, R): accuracy and error over every target, and the error
    over targets of accuracy > evaluate.ACCURACY_THRESHOLD as Table 1 counts it."""
    per = evaluate.summarise_tasks(metrics)
    table1 = evaluate.table_row(per)
    return {
        "error_mean_m": float(per["error_mean_m"].mean()),
        "error_std_m": float(per["error_mean_m"].std()),
        "accuracy_mean": table1["accuracy_mean"],
        "accuracy_std": table1["accuracy_std"],
        "rel_error_mean": float(per["rel_error_mean"].mean()),
        "error_mean_above_threshold_m": table1["error_mean_m"],
        "targets_above_threshold": table1["tasks_above_threshold"],
        "per_target_error_m": per["error_mean_m"].tolist(),
        "per_target_accuracy": per["accuracy"].tolist(),
    }


SECTIONS = {"heldout": "Held-out targets", "dev": "Development targets"}  # config section -> title


def run(cfg, run_dir: Path, say=print, section: str = "heldout") -> dict:
    """Every variant on the targets of config `section` ("heldout", or "dev"); writes
    run_dir/<section>/<section>.json and <section>.md."""
    t_start = time.perf_counter()
    run_dir = Path(run_dir)
    inputs(cfg, run_dir)
    runio.check_writable(run_dir / section)
    h, f = cfg[section], cfg.filter
    targets = np.asarray(h.targets, np.float64)
    sel_key, eval_key = filtering.noise_keys(h.seed)
    mesh = sharding.device_mesh(impl=cfg.env.impl)
    family = experts_stage.load_family(cfg, run_dir)
    nearest = nearest_tasks(family.tasks, targets)
    say(f"{section}: {len(targets)} targets x {h.repetitions} episodes; experts of the nearest task (compiling first)",
        flush=True)  # fmt: skip
    env = meta_programs.stage_env(cfg.env, cfg.task)
    params = jax.tree.map(lambda a: jnp.asarray(a)[nearest], family.params)
    keys = filtering.stage_keys(eval_key, len(targets), h.repetitions).reshape(len(targets), h.repetitions)
    tj = jnp.asarray(targets, jnp.float32)  # the same noise as evaluate_chosen's, below
    metrics = {
        "experts_nearest": jax.tree.map(np.asarray, rollout.matched_fn(env, family.apply_fn)(params, tj, tj, keys))
    }
    contexts = filtering.candidate_contexts(targets, filtering.context_grid(*f.context_range, f.context_step))
    selections = {}
    for net in meta_stage.NETS:
        say(f"{net}: unfiltered, then filtered over {len(contexts)} contexts", flush=True)
        metrics[net], metrics[filtered_name(net)], selections[filtered_name(net)] = meta_variants(
            cfg, run_dir, net, targets, contexts, (sel_key, eval_key), mesh, h
        )
    name, a, b = ENSEMBLE
    ens = filtering.ensemble_choice(selections[a], selections[b], metrics[a], metrics[b])
    metrics[name] = ens.metrics
    payload = {
        "targets_m": targets.tolist(),
        "seed": int(h.seed),
        "repetitions": int(h.repetitions),
        "selection": f.selection,
        "selection_repetitions": int(h.selection_repetitions),
        "rows": rows_of(metrics, selections, ens, len(contexts)),
        "error_rule": "error_mean_m: the mean over every target of its mean final error (invalid episodes included)",
        "nearest_expert_task_m": family.tasks[nearest].tolist(),
        "chosen_contexts": {k: s.contexts[s.chosen].tolist() for k, s in selections.items()},
        "filtered_ensemble_uses_11x128": ens.use_b.tolist(),
        "section": section,
        "config": {
            section: h.to_dict(),
            "filter": {k: f[k] for k in ("context_range", "context_step", "width", "net_seed")},
        },  # fmt: skip
        "run": str(run_dir),
        **runio.provenance(cfg.preset, time.perf_counter() - t_start, config.resolved_env(cfg)),
    }
    runio.write_json(run_dir / section / f"{section}.json", payload)
    lines = tables.heldout_lines(payload)
    runio.write_text(run_dir / section / f"{section}.md", f"# {SECTIONS[section]}\n\n" + "\n".join(lines) + "\n")
    for line in lines:
        say(line)
    return runio.json_safe(payload)


def meta_variants(cfg, run_dir: Path, net: str, targets, contexts, noise_keys, mesh, h):
    """One meta-policy on the evaluation's targets: (its unfiltered metrics, its filtered metrics,
    the selection), each metric of (T, h.repetitions) on the evaluation noise (`h`: the heldout or
    dev section). The filter stage's selection rule; "fixed" spends h.selection_repetitions per context."""
    f = cfg.filter
    sel_key, eval_key = noise_keys
    depth, width = cfg.meta.nets[net]
    # The nets' input normalisation as the meta stage trained them (None: the kick's (phase, target) as they are).
    obs_norm = meta_stage.run_obs_norm(run_dir)
    _, params = bc.load_policy(run_dir / "meta" / net, depth, width, cfg.meta.train, obs_norm=obs_norm)
    params = jax.tree.map(lambda a: a[f.net_seed : f.net_seed + 1], params)
    grid = meta_programs.meta_grid(cfg.env, depth, width, mesh, cfg.task, obs_norm)
    reps = int(h.repetitions)
    unfiltered = filtering.evaluate_chosen(grid, params, targets, targets, reps, eval_key, f.block, sharding.ways(mesh))
    sel = filtering.filter_policy(
        grid, params, contexts, targets, f.width, h.selection_repetitions, sel_key,
        task_range=tuple(cfg.env.task_range), block=f.block, multiple=sharding.ways(mesh),
        rungs=tuple(f.halving_rungs) if f.selection == "halving" else None, keep=f.halving_keep,
        **filtering.scoring(meta_programs.stage_env(cfg.env, cfg.task)),
    )  # fmt: skip
    chosen = sel.contexts[sel.chosen]
    filtered = filtering.evaluate_chosen(grid, params, chosen, targets, reps, eval_key, f.block, sharding.ways(mesh))
    return unfiltered, filtered, sel


def rows_of(metrics: dict, selections: dict, ens, n_contexts: int) -> dict:
    """The record's rows: `row` of every variant, the filtered ones with their selection error,
    contexts and rollouts (the ensemble: both nets' contexts and rollouts)."""
    name, a, b = ENSEMBLE
    rows = {key: row(metrics[key]) for key in ("experts_nearest", *meta_stage.NETS, a, b, name)}
    for key, sel in selections.items():
        rows[key].update(selection_error_m=float(sel.best_score.mean()), n_contexts=n_contexts,
                         rollouts=int(sel.rollouts))  # fmt: skip
    rows[name].update(selection_error_m=float(ens.best_score.mean()), n_contexts=2 * n_contexts,
                      rollouts=rows[a]["rollouts"] + rows[b]["rollouts"])  # fmt: skip
    return rows
