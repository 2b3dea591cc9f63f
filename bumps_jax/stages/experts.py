"""Stage 2: one PPO expert per task, all tasks in one compiled program.

Each expert starts from its own keyframe kick (`starting_kicks`: the prior's family at the
task's calibrated strength, or the best of that and the prior's anchors, then tuned by CMA-ES
for every task at once), clones it into its Gaussian policy (`bc.clone_kick`), and PPO refines
it on its own target. The host loop runs jitted chunks of `updates_per_chunk` updates; between
chunks it prints progress with an ETA, appends progress.csv and saves an orbax checkpoint. A
killed run resumes from the newest readable checkpoint and ends exactly where an uninterrupted
one would: every random number comes from the carried `TrainState.rng`.

Writes run_dir/experts/: starting_kicks.json, checkpoints/ (while training; removed once the
record is written), progress.csv, wall_time.json, final_params/, experts.json, experts.md.
"""

from __future__ import annotations

import functools
import json
import shutil
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax import bc, evaluate, kick_env, kick_model, kick_scoring, ppo, rollout, runio, sharding, tables
from bumps_jax.stages import prior as prior_stage

OUTPUT = "experts.json"
PRIOR = prior_stage.ASSET  # the record a prior stage writes, and the copy an experts run keeps


# -- the kick prior the experts start from ------------------------------------------------------


def prior_path(cfg, run_dir: Path) -> Path:
    """The kick prior record this run's experts start from: the run's own prior stage's record,
    else the copy this stage keeps of the one it started from, else the committed asset."""
    for path in (run_dir / "prior" / PRIOR, run_dir / "experts" / PRIOR):
        if path.is_file():
            return path
    return kick_model.ASSET


def inputs(cfg, run_dir: Path) -> dict:
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

    apply_fn: Any  # (params of one expert, obs (2,)) -> action (22,)
    params: Any
    tasks: np.ndarray  # (E,) m


def expert_params(state: ppo.TrainState) -> ExpertParams:
    return ExpertParams(state.normalizer, state.params.policy)


def expert_policy(networks):
    """apply_fn(ExpertParams, obs (2,)) -> action (22,): the Gaussian's mean."""

    def apply(params: ExpertParams, obs):
        return ppo.policy_mean(networks, params.normalizer, params.policy, obs)

    return apply


class Compiled(NamedTuple):
    """The jitted, task-vmapped programs of one config, split over `mesh` along the task axis."""

    env: kick_env.KickEnv
    trainer: ppo.Trainer
    mesh: Any
    init: Any  # (rngs (N, 2), targets (N,), kicks (N, 14)) -> (TrainState (N, ...), BC losses (N, steps))
    chunk: Any  # (TrainState (N, ...), targets (N,)) -> (TrainState, UpdateMetrics (N, chunk))


def make_init(cfg, env: kick_env.KickEnv, trainer: ppo.Trainer):
    """A pure fn (rng, target, kick (14,)) -> (TrainState after cloning that kick, BC losses (steps,))."""

    def init(rng, target, kick):
        rng_state, rng_policy = jax.random.split(rng)
        policy = trainer.networks.policy_network.init(rng_policy)
        obs, actions = bc.kick_dataset(env, target, kick)
        policy, losses = bc.clone_kick(trainer.networks, policy, obs, actions, cfg.bc.steps, cfg.bc.learning_rate)
        return trainer.init(rng_state, policy), losses

    return init


def compile_programs(cfg, env: kick_env.KickEnv | None = None, mesh=None) -> Compiled:
    """The experts' programs for a pipeline config (its `experts` section, its env); compiled on first call."""
    env = env or kick_env.KickEnv(cfg.env)
    mesh = mesh or sharding.device_mesh()
    trainer = ppo.make_train(cfg.experts.ppo, env)
    init = sharding.over_batch(jax.vmap(make_init(cfg.experts, env, trainer)), mesh, (True, True, True))
    n = int(cfg.experts.updates_per_chunk)
    chunk = jax.vmap(lambda state, target: trainer.run_updates(state, target, n))
    return Compiled(env, trainer, mesh, init, sharding.over_batch(chunk, mesh, (True, True)))


def run_init(programs: Compiled, rngs, targets, kicks):
    """Cloning of `kicks` (N, 14) for any number N of tasks: (TrainState (N, ...), BC losses (N, steps))."""
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
    args = (task_rngs(0, n_tasks), jnp.zeros(n_tasks), jnp.zeros((n_tasks, kick_model.N_PARAMS)))
    return jax.eval_shape(functools.partial(run_init, programs), *args)[0]


# -- starting kicks -----------------------------------------------------------------------------


def prior_kicks(cfg, record: dict, targets, env, say=print) -> tuple[np.ndarray, dict, int]:
    """The prior family's kick (N, 14) for each of `targets` (N,) m, what was chosen, and the
    episodes the choice cost.

    The family at each target's calibrated strength (or the main kick for every target), or
    with `tune.anchor_starts` the best of that and the prior's anchors on `tune.eval_repetitions`
    noisy kicks at the target.
    """
    e = cfg.experts
    targets = np.asarray(targets, np.float32)
    info = {"start_targets_m": targets.tolist()}
    if not e.bc.per_task_strength:
        return np.tile(np.asarray(record["params"], np.float32), (len(targets), 1)), info, 0
    anchors = jnp.asarray(record["anchors"], jnp.float32)
    table = jnp.asarray(kick_model.calibration(record))
    starts = np.asarray(jax.vmap(lambda t: kick_model.kick_for(anchors, table, t))(jnp.asarray(targets)))
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


def tune_env(cfg) -> kick_env.KickEnv:
    """The env the starting kicks are chosen and tuned in (cfg.env over the prior's task range),
    built once per process and env config: cmaes keeps its programs per env, so a second tuning
    in the same process (a resumed or repeated run) compiles nothing again."""
    task_range = tuple(float(t) for t in cfg.prior.task_range)
    key = (json.dumps(kick_env.resolved(cfg.env), sort_keys=True), task_range)
    if key not in _TUNE_ENVS:
        _TUNE_ENVS[key] = kick_env.KickEnv(cfg.env, {"task_range": task_range})
    return _TUNE_ENVS[key]


def starting_kicks(cfg, record: dict, say=print) -> tuple[np.ndarray, dict]:
    """The keyframe kick (T, 14) each expert clones, and a record of how it was made.

    Scheme "per_task": each task's `prior_kicks` start, then with `tune.generations` > 0 one
    CMA-ES per task (`cmaes.tune_for_tasks`). Scheme "family": the `prior_kicks` at
    `tune.knots` knots over the tasks' range make a contextual kick (`kick_model.family_params`),
    then with `tune.generations` > 0 one CMA-ES over it scored on every task
    (`cmaes.tune_family`); each task's kick is the family's at its target. The record counts
    every episode the kicks cost (`episodes`) and the largest jump between neighbouring tasks'
    kicks (`smoothness`, `kick_model.largest_jump`).
    """
    from bumps_jax import cmaes  # noqa: PLC0415

    e = cfg.experts
    targets = np.asarray(e.tasks, np.float32)
    env = tune_env(cfg)
    info = {"tasks_m": targets.tolist(), "scheme": e.tune.scheme, "tuned": False}
    family = e.tune.scheme == "family"
    if family:
        knots = kick_model.knot_targets(float(targets.min()), float(targets.max()), e.tune.knots)
        knot_params, start_info, episodes = prior_kicks(cfg, record, knots, env, say)
        members = jax.vmap(kick_model.family_params, in_axes=(None, None, 0))
        starts = np.asarray(members(jnp.asarray(knot_params), jnp.asarray(knots), jnp.asarray(targets)))
        info.update(knots_m=knots.tolist(), knot_params=np.asarray(knot_params).tolist())
    else:
        starts, start_info, episodes = prior_kicks(cfg, record, targets, env, say)
    info.update(start_info)
    if e.tune.generations > 0:
        t0 = time.perf_counter()
        common = dict(fitness=cfg.prior.fitness, say=say)
        if family:
            out = cmaes.tune_family(env, targets, knots, knot_params, e.tune, e.tune.generations,
                                    e.tune.sigma_init, **common)  # fmt: skip
            info["knot_params"] = out["knot_params"].tolist()
        else:
            out = cmaes.tune_for_tasks(env, targets, starts, e.tune, e.tune.generations, e.tune.sigma_init,
                                       **common)  # fmt: skip
        starts = out["params"]
        episodes += out["episodes"]
        improved = out["improved"].tolist() if isinstance(out["improved"], np.ndarray) else out["improved"]
        info.update(tuned=True, wall_s=time.perf_counter() - t0, start_cost=out["start_cost"],
                    tuned_cost=out["tuned_cost"], improved=improved, history_best_cost=out["history"])  # fmt: skip
    info["episodes"] = int(episodes)  # every episode the starting kicks cost: choice of starts and tuning
    info["smoothness"] = smoothness(starts, targets)
    info["params"] = np.asarray(starts).tolist()
    return np.asarray(starts, np.float32), info


def smoothness(kicks, targets) -> dict | None:
    """`kick_model.largest_jump` of the tasks' kicks (T, 14), or None for fewer than two tasks."""
    return kick_model.largest_jump(kicks, targets) if len(set(np.asarray(targets).tolist())) > 1 else None


# -- training -----------------------------------------------------------------------------------

CSV_FIELDS = ("update", "env_steps", "target_m", *ppo.UpdateMetrics._fields)


def chunk_rows(first_update, metrics: ppo.UpdateMetrics, tasks, steps_per_update: int) -> list:
    """CSV rows of one chunk: metrics (N tasks, n updates) -> N x n dicts."""
    m = jax.tree.map(np.asarray, metrics)
    rows = []
    for i, target in enumerate(tasks):
        for j in range(m.episode_return.shape[1]):
            update = int(first_update) + j + 1
            row = {"update": update, "env_steps": update * steps_per_update, "target_m": float(target)}
            rows.append({**row, **{k: float(getattr(m, k)[i, j]) for k in ppo.UpdateMetrics._fields}})
    return rows


def progress_line(tasks, metrics: ppo.UpdateMetrics, update: int, total: int, eta: str) -> str:
    """One line per chunk: mean return, final error and valid fraction over the experts, and the worst task."""
    m = jax.tree.map(np.asarray, metrics)
    err = m.final_error[:, -1]
    worst = int(np.argmax(err))
    return (
        f"update {update}/{total}  return {m.episode_return[:, -1].mean():8.2f}  final error {err.mean():.2f} m"
        f" (worst {err[worst]:.2f} m at {tasks[worst]:.1f} m)  valid {m.valid[:, -1].mean():.2f}  {eta}"
    )


def initial_state(cfg, run_dir: Path, programs: Compiled, say=print):
    """The cloned starting kicks' TrainState (N, ...): written as checkpoint 0 with starting_kicks.json."""
    stage_dir = run_dir / "experts"
    path = prior_path(cfg, run_dir)
    record = kick_model.load_record(path, env_cfg=cfg.env)
    if path == kick_model.ASSET:  # keep the prior this run started from: a rerun must not read a newer asset
        runio.write_text(stage_dir / PRIOR, path.read_text())
    kicks, info = starting_kicks(cfg, record, say)
    runio.write_json(stage_dir / "starting_kicks.json", {**info, "prior": str(path)})
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
    loop = runio.ChunkedTraining(
        init=lambda: initial_state(cfg, run_dir, programs, say),
        chunk=lambda state: run_chunk(programs, state, targets),
        abstract=abstract_state(programs, len(tasks)),
        updates=lambda state: int(np.asarray(state.update)[0]),
        rows=lambda before, m: chunk_rows(before, m, tasks, programs.trainer.steps_per_update),
        line=lambda m, update, eta: progress_line(tasks, m, update, total, eta),
        fields=CSV_FIELDS,
    )
    out = runio.train_in_chunks(stage_dir, loop, total, cfg.experts.keep_checkpoints, say, stop_after_chunks)
    if out["finished"]:
        with ocp.StandardCheckpointer() as checkpointer:  # leaving the context waits for the write
            checkpointer.save((stage_dir / "final_params").resolve(), expert_params(out["state"]), force=True)
    return out


def load_final_params(stage_dir: Path, programs: Compiled, n_tasks: int) -> ExpertParams:
    """The ExpertParams (N, ...) saved under stage_dir/final_params; ValueError naming it if unreadable."""
    import orbax.checkpoint as ocp  # noqa: PLC0415

    final = (Path(stage_dir) / "final_params").resolve()
    try:
        return ocp.StandardCheckpointer().restore(final, expert_params(abstract_state(programs, n_tasks)))
    except Exception as err:  # noqa: BLE001 (orbax and tensorstore raise many kinds)
        reason = type(err).__name__
        raise ValueError(f"{final}: cannot read the trained experts ({reason}); rerun train-experts") from None


def load_family(cfg, run_dir: Path) -> Family:
    """The trained experts of a run, for behaviour cloning and replays."""
    programs = compile_programs(cfg)
    params = load_final_params(Path(run_dir) / "experts", programs, len(cfg.experts.tasks))
    return Family(expert_policy(programs.trainer.networks), params, np.asarray(cfg.experts.tasks, np.float64))


def evaluate_experts(cfg, stage_dir: Path, params: ExpertParams, programs: Compiled, wall_s: float, say=print) -> dict:
    """Every expert on its own task (`eval.repetitions` noisy kicks each): experts.json and experts.md."""
    start = time.perf_counter()
    e = cfg.experts
    say(f"evaluating {len(e.tasks)} experts x {e.eval.repetitions} noisy kicks (compiling first)", flush=True)
    apply = expert_policy(programs.trainer.networks)
    metrics = evaluate.evaluate_experts(programs.env, apply, params, e.tasks, e.eval.repetitions, e.eval.seed)
    record = evaluate.experts_record(e.tasks, metrics, programs.trainer.n_updates * programs.trainer.steps_per_update)
    kicks = runio.read_json(stage_dir / "starting_kicks.json")
    record["starting_kicks"] = evaluate_starting_kicks(cfg, programs.env, kicks["params"])
    record["starting_kicks_smoothness"] = smoothness(kicks["params"], e.tasks)
    record["env_steps_breakdown"] = env_steps_breakdown(cfg, stage_dir.parent, kicks, programs.env.n_steps,
                                                        record["env_steps"])  # fmt: skip
    known = [v for v in record["env_steps_breakdown"].values() if v is not None]
    record["env_steps_total"] = int(sum(known))  # per expert, the parts that are known
    record.update(runio.provenance(cfg.preset, wall_s + time.perf_counter() - start, cfg.env))
    record["eval_repetitions"] = int(e.eval.repetitions)
    runio.write_text(stage_dir / "experts.md", tables.experts_markdown(record))
    runio.write_json(stage_dir / OUTPUT, record)
    return record


def evaluate_starting_kicks(cfg, env: kick_env.KickEnv, kicks) -> dict:
    """The tasks' starting kicks (T, 14) scored exactly as their experts are (the same tasks,
    `experts.eval` noisy kicks and seed, `evaluate`'s statistics): Table 1's "starting kicks
    (before PPO)" row, with its per-task list."""
    e = cfg.experts
    tables_ = kick_model.action_tables(jnp.asarray(kicks, jnp.float32), env.n_steps, env.dt)
    metrics = evaluate.evaluate_experts(env, rollout.table_policy, tables_, e.tasks, e.eval.repetitions, e.eval.seed)
    return evaluate.tasks_record(e.tasks, metrics)


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
    # (most of a paper run directory's size) go.
    shutil.rmtree(stage_dir / "checkpoints", ignore_errors=True)
    say(tables.experts_markdown(record))
    return record


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
