"""Stage 3: the experts behaviour-cloned into the contextual meta-policies, and Table 1 (BUMPS step 2).

1. Dataset: every expert (one per meta-training task) is rolled out `meta.dataset.repetitions`
   times on its own task (the paper: once, with the noise off); each step's (observation,
   action) is kept, the observation's context being the expert's task. Saved as dataset.npz
   and reused when the stage resumes.
2. The nets of `meta.nets` (`bc.MetaPolicy`) are trained on it, resumable, all in one stacked
   program (`bc.train_nets`); with several processes each trains its share of the nets.
3. Evaluation, unfiltered: every net on `meta.eval.tasks` x `meta.eval.repetitions` noisy kicks
   with context = target (`rollout.grid_fn`); the experts' row comes from their own record.

Writes run_dir/meta/: dataset.npz, <net>/progress.csv, <net>/checkpoints/ (only the newest once
table1.json is written), table1.json, table1.md.
"""

from __future__ import annotations

import copy
import time
from pathlib import Path

import jax
import numpy as np

from bumps_jax import config, resumable, runio
from bumps_jax import records as env_records
from bumps_jax.algo import bc, evaluate, rollout, sharding
from bumps_jax.envs import base as task_env
from bumps_jax.pipeline import programs as meta_programs
from bumps_jax.pipeline.stages import experts as experts_stage
from bumps_jax.tasks import registry as tasks

OUTPUT = "table1.json"
NETS = ("meta_4x256", "meta_11x128")  # the paper's two meta-policies, in its order
# The experts' record's keys that make their Table 1 row.
ROW_KEYS = (
    "accuracy_mean", "accuracy_std", "error_mean_m", "error_std_m", "error_mean_all_m", "tasks_above_threshold",
    "n_tasks",
)  # fmt: skip
PER_TASK_KEYS = ("target_m", "accuracy", "error_mean_m")  # each row's per-task list


def inputs(cfg, run_dir: Path) -> dict:
    """The experts' record and their trained params; ValueError naming a missing or bad one."""
    stage = Path(run_dir) / "experts"
    record_path = stage / experts_stage.OUTPUT
    record = runio.read_json(record_path, "the experts' record: run train-experts first")
    env_records.check_same_env(record.get("env"), config.resolved_env(cfg), f"the experts' record {record_path}")
    experts_row(record, record_path)
    params = stage / "final_params"
    if not params.is_dir():
        raise ValueError(f"{params}: no such folder (the trained experts): run train-experts first")
    return {"experts": record_path, "experts_params": params}


def experts_row(record: dict, path) -> tuple[dict, dict | None]:
    """The experts' Table 1 row from their record (`evaluate.experts_record`, or its
    "starting_kicks" entry), and their per-task errors {"tasks", "error_mean_m"} if it lists
    them; ValueError naming `path` if it has no row."""
    if "accuracy_mean" not in record:
        raise ValueError(f"{path}: no experts row (accuracy_mean missing): rerun train-experts")
    row = {k: record[k] for k in ROW_KEYS if k in record}
    per_task = None
    if isinstance(record.get("per_task"), list):
        row["per_task"] = [{k: r[k] for k in PER_TASK_KEYS} for r in record["per_task"]]
        per_task = {
            "tasks": [r["target_m"] for r in record["per_task"]],
            "error_mean_m": [r["error_mean_m"] for r in record["per_task"]],
        }
    return {**row, "source": Path(path).relative_to(Path(path).parents[1]).as_posix()}, per_task  # in the run dir


def per_task_list(tasks, summary: dict) -> list[dict]:
    """A row's per-task list [{target_m, accuracy, error_mean_m}] from `evaluate.summarise_tasks`."""
    return [
        {
            "target_m": task_env.context_json(t),
            "accuracy": float(summary["accuracy"][i]),
            "error_mean_m": float(summary["error_mean_m"][i]),
        }
        for i, t in enumerate(tasks)
    ]


def net_names(nets) -> list[str]:
    """The nets of `meta.nets`, the paper's first in its order, then any others sorted."""
    return [n for n in NETS if n in nets] + sorted(n for n in nets if n not in NETS)


# -- the dataset --------------------------------------------------------------------------------


def dataset_env(cfg):
    """The env the experts are recorded in: cfg.env, noise-free when they run once each (the paper)."""
    overrides = {}
    if cfg.meta.dataset.repetitions == 1:
        overrides = tasks.get(cfg.task).noise_free(cfg.env)
    # A copy: `locked_config` shares the nested sections of the config it is given.
    return tasks.make_env(cfg.task, copy.deepcopy(cfg.env), overrides)


def pairs(targets: np.ndarray, obs, actions) -> bc.Dataset:
    """A bc.Dataset from episodes' (obs (E, K, T, O), actions (E, K, T, A)) at targets (E,) or (E, C)."""
    n = obs.shape[0] * obs.shape[1] * obs.shape[2]
    rest = targets.shape[1:]  # () for a scalar context, (C,) for a vector one
    task = np.broadcast_to(targets.reshape(-1, 1, 1, *rest), obs.shape[:3] + rest).reshape(n, *rest)
    return bc.Dataset(
        obs=np.asarray(obs, np.float32).reshape(n, obs.shape[-1]),
        actions=np.asarray(actions, np.float32).reshape(n, actions.shape[-1]),
        task=np.asarray(task, np.float32),
    )


def clipped(env, actions, clip: bool):
    """Labels clipped to the env's action bound (`ACTION_BOUND`) when `clip` and the env has one."""
    bound = env.ACTION_BOUND
    return np.clip(actions, -bound, bound) if clip and bound is not None else actions


def collect_dataset(env, family, repetitions: int, seed: int = 0, action_noise: float = 0.0,
                    clip_labels: bool = False) -> tuple[bc.Dataset, dict]:  # fmt: skip
    """Roll each expert out `repetitions` (K) times on its own task: (bc.Dataset of E * K * T
    pairs, final metrics of (E, K)). family: (apply_fn, params stacked over E, tasks (E,) m, or
    (E, C) for a vector context, whose Dataset.task is then (N, C)). action_noise: the episodes
    act with noise of this std, labelled with the expert's own action (`rollout.episode_fn`);
    clip_labels: labels clipped to the env's action bound."""
    targets = env.check_targets(family.tasks).astype(np.float32)
    if repetitions < 1:
        raise ValueError(f"repetitions must be >= 1, got {repetitions!r}")
    program = rollout.matched_fn(env, family.apply_fn, record="trajectory", action_noise=action_noise)
    keys = rollout.repetition_keys(seed, len(targets), repetitions)
    metrics, (obs, actions) = program(family.params, targets, targets, keys)  # (E, K, T, ...)
    data = pairs(targets, obs, clipped(env, np.asarray(actions), clip_labels))
    return data, {k: np.asarray(v) for k, v in metrics.items()}


def save_dataset(path, data: bc.Dataset) -> Path:
    """npz with obs, actions, task; written atomically."""
    runio.write_npz(path, **data._asdict())
    runio.write_file_checksum(path)
    return Path(path)


def load_dataset(path) -> bc.Dataset:
    """The bc.Dataset saved by `save_dataset`; CorruptError (a ValueError) naming it if its bytes changed."""
    runio.verify_file_checksum(path)
    with np.load(path) as f:
        return bc.Dataset(**{name: f[name] for name in bc.Dataset._fields})


def dataset(cfg, run_dir: Path, say=print) -> bc.Dataset:
    """run_dir/meta/dataset.npz if a previous call of this stage saved it, else recorded from the
    trained experts now (and saved)."""
    path = Path(run_dir) / "meta" / "dataset.npz"
    if path.exists():
        try:
            data = load_dataset(path)
        except runio.CorruptError as err:  # this stage's own intermediate: recorded again
            say(f"dataset: {err}; recording it again")
        else:
            say(f"dataset: {path} ({len(data.obs)} pairs, reused)")
            return data
    t0 = time.perf_counter()
    family = experts_stage.load_family(cfg, run_dir)
    d = cfg.meta.dataset
    reps = d.repetitions
    env = dataset_env(cfg)
    data, metrics = collect_dataset(env, family, reps, d.seed, float(d.action_noise), bool(d.clip_labels))
    save_dataset(path, data)
    say(
        f"dataset: {len(data.obs)} pairs from {len(family.tasks)} experts x {reps} in {time.perf_counter() - t0:.1f} s;"
        f" expert error in the recording env {metrics['final_error'].mean():.2f} {env.UNIT}"
    )
    return data


def net_obs_norm(cfg, env, data: bc.Dataset) -> tuple | None:
    """The nets' `bc.MetaPolicy.obs_norm`: another task's states normalised by the dataset's
    statistics (`Task.normalise_meta_inputs`), else the observation as it is (the kick's phase
    and normalised context, in [0, 1] already)."""
    if tasks.get(cfg.task).normalise_meta_inputs:
        return bc.obs_norm_of(data.obs)
    return None


def run_obs_norm(run_dir: Path) -> tuple | None:
    """The nets' `bc.MetaPolicy.obs_norm` as a run's meta stage trained them (its table1.json)."""
    return bc.obs_norm_of_record(runio.read_json(Path(run_dir) / "meta" / OUTPUT))


def cloning_variant(m) -> str:
    """The cloning a meta section asks for, in words (what each table used)."""
    d, parts = m.dataset, [f"{m.dataset.repetitions} episode(s) per expert"]
    if d.repetitions == 1:
        parts[0] += " noise-free"
    if d.action_noise:
        parts.append(f"DART action noise {d.action_noise:g}")
    if d.clip_labels:
        parts.append("labels clipped")
    return ", ".join(parts) if len(parts) > 1 or d.repetitions == 1 else parts[0] + " (plain cloning)"


def cloning_record(cfg, env) -> dict:
    """table1.json's "cloning": the variant in words and the env steps it spent."""
    steps = cloning_env_steps(cfg, env)
    return {"variant": cloning_variant(cfg.meta), "env_steps": steps, "env_steps_total": int(sum(steps.values()))}


# -- training and Table 1 -----------------------------------------------------------------------


def evaluate_unfiltered(grid, params, tasks, repetitions: int, seed: int) -> dict:
    """Metrics (P, n_tasks, R) of each stacked policy (P, ...) on each task (n_tasks,) (vectors:
    (n_tasks, K)) with context = target."""
    tasks = np.asarray(tasks, np.float32)
    out = grid(params, tasks, tasks, rollout.repetition_keys(seed, len(tasks), repetitions))
    return {k: np.asarray(v) for k, v in out.items()}


def cloning_env_steps(cfg, env) -> dict:
    """The env steps cloning spends: the experts' recorded episodes."""
    return {"dataset": int(len(cfg.experts.tasks) * cfg.meta.dataset.repetitions * env.n_steps)}


def train(cfg, stage_dir: Path, data: bc.Dataset, env, say=print) -> tuple[dict, dict, dict]:
    """Train (or resume) every net of cfg.meta.nets into stage_dir/<net>, all stacked in one
    program (`bc.make_trainer`). Returns ({net: bc.MetaPolicy}, {net: final bc.TrainState},
    {net: train_wall_s}: the nets share one loop, so each shows its whole time)."""
    m = cfg.meta
    obs_norm = net_obs_norm(cfg, env, data)
    names = net_names(m.nets)
    models = {name: bc.MetaPolicy(*m.nets[name], env.action_size, obs_norm) for name in names}
    for name in names:
        say(f"{name}: {m.nets[name][0]} x {m.nets[name][1]}, {m.train.epochs} epochs, {m.train.n_seeds} seed(s)")
    if jax.process_count() > 1 and len(names) > 1:  # `bc.train_nets` splits them
        say("; ".join(f"{name} on process {sharding.owner(i)}" for i, name in enumerate(names)))
    else:
        say(f"{', '.join(names)}: trained stacked in one loop")

    def timed(clock):  # each progress line (after a checkpoint) records the training seconds so far
        def say_and_save(*args, **kwargs):
            clock.save()
            say(*args, **kwargs)

        return say_and_save

    # Training seconds over every process (a killed call's up to its last progress line), compiling
    # and checkpoints included; the nets share one loop, so each shows its whole time.
    clock = resumable.CarriedClock(stage_dir / "train_wall_time.json")
    states = bc.train_nets(models, data, m.train, {name: stage_dir / name for name in names}, timed(clock))
    return models, states, dict.fromkeys(names, clock.save())


def evaluate_net(cfg, name: str, model: bc.MetaPolicy, state: bc.TrainState, env, say=print) -> dict:
    """One trained net's seeds evaluated unfiltered: its row, rows_per_seed, per_task and eval time.
    Its program is the filter stage's (`programs.meta_grid`, one per architecture and inputs), its
    (task, repetition) pairs split over this process's devices and the processes."""
    m = cfg.meta
    t0 = time.perf_counter()
    mesh = sharding.device_mesh(impl=cfg.env.impl)
    grid = meta_programs.meta_grid(cfg.env, model.depth, model.width, mesh, cfg.task, model.obs_norm)
    metrics = evaluate_unfiltered(grid, state.params, m.eval.tasks, m.eval.repetitions, m.eval.seed)
    summaries = [evaluate.summarise_tasks({k: v[s] for k, v in metrics.items()}) for s in range(m.train.n_seeds)]
    eval_wall_s = time.perf_counter() - t0
    row = {**evaluate.table_row(summaries[0]), "per_task": per_task_list(m.eval.tasks, summaries[0])}
    unit = env.UNIT
    kept = "no task" if row["error_mean_m"] is None else f"{row['error_mean_m']:.2f} {unit}"
    say(
        f"{name}: evaluated in {eval_wall_s:.1f} s: accuracy {row['accuracy_mean']:.2f},"
        f" error {kept} over tasks with accuracy > {evaluate.ACCURACY_THRESHOLD},"
        f" {row['error_mean_all_m']:.2f} {unit} over all"
    )
    return {
        "row": row,
        "rows_per_seed": [evaluate.table_row(s) for s in summaries],
        "per_task": {
            "error_mean_m": summaries[0]["error_mean_m"].tolist(),
            "accuracy": summaries[0]["accuracy"].tolist(),
        },
        "eval_wall_s": eval_wall_s,
    }


def run(cfg, run_dir: Path, say=print) -> dict:
    """The stage: dataset, every net trained (resumable) and evaluated; writes table1.json and
    table1.md under run_dir/meta and returns the record."""
    t_start = time.perf_counter()
    run_dir = Path(run_dir)
    stage_dir = run_dir / "meta"
    record_path = inputs(cfg, run_dir)["experts"]
    data = dataset(cfg, run_dir, say)
    env, e = meta_programs.stage_env(cfg.env, cfg.task), cfg.meta.eval
    rows, per_task = {}, {"tasks": [task_env.context_json(t) for t in e.tasks]}
    experts_record = runio.read_json(record_path)
    rows["experts"], experts_per_task = experts_row(experts_record, record_path)
    if experts_per_task:
        per_task["experts"] = experts_per_task
    start_row = tasks.get(cfg.task).report.start_row  # the experts' starts, scored as the experts are
    if start_row in experts_record:
        rows[start_row], per_task[start_row] = experts_row(experts_record[start_row], record_path)
    rows_per_seed, timings = {}, {}
    models, states, train_s = train(cfg, stage_dir, data, env, say)
    for name, model in models.items():
        out = evaluate_net(cfg, name, model, states[name], env, say)
        rows[name], rows_per_seed[name], per_task[name] = out["row"], out["rows_per_seed"], out["per_task"]
        # the nets share one loop: each shows its whole time
        timings[name] = {"train_wall_s": train_s[name], "eval_wall_s": out["eval_wall_s"]}
    payload = {
        "rows": rows,
        "rows_per_seed": rows_per_seed,
        "per_task": per_task,
        "eval": {"repetitions": e.repetitions, "n_tasks": len(e.tasks), "seed": e.seed},
        "dataset_pairs": len(data.obs),
        "cloning": cloning_record(cfg, env),
        "timings": timings,
        "config": cfg.meta.to_dict(),  # what the filter stage checks its nets against
        **runio.provenance(cfg.preset, time.perf_counter() - t_start, config.resolved_env(cfg)),
    }
    payload.update(task=cfg.task, unit=env.UNIT, obs_size=int(data.obs.shape[-1]), n_actions=env.action_size)
    # every net's `net_obs_norm`: what the filter and held-out stages, and the shipped policies, build the nets with
    payload.update(bc.obs_norm_fields(next(iter(models.values())).obs_norm))
    runio.write_json(stage_dir / OUTPUT, payload)
    # From here on each net is read from its newest checkpoint (the trained policy): the older
    # ones go, as the experts' and the baseline's do once their records are written.
    for name in models:
        resumable.keep_newest_checkpoint(stage_dir / name / "checkpoints")
    markdown = tasks.get(cfg.task).report.table1(rows, env.UNIT)
    runio.write_text(stage_dir / "table1.md", markdown)
    return runio.json_safe(payload)
