"""The paper's Figure 1: plain multi-task PPO, one contextual policy for every target distance.

The experts' PPO trainer on one policy (the `baseline` section: 11 x 256 in the paper preset)
whose episodes each draw their target from `baseline.ppo.sample_task_range` (the kick: U[7, 18] m),
started as the task's expert start says (`ExpertStart.baseline_start`: the kick clones the main
kick of the run's prior at every training context; without one, a fresh policy), several seeds
trained side by side (vmap over seeds). The policy sees the contextual observation
(`ContextObserved`) and is scored by the env's own error.
Besides the paper's learning rate (`baseline.ppo.learning_rate`) an optional second arm
(`baseline.extra_learning_rate`) trains the same seeds in the same program (the rate is a value
of each run's optimiser state). Writes run_dir/baseline/baseline.json (per arm: the return curve
and the training error curve in the task's unit, each with a 95 % bootstrap band over seeds, and the meta-test
error evaluated like the BUMPS variants; the paper arm's also at the top level) and
baseline_curve.png. Training runs in compiled chunks of `baseline.updates_per_chunk` updates, each
followed by progress.csv rows, an orbax checkpoint and a progress line; a killed run resumes.
Once the record is written only the newest checkpoint (the trained runs) is kept.
"""

from __future__ import annotations

import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax import config, resumable, runio
from bumps_jax.algo import evaluate, ppo, rollout, sharding
from bumps_jax.envs import base as task_env
from bumps_jax.pipeline import expert_programs
from bumps_jax.pipeline.programs import stage_env
from bumps_jax.pipeline.stages import experts as experts_stage
from bumps_jax.report import curves as figures
from bumps_jax.tasks import registry as tasks

OUTPUT = "baseline.json"


def inputs(cfg, run_dir: Path) -> dict:
    """What the task's expert start reads (the baseline starts as its experts do)."""
    return experts_stage.inputs(cfg, run_dir)


def start_policy(cfg, env, trainer: ppo.Trainer, run_dir: Path, say=print) -> tuple:
    """The policy every seed starts from and its losses: the task's (`ExpertStart.baseline_start`,
    the kick's main kick cloned), else a fresh policy (no losses: None)."""
    start = tasks.get(cfg.task).expert_start
    if start is None:
        say(f"a fresh {len(cfg.baseline.ppo.policy_hidden)}-layer policy", flush=True)
        return trainer.networks.policy_network.init(jax.random.key(0)), None
    return start.baseline_start(cfg, env, trainer, run_dir, say)


def bootstrap_curve(returns: np.ndarray, steps_per_update: int) -> dict:
    """Mean return over seeds (seeds, updates) with its 95 % bootstrap band, per env step; one
    seed has no band (`ci_low`, `ci_high` None)."""
    from scipy import stats  # noqa: PLC0415

    curve = {
        "env_steps": (steps_per_update * np.arange(1, returns.shape[1] + 1)).tolist(),
        "mean": returns.mean(axis=0).tolist(),
        "ci_low": None,
        "ci_high": None,
    }
    if returns.shape[0] > 1:
        ci = stats.bootstrap((returns,), np.mean, axis=0, confidence_level=0.95, n_resamples=1000, random_state=0)
        curve.update(ci_low=np.asarray(ci.confidence_interval.low).tolist(),
                     ci_high=np.asarray(ci.confidence_interval.high).tolist())  # fmt: skip
    return curve


def learning_rates(b) -> tuple[float, ...]:
    """The arms' policy learning rates: the paper's first."""
    return (float(b.ppo.learning_rate),) + (() if b.extra_learning_rate is None else (float(b.extra_learning_rate),))


# One row per run and update; run i is arm i // seeds, seed i % seeds.
CSV_FIELDS = ("update", "env_steps", "run", "learning_rate", "seed", *ppo.UpdateMetrics._fields)
# The target passed to the trainer; unused, since every episode draws its own (ppo.sample_task_range).
TRAIN_TARGET = 12.0


def training_loop(cfg, trainer: ppo.Trainer, policy0, unit: str = "m", mesh=None) -> resumable.ChunkedTraining:
    """Every arm's seeds from `policy0`, vmapped over runs, in chunks of updates (errors in `unit`).
    The runs are independent: they are split over `mesh` (default: this process's devices for
    the task's physics) and the processes (`sharding.over_batch`), and gathered after each chunk."""
    b = cfg.baseline
    rates = learning_rates(b)
    seeds = int(b.seeds)
    mesh = mesh or sharding.device_mesh(impl=cfg.env.impl)
    # Every arm trains the same seeds (the same keys); the rate is a value of each run's optimiser state.
    rngs = jnp.concatenate([jax.random.split(jax.random.PRNGKey(1), seeds)] * len(rates))  # raw keys: orbax saves them
    lrs = jnp.repeat(jnp.asarray(rates, jnp.float32), seeds)
    init_runs = jax.vmap(lambda rng, lr: trainer.init(rng, policy0, lr))
    init = sharding.over_batch(init_runs, mesh, (True, True))
    n = int(b.updates_per_chunk)
    program = sharding.over_batch(jax.vmap(lambda state: trainer.run_updates(state, TRAIN_TARGET, n)), mesh, (True,))

    def chunk(state):
        return sharding.run_padded(program, mesh, state)

    total = trainer.n_updates

    def fresh():
        # Strong dtypes throughout (Adam starts its count weakly typed): the chunk compiles once.
        return jax.tree.map(lambda x: x.astype(x.dtype), sharding.run_padded(init, mesh, rngs, lrs))

    def rows(before: int, metrics: ppo.UpdateMetrics) -> list:
        m = jax.tree.map(np.asarray, metrics)
        out = []
        for run in range(len(lrs)):
            for j in range(m.episode_return.shape[1]):
                update = before + j + 1
                head = {"update": update, "env_steps": update * trainer.steps_per_update, "run": run,
                        "learning_rate": rates[run // seeds], "seed": run % seeds}  # fmt: skip
                out.append({**head, **{k: float(getattr(m, k)[run, j]) for k in ppo.UpdateMetrics._fields}})
        return out

    def line(metrics: ppo.UpdateMetrics, update: int, eta: str) -> str:
        m = jax.tree.map(np.asarray, metrics)
        arms = "  ".join(
            f"lr {lr:g}: return {m.episode_return[i * seeds : (i + 1) * seeds, -1].mean():8.2f}"
            f" error {m.final_error[i * seeds : (i + 1) * seeds, -1].mean():.2f} {unit}"
            for i, lr in enumerate(rates)
        )
        return f"baseline update {update}/{total}  {arms}  {eta}"

    return resumable.ChunkedTraining(
        init=fresh,
        chunk=chunk,
        abstract=jax.eval_shape(lambda: jax.tree.map(lambda x: x.astype(x.dtype), init_runs(rngs, lrs))),
        updates=lambda state: int(np.asarray(state.update)[0]),
        rows=rows,
        line=line,
        fields=CSV_FIELDS,
    )


def read_progress(path: Path, n_runs: int, n_updates: int) -> dict[str, np.ndarray]:
    """progress.csv as {metric: (runs, updates)}; ValueError naming the file if a row is missing."""
    import csv  # noqa: PLC0415

    out = {k: np.full((n_runs, n_updates), np.nan) for k in ppo.UpdateMetrics._fields}
    with path.open(newline="") as f:
        for row in csv.DictReader(f):
            run, update = int(row["run"]), int(row["update"])
            for k in out:
                out[k][run, update - 1] = float(row[k])
    if any(np.isnan(v).any() for v in out.values()):
        raise ValueError(f"{path}: rows missing for some runs and updates; rerun the baseline stage to redo them")
    return out


def run(cfg, run_dir: Path, say=print, max_chunks: int | None = None) -> dict | None:
    """Train (or resume) every arm's seeds, evaluate them on the meta-test tasks, write the record
    and the figure. max_chunks: stop after this many chunks (tests of the resume path; returns None)."""
    start = time.perf_counter()
    b = cfg.baseline
    stage_dir = Path(run_dir) / "baseline"
    env = stage_env(cfg.env, cfg.task)
    unit = env.UNIT
    trainer = ppo.make_train(b.ppo, task_env.ContextObserved(env), traced_learning_rate=True, prefix="baseline.ppo.")
    policy0, bc_losses = start_policy(cfg, env, trainer, run_dir, say)
    rates = learning_rates(b)
    n_runs = len(rates) * b.seeds
    say(f"training {len(rates)} arm(s) x {b.seeds} seeds x {trainer.n_updates} updates, "
        f"{b.updates_per_chunk} per compiled chunk (compiling first)", flush=True)  # fmt: skip
    loop = training_loop(cfg, trainer, policy0, unit)
    out = resumable.train_in_chunks(stage_dir, loop, trainer.n_updates, b.keep_checkpoints, say, max_chunks)
    if not out["finished"]:
        return None
    state, train_s = out["state"], out["wall_s"]
    curves = read_progress(stage_dir / "progress.csv", n_runs, trainer.n_updates)

    rows, per_task = evaluate_runs(cfg, env, trainer, policy0, state)
    env_steps = trainer.n_updates * trainer.steps_per_update
    arms = arms_of(rates, b.seeds, rows[1:], curves, trainer.steps_per_update)
    eval_tasks = np.asarray(b.eval_tasks, np.float32)
    paper = arms[0]
    payload = {
        # Wall time: training over every call plus this call's clone and evaluation.
        **runio.provenance(cfg.preset, train_s + time.perf_counter() - start - out["call_s"], config.resolved_env(cfg)),
        "seeds": int(b.seeds),
        "env_steps_per_seed": int(env_steps),
        "learning_rates": list(rates),
        # The paper arm (ppo.learning_rate) at the top level, as the results contract names it.
        **{k: paper[k] for k in ("learning_rate", "curve", "error_curve", "error_mean_m", "accuracy_mean", "per_seed")},
        "arms": arms,
        "start": rows[0],  # the policy every seed started from, before PPO
        **({} if bc_losses is None else {"bc_final_loss": float(bc_losses[-1])}),  # the clone's fit
        "env_steps": int(env_steps),
        "train_wall_s": train_s,
        "eval_tasks": eval_tasks.tolist(),
        "eval_repetitions": int(b.eval_repetitions),
    }
    # The task's name and unit, and the range its training targets came from.
    payload.update(task=cfg.task, unit=unit, sample_task_range=list(b.ppo.sample_task_range))
    # Per eval task, the first arm's mean error over its seeds (unit), as BUMPS's tables list them.
    payload["per_task_error_m"] = per_task[1 : 1 + b.seeds].mean(axis=0).tolist()
    runio.write_json(stage_dir / OUTPUT, payload)
    resumable.keep_newest_checkpoint(stage_dir / "checkpoints")  # the trained policies; the rest is history
    figures.baseline(payload, stage_dir / "baseline_curve.png")
    for arm in arms:
        say(f"baseline, lr {arm['learning_rate']:g}: error {arm['error_mean_m']:.2f} {unit}, "
            f"accuracy {arm['accuracy_mean']:.2f}, {env_steps:,} env steps per seed")  # fmt: skip
    start_name = "the fresh policy" if bc_losses is None else "the cloned start"
    say(f"at the start ({start_name}): error {rows[0]['error_mean_all_m']:.2f} {unit}, "
        f"accuracy {rows[0]['accuracy_mean']:.2f}")  # fmt: skip
    return payload


def evaluate_runs(cfg, env, trainer, policy0, state) -> tuple[list[dict], np.ndarray]:
    """Table 1 rows (`evaluate.table_row`) on the baseline's eval tasks and noise: row 0 the policy
    every seed started from (before PPO), then every run (arm-major, seeds within); and their mean
    errors per eval task, (1 + runs, tasks). Each policy sees the contextual observation
    (`env.with_context`), as it trained."""
    b = cfg.baseline
    cloned = expert_programs.ExpertParams(ppo.init_normalizer(task_env.ContextObserved(env).observation_size), policy0)
    params = jax.tree.map(
        lambda a, s: jnp.concatenate([jnp.asarray(a, s.dtype)[None], s]),
        cloned,
        jax.vmap(expert_programs.expert_params)(state),
    )
    eval_tasks = np.asarray(b.eval_tasks, np.float32)
    keys = rollout.repetition_keys(b.eval_seed, len(eval_tasks), b.eval_repetitions)
    mesh = sharding.device_mesh(impl=cfg.env.impl)  # the (task, repetition) pairs split over devices and processes
    grid = rollout.grid_fn(env, expert_programs.expert_policy(trainer.networks), mesh)
    m = grid(params, eval_tasks, eval_tasks, keys)  # (1 + runs, tasks, reps)
    summaries = [evaluate.summarise_tasks({k: v[s] for k, v in m.items()}) for s in range(len(m["valid"]))]
    return [evaluate.table_row(x) for x in summaries], np.stack([x["error_mean_m"] for x in summaries])


def arms_of(rates, seeds: int, run_rows: list[dict], curves: dict, steps_per_update: int) -> list[dict]:
    """Per learning rate: its seeds' rows, mean error and accuracy over seeds, and the training
    curves (return and final error) with 95 % bootstrap bands over seeds."""
    returns = curves["episode_return"].reshape(len(rates), seeds, -1)
    errors = curves["final_error"].reshape(len(rates), seeds, -1)
    arms = []
    for i, lr in enumerate(rates):
        per_seed = run_rows[i * seeds : (i + 1) * seeds]
        arms.append({
            "learning_rate": lr,
            "curve": bootstrap_curve(returns[i], steps_per_update),
            "error_curve": bootstrap_curve(errors[i], steps_per_update),
            "error_mean_m": float(np.mean([r["error_mean_all_m"] for r in per_seed])),
            "accuracy_mean": float(np.mean([r["accuracy_mean"] for r in per_seed])),
            "per_seed": per_seed,
        })  # fmt: skip
    return arms
