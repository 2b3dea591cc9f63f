"""Stage 2: one PPO expert per task, all tasks in one compiled program.

Each expert starts from its own keyframe kick (`bumps_jax.tasks.kick.starting_kicks`: the prior's family
at the task's calibrated strength, or the best of that and the prior's anchors, then tuned by
CMA-ES for every task at once), clones it into its Gaussian policy (`bc.clone_kick`), and PPO refines
it on its own target. The host loop runs jitted chunks of `updates_per_chunk` updates; between
chunks it prints progress with an ETA, appends progress.csv and saves an orbax checkpoint. A
killed run resumes from the newest readable checkpoint and ends exactly where an uninterrupted
one would: every random number comes from the carried `TrainState.rng`.

A task other than the kick (`cfg.task`, e.g. cheetah_vel) has no keyframe prior: its experts
start from a fresh policy, and PPO trains them on their own targets.

Writes run_dir/experts/: starting_kicks.json (the kick), tuning/ (the starts and each finished
CMA-ES tuning run, so that a stopped tuning resumes at its next run) and checkpoints/ (while
training; both removed once the record is written), progress.csv, wall_time.json, final_params/,
experts.json, experts.md.
"""

from __future__ import annotations

import functools
import shutil
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax import config
from bumps_jax.algo import bc, evaluate, ppo, sharding
from bumps_jax.pipeline import runio
from bumps_jax.pipeline.stages import prior as prior_stage
from bumps_jax.report import tables
from bumps_jax.tasks import registry as tasks
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model
from bumps_jax.tasks.kick import starting_kicks

OUTPUT = "experts.json"
PRIOR = prior_stage.ASSET  # the record a prior stage writes, and the copy an experts run keeps
TUNING = "tuning"  # the starting kicks' starts and finished tuning runs, until the record is written


# -- the kick prior the experts start from ------------------------------------------------------


def prior_path(cfg, run_dir: Path) -> Path:
    """The kick prior record this run's experts start from: the run's own prior stage's record,
    else the copy this stage keeps of the one it started from, else the committed asset."""
    for path in (run_dir / "prior" / PRIOR, run_dir / "experts" / PRIOR):
        if path.is_file():
            return path
    return kick_model.ASSET


def inputs(cfg, run_dir: Path) -> dict:
    if cfg.task != "kick":  # experts from a fresh policy: nothing to read
        return {}
    path = prior_path(cfg, run_dir)
    kick_model.load_record(path, env_cfg=cfg.env)  # exists, parses, and was made under this env config
    return {"prior": path}


# -- programs -----------------------------------------------------------------------------------


class ExpertParams(NamedTuple):
    """What a deterministic expert needs: observation statistics and policy params."""

    normalizer: Any
    policy: Any


class Family(NamedTuple):
    """Deterministic policies stacked over experts: params leaves have a leading axis (E,)."""

    apply_fn: Any  # (params of one expert, contextual obs) -> action: `expert_policy`
    params: Any
    tasks: np.ndarray  # (E,) targets (the task's unit)


def expert_params(state: ppo.TrainState) -> ExpertParams:
    return ExpertParams(state.normalizer, state.params.policy)


def expert_policy(networks, env=None):
    """apply_fn(ExpertParams, obs) -> action: the Gaussian's mean. With `env`, obs is the
    contextual observation a rollout shows (`env.with_context`) and the expert sees its
    `env.expert_observation`; without, obs is the expert's own (the kick's: (2,) both)."""

    def apply(params: ExpertParams, obs):
        seen = obs if env is None else env.expert_observation(obs)
        return ppo.policy_mean(networks, params.normalizer, params.policy, seen)

    return apply


def task_expert_policy(cfg, programs):
    """`expert_policy` of a config's task: the kick's experts see the rollout's observation as it
    is, another task's their env's `expert_observation` of it (the state without the context)."""
    return expert_policy(programs.trainer.networks, None if cfg.task == "kick" else programs.env)


class Compiled(NamedTuple):
    """The jitted, task-vmapped programs of one config, split over `mesh` along the task axis."""

    env: Any  # the task's env (task_env.ContextualEnv)
    trainer: ppo.Trainer
    mesh: Any
    # (rngs (N, 2), targets (N,), kicks (N, K)) -> (TrainState (N, ...), BC losses (N, steps)); K: the
    # kick's 14 parameters, 0 for a task that starts from a fresh policy (no losses then)
    init: Any
    chunk: Any  # (TrainState (N, ...), targets (N,)) -> (TrainState, UpdateMetrics (N, chunk))
    n_kick: int = kick_model.N_PARAMS  # K above (`kick_size`)


def make_init(cfg, env: kick_env.KickEnv, trainer: ppo.Trainer):
    """A pure fn (rng, target, kick (14,)) -> (TrainState after cloning that kick, BC losses (steps,))."""

    def init(rng, target, kick):
        rng_state, rng_policy = jax.random.split(rng)
        policy = trainer.networks.policy_network.init(rng_policy)
        obs, actions = bc.kick_dataset(env, target, kick)
        policy, losses = bc.clone_kick(trainer.networks, policy, obs, actions, cfg.bc.steps, cfg.bc.learning_rate)
        return trainer.init(rng_state, policy), losses

    return init


def make_fresh_init(trainer: ppo.Trainer):
    """A pure fn (rng, target, kick (0,)) -> (TrainState of a fresh policy, no BC losses (0,)):
    the start of a task without a keyframe prior, in `make_init`'s signature."""

    def init(rng, target, kick):
        return trainer.init(rng), jnp.zeros((0,), jnp.float32)

    return init


def kick_size(cfg) -> int:
    """Numbers of one starting kick the init program takes: the kick's 14, else 0."""
    return kick_model.N_PARAMS if cfg.task == "kick" else 0


def compile_programs(cfg, env=None, mesh=None) -> Compiled:
    """The experts' programs for a pipeline config (its task's `experts` section and env,
    `config.task_view`); compiled on first call."""
    env = env or tasks.make_env(cfg.task, cfg.env)
    mesh = mesh or sharding.device_mesh(impl=env.config.impl)
    trainer = ppo.make_train(cfg.experts.ppo, env)
    make = make_init(cfg.experts, env, trainer) if cfg.task == "kick" else make_fresh_init(trainer)
    init = sharding.over_batch(jax.vmap(make), mesh, (True, True, True))
    n = int(cfg.experts.updates_per_chunk)
    chunk = jax.vmap(lambda state, target: trainer.run_updates(state, target, n))
    return Compiled(env, trainer, mesh, init, sharding.over_batch(chunk, mesh, (True, True)), kick_size(cfg))


def run_init(programs: Compiled, rngs, targets, kicks):
    """Cloning of `kicks` (N, 14) for any number N of tasks, or fresh policies for kicks (N, 0):
    (TrainState (N, ...), BC losses (N, steps))."""
    n = len(targets)
    args = (rngs, jnp.asarray(targets, jnp.float32), jnp.asarray(kicks, jnp.float32))
    out = programs.init(*sharding.place(sharding.pad(args, sharding.padded_size(n, programs.mesh)), programs.mesh))
    # Strong dtypes throughout (Adam starts its count weakly typed): the chunk compiles once.
    return jax.tree.map(lambda x: x.astype(x.dtype), sharding.unpad(out, n))


def run_chunk(programs: Compiled, state: ppo.TrainState, targets):
    """One chunk of PPO updates for any number of tasks: (TrainState (N, ...), UpdateMetrics (N, chunk))."""
    n = len(targets)
    args = sharding.pad((state, jnp.asarray(targets, jnp.float32)), sharding.padded_size(n, programs.mesh))
    return sharding.unpad(programs.chunk(*sharding.place(args, programs.mesh)), n)


def task_rngs(seed: int, n_tasks: int) -> jax.Array:
    """(n_tasks, 2) raw keys, one per expert: expert i's run is the same alone or in a batch."""
    return jax.random.split(jax.random.PRNGKey(seed), n_tasks)


def abstract_state(programs: Compiled, n_tasks: int):
    """The TrainState (N, ...) shapes and dtypes, for restoring checkpoints."""
    args = (task_rngs(0, n_tasks), jnp.zeros(n_tasks), jnp.zeros((n_tasks, programs.n_kick)))
    return jax.eval_shape(functools.partial(run_init, programs), *args)[0]


# -- training -----------------------------------------------------------------------------------

CSV_FIELDS = ("update", "env_steps", "target_m", *ppo.UpdateMetrics._fields)
# Another task's progress.csv names its target's unit (ppo's final_error is in it too).
TASK_CSV_FIELDS = {"cheetah_vel": ("update", "env_steps", "target_m_per_s", *ppo.UpdateMetrics._fields)}


def csv_fields(task: str) -> tuple:
    """progress.csv's columns for `task`."""
    return TASK_CSV_FIELDS.get(task, CSV_FIELDS)


def chunk_rows(first_update, metrics: ppo.UpdateMetrics, tasks, steps_per_update: int, fields=CSV_FIELDS) -> list:
    """CSV rows of one chunk: metrics (N tasks, n updates) -> N x n dicts with the columns `fields`."""
    m = jax.tree.map(np.asarray, metrics)
    rows = []
    for i, target in enumerate(tasks):
        for j in range(m.episode_return.shape[1]):
            update = int(first_update) + j + 1
            row = {"update": update, "env_steps": update * steps_per_update, fields[2]: float(target)}
            rows.append({**row, **{k: float(getattr(m, k)[i, j]) for k in ppo.UpdateMetrics._fields}})
    return rows


def progress_line(tasks, metrics: ppo.UpdateMetrics, update: int, total: int, eta: str, unit: str = "m") -> str:
    """One line per chunk: mean return, final error and valid fraction over the experts, and the
    worst task (errors and targets in `unit`)."""
    m = jax.tree.map(np.asarray, metrics)
    err = m.final_error[:, -1]
    worst = int(np.argmax(err))
    return (
        f"update {update}/{total}  return {m.episode_return[:, -1].mean():8.2f}  final error {err.mean():.2f} {unit}"
        f" (worst {err[worst]:.2f} {unit} at {tasks[worst]:.1f} {unit})  valid {m.valid[:, -1].mean():.2f}  {eta}"
    )


def initial_state(cfg, run_dir: Path, programs: Compiled, say=print):
    """The cloned starting kicks' TrainState (N, ...): written as checkpoint 0 with starting_kicks.json.
    A task without a keyframe prior: fresh policies."""
    tasks_ = np.asarray(cfg.experts.tasks, np.float32)
    if cfg.task != "kick":
        kicks = np.zeros((len(tasks_), programs.n_kick))
        state, _ = run_init(programs, task_rngs(cfg.experts.seed, len(tasks_)), tasks_, kicks)
        return state
    stage_dir = run_dir / "experts"
    path = prior_path(cfg, run_dir)
    record = kick_model.load_record(path, env_cfg=cfg.env)
    if path == kick_model.ASSET:  # keep the prior this run started from: a rerun must not read a newer asset
        runio.write_text(stage_dir / PRIOR, path.read_text())
    kicks, info = starting_kicks.starting_kicks(cfg, record, say, keep_dir=stage_dir / TUNING)
    runio.write_json(stage_dir / "starting_kicks.json", {**info, "prior": runio.shown(path)})
    tasks = np.asarray(cfg.experts.tasks, np.float32)
    state, bc_losses = run_init(programs, task_rngs(cfg.experts.seed, len(tasks)), tasks, kicks)
    say(f"behaviour cloning: final mse per task {np.asarray(bc_losses[:, -1]).round(6).tolist()} rad^2")
    return state


def train(cfg, run_dir: Path, programs: Compiled, say=print, stop_after_chunks: int | None = None) -> dict:
    """Train every task's expert under run_dir/experts, resuming from its newest readable checkpoint.

    Returns {"state": TrainState (N, ...), "finished": bool, "wall_s": training seconds over every call}.
    """
    import orbax.checkpoint as ocp  # noqa: PLC0415

    stage_dir = run_dir / "experts"
    tasks = tuple(float(t) for t in cfg.experts.tasks)
    targets = jnp.asarray(tasks, jnp.float32)
    total = programs.trainer.n_updates
    fields, unit = csv_fields(cfg.task), programs.env.UNIT
    loop = runio.ChunkedTraining(
        init=lambda: initial_state(cfg, run_dir, programs, say),
        chunk=lambda state: run_chunk(programs, state, targets),
        abstract=abstract_state(programs, len(tasks)),
        updates=lambda state: int(np.asarray(state.update)[0]),
        rows=lambda before, m: chunk_rows(before, m, tasks, programs.trainer.steps_per_update, fields),
        line=lambda m, update, eta: progress_line(tasks, m, update, total, eta, unit),
        fields=fields,
    )
    out = runio.train_in_chunks(stage_dir, loop, total, cfg.experts.keep_checkpoints, say, stop_after_chunks)
    if out["finished"]:
        with ocp.StandardCheckpointer() as checkpointer:  # leaving the context waits for the write
            checkpointer.save((stage_dir / "final_params").resolve(), expert_params(out["state"]), force=True)
        runio.write_checksums(stage_dir / "final_params")
    return out


def load_final_params(stage_dir: Path, programs: Compiled, n_tasks: int) -> ExpertParams:
    """The ExpertParams (N, ...) saved under stage_dir/final_params; ValueError naming it if unreadable."""
    import orbax.checkpoint as ocp  # noqa: PLC0415

    final = (Path(stage_dir) / "final_params").resolve()
    runio.verify_checksums(final)  # CorruptError (a ValueError) naming a changed file
    try:
        with ocp.StandardCheckpointer() as checkpointer:  # closed on leaving: no thread outlives the read
            return checkpointer.restore(final, expert_params(abstract_state(programs, n_tasks)))
    except Exception as err:  # noqa: BLE001 (orbax and tensorstore raise many kinds)
        reason = type(err).__name__
        raise ValueError(f"{final}: cannot read the trained experts ({reason}); rerun train-experts") from None


def load_family(cfg, run_dir: Path) -> Family:
    """The trained experts of a run, for behaviour cloning and replays."""
    programs = compile_programs(cfg)
    params = load_final_params(Path(run_dir) / "experts", programs, len(cfg.experts.tasks))
    return Family(task_expert_policy(cfg, programs), params, np.asarray(cfg.experts.tasks, np.float64))


def evaluate_experts(cfg, stage_dir: Path, params: ExpertParams, programs: Compiled, wall_s: float, say=print) -> dict:
    """Every expert on its own task (`eval.repetitions` noisy kicks each): experts.json and experts.md."""
    start = time.perf_counter()
    e = cfg.experts
    say(f"evaluating {len(e.tasks)} experts x {e.eval.repetitions} noisy episodes (compiling first)", flush=True)
    apply = task_expert_policy(cfg, programs)
    metrics = evaluate.evaluate_experts(programs.env, apply, params, e.tasks, e.eval.repetitions, e.eval.seed)
    record = evaluate.experts_record(e.tasks, metrics, programs.trainer.n_updates * programs.trainer.steps_per_update)
    if cfg.task != "kick":  # no prior, no starting kicks: every env step an expert cost is PPO's
        record["env_steps_breakdown"] = {"ppo": record["env_steps"]}
        record["env_steps_total"] = record["env_steps"]
        record.update(runio.provenance(cfg.preset, wall_s + time.perf_counter() - start, config.resolved_env(cfg)))
        record.update(task=cfg.task, unit=programs.env.UNIT, eval_repetitions=int(e.eval.repetitions))
        runio.write_text(stage_dir / "experts.md", tables.task_experts_markdown(record))
        runio.write_json(stage_dir / OUTPUT, record)
        return record
    kicks = runio.read_json(stage_dir / "starting_kicks.json")
    record["starting_kicks"], record["starting_kicks_midpoints"] = starting_kicks.evaluate_starting_kicks(
        cfg, programs.env, kicks["params"]
    )
    record["starting_kicks_smoothness"] = starting_kicks.smoothness(kicks["params"], e.tasks)
    if len(kicks.get("restart_costs", [])) > 1:  # `tune.restarts`: every run's fresh cost, and what was kept
        record["starting_kicks_tuning_runs"] = {"kept": kicks["restart"], "fresh_costs": kicks["restart_costs"]}
        if "run_seconds" in kicks:  # each run's time, also of runs a resumed tuning read back
            record["starting_kicks_tuning_runs"]["run_seconds"] = kicks["run_seconds"]
        if kicks.get("keep") in ("task", "chain"):  # each task's run (0: its start), the polish's tasks improved
            record["starting_kicks_tuning_runs"]["runs_kept"] = kicks["runs_kept"]
            record["starting_kicks_tuning_runs"]["keep"] = kicks["keep"]
            if "polish" in kicks:
                record["starting_kicks_tuning_runs"]["polish_improved"] = int(sum(kicks["polish"]["improved"]))
    record["env_steps_breakdown"] = env_steps_breakdown(cfg, stage_dir.parent, kicks, programs.env.n_steps,
                                                        record["env_steps"])  # fmt: skip
    known = [v for v in record["env_steps_breakdown"].values() if v is not None]
    record["env_steps_total"] = int(sum(known))  # per expert, the parts that are known
    record.update(runio.provenance(cfg.preset, wall_s + time.perf_counter() - start, config.resolved_env(cfg)))
    record["eval_repetitions"] = int(e.eval.repetitions)
    runio.write_text(stage_dir / "experts.md", tables.experts_markdown(record))
    runio.write_json(stage_dir / OUTPUT, record)
    return record


def env_steps_breakdown(cfg, run_dir: Path, kicks: dict, n_steps: int, ppo_steps: int) -> dict:
    """Env steps one expert cost: {"prior": its share (1 / n tasks) of the prior stage's
    episodes (None where the prior's record does not say how it was made), "tuning": its share of
    the starting kicks' episodes, "ppo": its PPO steps}."""
    n = len(cfg.experts.tasks)
    record = kick_model.load_record(prior_path(cfg, run_dir))
    prior_episodes = prior_stage.episodes_of(record)
    return {
        "prior": None if prior_episodes is None else int(prior_episodes * n_steps / n),
        "tuning": int(kicks.get("episodes", 0) * n_steps / n),
        "ppo": int(ppo_steps),
    }


def run(cfg, run_dir: Path, say=print) -> dict:
    """The stage: train (or resume) every expert, then evaluate them; returns experts.json's record."""
    stage_dir = Path(run_dir) / "experts"
    programs = compile_programs(cfg)
    n = len(cfg.experts.tasks)
    if (stage_dir / "final_params").exists():  # trained; a previous call stopped before its evaluation
        say(f"experts already trained ({stage_dir / 'final_params'}): evaluating them")
        params = load_final_params(stage_dir, programs, n)
        clock = runio.read_json(stage_dir / "wall_time.json") if (stage_dir / "wall_time.json").exists() else {}
        wall = max([0.0, *map(float, clock.values())])
    else:
        out = train(cfg, run_dir, programs, say)
        params, wall = expert_params(out["state"]), out["wall_s"]
    record = evaluate_experts(cfg, stage_dir, params, programs, wall, say)
    # The record and final_params hold everything later stages read: the training checkpoints
    # (most of a paper run directory's size) go, once final_params is verified.
    runio.verify_checksums(stage_dir / "final_params")
    shutil.rmtree(stage_dir / "checkpoints", ignore_errors=True)
    shutil.rmtree(stage_dir / TUNING, ignore_errors=True)
    say(tables.experts_markdown(record) if cfg.task == "kick" else tables.task_experts_markdown(record))
    return record
