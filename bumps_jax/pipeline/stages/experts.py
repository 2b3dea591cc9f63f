"""Stage 2: one PPO expert per task, all tasks in one compiled program.

Each expert starts as its task says (`Task.expert_start`: the kick clones its own tuned keyframe
kick; a task without one starts from a fresh policy), and PPO refines it on its own target. The
host loop runs jitted chunks of `updates_per_chunk` updates; between chunks it prints progress
with an ETA, appends progress.csv and saves an orbax checkpoint. A killed run resumes from the
newest readable checkpoint and ends exactly where an uninterrupted one would: every random number
comes from the carried `TrainState.rng`.

Writes run_dir/experts/: what the task's start keeps (the kick: starting_kicks.json, tuning/),
checkpoints/ (while training; removed with the start's scratch once the record is written),
progress.csv, wall_time.json, final_params/, experts.json, experts.md.
"""

from __future__ import annotations

import functools
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from bumps_jax import config, resumable, runio
from bumps_jax.algo import evaluate, ppo, rollout, sharding
from bumps_jax.envs import base as task_env
from bumps_jax.pipeline import sections as stage_sections
from bumps_jax.records import jsonable
from bumps_jax.tasks import registry as tasks

OUTPUT = "experts.json"


def inputs(cfg, run_dir: Path) -> dict:
    """What the task's expert start reads (nothing for a fresh policy)."""
    start = tasks.get(cfg.task).expert_start
    return {} if start is None else start.inputs(cfg, run_dir)


# -- programs -----------------------------------------------------------------------------------


class ExpertParams(NamedTuple):
    """What a deterministic expert needs: observation statistics and policy params."""

    normalizer: Any
    policy: Any


class Family(NamedTuple):
    """Deterministic policies stacked over experts: params leaves have a leading axis (E,)."""

    apply_fn: Any  # (params of one expert, contextual obs) -> action: `expert_policy`
    params: Any
    tasks: np.ndarray  # (E,) targets (the task's unit); (E, K) for a vector context


def expert_params(state: ppo.TrainState) -> ExpertParams:
    return ExpertParams(state.normalizer, state.params.policy)


def expert_policy(networks, env=None):
    """apply_fn(ExpertParams, obs) -> action: the Gaussian's mean. With `env`, obs is the
    contextual observation a rollout shows (`env.with_context`) and the expert sees its
    `env.expert_observation`; without, obs is the expert's own."""

    def apply(params: ExpertParams, obs):
        seen = obs if env is None else env.expert_observation(obs)
        return ppo.policy_mean(networks, params.normalizer, params.policy, seen)

    return apply


def task_expert_policy(cfg, programs):
    """`expert_policy` of a config's task: its experts see their env's `expert_observation` of
    the rollout's contextual observation."""
    return expert_policy(programs.trainer.networks, programs.env)


class Compiled(NamedTuple):
    """The jitted, task-vmapped programs of one config, split over `mesh` along the task axis."""

    env: Any  # the task's env (task_env.ContextualEnv)
    trainer: ppo.Trainer
    mesh: Any
    # (rngs (N, 2), targets (N,) (or (N, C) for a vector context), starts (N, K)) -> (TrainState
    # (N, ...), losses (N, steps)); K: the size of the task's expert start, 0 for a fresh policy
    init: Any
    chunk: Any  # (TrainState (N, ...), targets (N,)) -> (TrainState, UpdateMetrics (N, chunk))
    start_size: int  # K above


def make_fresh_init(trainer: ppo.Trainer):
    """A pure fn (rng, target, start (0,)) -> (TrainState of a fresh policy, no losses (0,)):
    the start of a task without an expert start, in `ExpertStart.make_init`'s signature."""

    def init(rng, target, start):
        return trainer.init(rng), jnp.zeros((0,), jnp.float32)

    return init


def compile_programs(cfg, env=None, mesh=None) -> Compiled:
    """The experts' programs for a pipeline config (its task's `experts` section and env); compiled
    on first call."""
    start = tasks.get(cfg.task).expert_start
    env = env or tasks.make_env(cfg.task, cfg.env)
    mesh = mesh or sharding.device_mesh(impl=env.config.impl)
    trainer = ppo.make_train(cfg.experts.ppo, env)
    make = make_fresh_init(trainer) if start is None else start.make_init(cfg, env, trainer)
    init = sharding.over_batch(jax.vmap(make), mesh, (True, True, True))
    n = int(cfg.experts.updates_per_chunk)
    chunk = jax.vmap(lambda state, target: trainer.run_updates(state, target, n))
    size = 0 if start is None else start.size
    return Compiled(env, trainer, mesh, init, sharding.over_batch(chunk, mesh, (True, True)), size)


def run_init(programs: Compiled, rngs, targets, starts):
    """The experts' starts (N, K) for any number N of tasks, made into policies (fresh ones for
    starts (N, 0)): (TrainState (N, ...), losses (N, steps))."""
    args = (rngs, jnp.asarray(targets, jnp.float32), jnp.asarray(starts, jnp.float32))
    out = sharding.run_padded(programs.init, programs.mesh, *args)
    # Strong dtypes throughout (Adam starts its count weakly typed): the chunk compiles once.
    return jax.tree.map(lambda x: x.astype(x.dtype), out)


def run_chunk(programs: Compiled, state: ppo.TrainState, targets):
    """One chunk of PPO updates for any number of tasks: (TrainState (N, ...), UpdateMetrics (N, chunk))."""
    return sharding.run_padded(programs.chunk, programs.mesh, state, jnp.asarray(targets, jnp.float32))


def task_rngs(seed: int, n_tasks: int) -> jax.Array:
    """(n_tasks, 2) raw keys, one per expert: expert i's run is the same alone or in a batch."""
    return jax.random.split(jax.random.PRNGKey(seed), n_tasks)


def abstract_state(programs: Compiled, n_tasks: int):
    """The TrainState (N, ...) shapes and dtypes, for restoring checkpoints."""
    shape = task_env.context_shape(programs.env.CONTEXT_SIZE)
    args = (task_rngs(0, n_tasks), jnp.zeros((n_tasks, *shape)), jnp.zeros((n_tasks, programs.start_size)))
    return jax.eval_shape(functools.partial(run_init, programs), *args)[0]


# -- training -----------------------------------------------------------------------------------


def csv_fields(unit: str) -> tuple:
    """progress.csv's columns: the target's column names its unit ("m/s" -> target_m_per_s)."""
    return ("update", "env_steps", "target_" + unit.replace("/", "_per_"), *ppo.UpdateMetrics._fields)


CSV_FIELDS = csv_fields("m")


def chunk_rows(first_update, metrics: ppo.UpdateMetrics, tasks, steps_per_update: int, fields=CSV_FIELDS) -> list:
    """CSV rows of one chunk: metrics (N tasks, n updates) -> N x n dicts with the columns `fields`."""
    m = jax.tree.map(np.asarray, metrics)
    rows = []
    for i, target in enumerate(tasks):
        for j in range(m.episode_return.shape[1]):
            update = int(first_update) + j + 1
            row = {"update": update, "env_steps": update * steps_per_update, fields[2]: task_env.context_json(target)}
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
        f" (worst {err[worst]:.2f} {unit} at {task_env.format_context(tasks[worst], '.1f')} {unit})"
        f"  valid {m.valid[:, -1].mean():.2f}  {eta}"
    )


def initial_state(cfg, run_dir: Path, programs: Compiled, say=print):
    """The experts' TrainState (N, ...) before PPO, from the task's expert start (fresh policies
    without one): written as checkpoint 0."""
    targets = np.asarray(cfg.experts.tasks, np.float32)  # (E,), or (E, K) for a vector context
    start = tasks.get(cfg.task).expert_start
    if start is None:
        starts = np.zeros((len(targets), 0))
    else:
        starts = start.starts(cfg, run_dir, run_dir / "experts", say)
    state, losses = run_init(programs, task_rngs(cfg.experts.seed, len(targets)), targets, starts)
    if start is not None:
        say(f"behaviour cloning: final mse per task {np.asarray(losses[:, -1]).round(6).tolist()}")
    return state


# -- one family: a centre expert first, every expert continued from it ----------------------------


def family_updates(cfg) -> tuple[int, int]:
    """(centre_updates, ramp_updates) of `experts.family` ((0, 0): every expert starts fresh)."""
    fam = cfg.experts.get("family")
    return (0, 0) if fam is None else (int(fam.centre_updates), int(fam.ramp_updates))


def centre_candidates(cfg) -> int:
    """How many centre experts are trained side by side before one is chosen (`experts.family`)."""
    fam = cfg.experts.get("family")
    return 1 if fam is None else int(fam.get("candidates", 1))


def choice_update(cfg) -> int:
    """After how many updates the centre candidates are compared (`sections.choice_update`)."""
    return stage_sections.choice_update(cfg.experts.family)


def family_centre(tasks) -> int:
    """The family's centre: the index of the training context nearest the contexts' mean."""
    t = np.asarray(tasks, np.float64).reshape(len(tasks), -1)
    return int(np.argmin(np.linalg.norm(t - t.mean(axis=0), axis=1)))


def ramped_targets(tasks: np.ndarray, centre: int, update: int, chunk: int, ramp: int) -> np.ndarray:
    """Every expert's training target for the chunk after `update` updates: its own context, or
    while the ramp lasts, the point (update + chunk) / ramp of the way from the centre's to it."""
    frac = 1.0 if ramp <= 0 else min(1.0, (update + chunk) / ramp)
    return tasks[centre] + (tasks - tasks[centre]) * frac


def family_state(centre: ppo.TrainState, rngs) -> ppo.TrainState:
    """The centre expert's TrainState (1, ...) copied to every expert (N = len(rngs)): the same
    policy, value net, optimiser and observation statistics; each its own rng, no updates yet."""
    n = len(rngs)
    state = jax.tree.map(lambda x: jnp.repeat(x, n, axis=0), centre)
    zeros = jnp.zeros((n,), state.update.dtype)
    return state._replace(
        rng=jnp.asarray(rngs, state.rng.dtype), update=zeros, env_steps=zeros.astype(state.env_steps.dtype)
    )


def chunked_loop(programs: Compiled, tasks, init, targets_at, n_updates: int) -> resumable.ChunkedTraining:
    """`resumable.ChunkedTraining` of experts on `tasks` (N,) or (N, K), starting from `init()`;
    targets_at(updates done) -> the chunk's training targets."""
    unit = programs.env.UNIT
    fields = csv_fields(unit)
    return resumable.ChunkedTraining(
        init=init,
        chunk=lambda state: run_chunk(programs, state, targets_at(int(np.asarray(state.update)[0]))),
        abstract=abstract_state(programs, len(tasks)),
        updates=lambda state: int(np.asarray(state.update)[0]),
        rows=lambda before, m: chunk_rows(before, m, tasks, programs.trainer.steps_per_update, fields),
        line=lambda m, update, eta: progress_line(tasks, m, update, n_updates, eta, unit),
        fields=fields,
    )


def centre_rounds(cfg) -> int:
    """At most how many rounds of fresh centre candidates are drawn (`experts.family.rounds`)."""
    fam = cfg.experts.get("family")
    return 1 if fam is None else int(fam.get("rounds", 1))


def round_dir(run_dir: Path, r: int) -> Path:
    """Round r's centre candidates (0: the first): run_dir/experts/centre, then centre_round2, ..."""
    return Path(run_dir) / "experts" / ("centre" if r == 0 else f"centre_round{r + 1}")


def round_rngs(own, k: int, r: int):
    """Round r's K candidates' rngs: round 0's first is the centre task's own, every other one
    folded from it, none twice over the rounds."""
    first = [own] if r == 0 else [jax.random.fold_in(own, 10_000 + r * k)]
    return jnp.stack([*first, *(jax.random.fold_in(own, 10_000 + r * k + c) for c in range(1, k))])


def train_centre(cfg, run_dir: Path, programs: Compiled, say=print, stop_after_chunks: int | None = None, r=0) -> dict:
    """Round r of the family's centre experts alone: `experts.family.candidates` of them side by
    side, each PPO updates up to the choice (`choice_update`) from a fresh policy of its own seed
    (`round_rngs`) on the centre context, under `round_dir` (resumable as the experts are).
    Returns `resumable.train_in_chunks`'s dict, its state (K, ...)."""
    tasks = task_env.as_contexts(cfg.experts.tasks, programs.env.CONTEXT_SIZE)
    i, k = family_centre(tasks), centre_candidates(cfg)
    (total, _), n = family_updates(cfg), choice_update(cfg)
    each = "" if k == 1 else f", {k} candidates side by side" + ("" if n == total else f" for the first {n}")
    where = f"{task_env.format_context(tasks[i])} {programs.env.UNIT}"
    rounds = centre_rounds(cfg)
    which = "" if rounds == 1 else f" (round {r + 1} of at most {rounds})"
    say(f"family: the centre expert at {where} first, {total} updates{each}{which}")
    rngs = round_rngs(task_rngs(cfg.experts.seed, len(tasks))[i], k, r)
    centre = np.repeat(tasks[i : i + 1], k, axis=0)
    start = np.zeros((k, programs.start_size))
    loop = chunked_loop(programs, centre, lambda: run_init(programs, rngs, centre, start)[0], lambda _: centre, n)
    return resumable.train_in_chunks(
        round_dir(run_dir, r), loop, n, cfg.experts.keep_checkpoints, say, stop_after_chunks
    )


def upright(candidate: dict) -> bool:
    """A candidate of a choice record stands upright (or its env reports no posture)."""
    return candidate.get("flipped_fraction", 0.0) <= evaluate.FLIPPED


def train_rounds(cfg, run_dir: Path, programs: Compiled, say=print, stop_after_chunks=None) -> dict:
    """The centre candidates' rounds (`train_centre`, `choose_centre`): another round only while
    every candidate of the last one runs flipped, at most `experts.family.rounds`. Returns
    {"state": the chosen candidate (1, ...), "finished", "wall_s"} (its state, unfinished)."""
    wall, rounds = 0.0, centre_rounds(cfg)
    for r in range(rounds):
        out = train_centre(cfg, run_dir, programs, say, stop_after_chunks, r)
        wall += out["wall_s"]
        if not out["finished"]:
            return {**out, "wall_s": wall}
        choice = choose_centre(cfg, run_dir, programs, out["state"], say, r)
        if upright(choice["candidates"][choice["chosen"]]) or r + 1 == rounds:
            break
        say(f"family: every candidate of round {r + 1} runs flipped: {centre_candidates(cfg)} fresh ones")
    c = choice["chosen"]
    return {"state": jax.tree.map(lambda x: x[c : c + 1], out["state"]), "finished": True, "wall_s": wall}


def train_chosen(cfg, run_dir: Path, programs: Compiled, chosen: ppo.TrainState, say=print, stop_after_chunks=None):
    """The chosen centre candidate (1, ...) alone from the choice to `experts.family.centre_updates`,
    under run_dir/experts/centre_chosen (resumable). Returns `resumable.train_in_chunks`'s dict."""
    tasks = task_env.as_contexts(cfg.experts.tasks, programs.env.CONTEXT_SIZE)
    i, (n, _) = family_centre(tasks), family_updates(cfg)
    centre = tasks[i : i + 1]
    say(f"family: the chosen centre alone from update {choice_update(cfg)} to {n}")
    loop = chunked_loop(programs, centre, lambda: chosen, lambda _: centre, n)
    stage_dir = run_dir / "experts" / "centre_chosen"
    return resumable.train_in_chunks(stage_dir, loop, n, cfg.experts.keep_checkpoints, say, stop_after_chunks)


def choose_centre(cfg, run_dir: Path, programs: Compiled, state: ppo.TrainState, say=print, r: int = 0) -> dict:
    """Which of round r's centre candidates the family continues from: each runs
    `experts.eval.repetitions` noisy episodes on the centre context (the same keys for all); the
    upright ones (where the env reports a posture: most steps not flipped) first, then the lowest
    error. Written to choice.json in `round_dir` on the first call and read back on the next, so a
    resumed run continues from the same one. Returns that record ({"chosen", "candidates": [...]})."""
    path = round_dir(run_dir, r) / "choice.json"
    runio.sync("centre choice")  # every process sees the same: the choice made, or not yet
    if not path.exists():
        runio.write_json(path, centre_choice(cfg, programs, state, say))
        runio.sync("centre chosen")
    return runio.read_json(path)  # every process continues from the first one's choice


def centre_choice(cfg, programs: Compiled, state: ppo.TrainState, say=print) -> dict:
    """`choose_centre`'s record, measured now."""
    env, e = programs.env, cfg.experts
    tasks = task_env.as_contexts(e.tasks, env.CONTEXT_SIZE)
    k = len(np.asarray(state.update))
    targets = np.repeat(np.asarray(env.check_targets(tasks), np.float32)[family_centre(tasks)][None], k, axis=0)
    keys = jnp.repeat(rollout.repetition_keys(e.eval.seed, 1, e.eval.repetitions), k, axis=0)  # the same for all
    apply = task_expert_policy(cfg, programs)
    metrics, posture = own_context_rollouts(env, apply, expert_params(state), targets, keys)
    errors = np.asarray(metrics["final_error"], np.float64).mean(axis=1)
    candidates = [{"error_m": float(errors[c]), **{n: float(v[c]) for n, v in posture.items()}} for c in range(k)]
    chosen = min(range(k), key=lambda c: (not upright(candidates[c]), candidates[c]["error_m"]))
    steps = k * int(e.eval.repetitions) * env.n_steps  # the choice's episodes
    record = {"chosen": chosen, "candidates": candidates, "repetitions": int(e.eval.repetitions), "env_steps": steps}
    if k > 1:
        shown = ", ".join(f"{c['error_m']:.3f}" + ("" if upright(c) else " (flipped)") for c in candidates)
        say(f"family: centre candidates' errors {shown} {env.UNIT}: continuing from candidate {chosen}")
    return record


def train(cfg, run_dir: Path, programs: Compiled, say=print, stop_after_chunks: int | None = None) -> dict:
    """Train every task's expert under run_dir/experts, resuming from its newest readable checkpoint;
    with `experts.family`, the centre expert first (`train_centre`) and every expert from it.

    Returns {"state": TrainState (N, ...), "finished": bool, "wall_s": training seconds over every call}.
    """
    import orbax.checkpoint as ocp  # noqa: PLC0415

    stage_dir = run_dir / "experts"
    tasks = task_env.as_contexts(cfg.experts.tasks, programs.env.CONTEXT_SIZE)  # (E,) or (E, K)
    total = programs.trainer.n_updates
    centre_updates, ramp = family_updates(cfg)
    centre_s = 0.0
    if centre_updates:
        centre = train_rounds(cfg, run_dir, programs, say, stop_after_chunks)
        if not centre["finished"]:
            return centre
        centre_s, chosen = centre["wall_s"], centre["state"]
        if choice_update(cfg) < centre_updates:  # the chosen one goes on alone
            alone = train_chosen(cfg, run_dir, programs, chosen, say, stop_after_chunks)
            centre_s += alone["wall_s"]
            if not alone["finished"]:
                return {**alone, "wall_s": centre_s, "finished": False}
            chosen = alone["state"]
        rngs = jax.vmap(lambda k: jax.random.fold_in(k, 1))(task_rngs(cfg.experts.seed, len(tasks)))
        init = functools.partial(family_state, chosen, rngs)
    else:
        init = functools.partial(initial_state, cfg, run_dir, programs, say)
    i, chunk = family_centre(tasks), int(cfg.experts.updates_per_chunk)
    loop = chunked_loop(programs, tasks, init, lambda u: ramped_targets(tasks, i, u, chunk, ramp), total)
    out = resumable.train_in_chunks(stage_dir, loop, total, cfg.experts.keep_checkpoints, say, stop_after_chunks)
    out["wall_s"] += centre_s
    if out["finished"]:
        with ocp.StandardCheckpointer() as checkpointer:  # leaving the context waits for the write
            params = resumable.savable(expert_params(out["state"]))
            checkpointer.save((stage_dir / "final_params").resolve(), params, force=True)
        runio.write_checksums(stage_dir / "final_params")
        runio.sync("final_params")
    return out


# What rebuilds an expert's policy besides the env's sizes: its PPO networks' keys.
POLICY_KEYS = ("policy_hidden", "value_hidden", "normalize_observations", "init_log_std")


def policy_record(ppo_cfg, env) -> dict:
    """The experts' policy as their record describes it: observation and action sizes and the PPO
    networks' architecture (`POLICY_KEYS`), all a reader needs to rebuild it."""
    shape = {"obs_size": int(env.observation_size), "action_size": int(env.action_size)}
    return {**shape, **{k: jsonable(ppo_cfg[k]) for k in POLICY_KEYS}}


def policy_networks(policy: dict):
    """The PPO networks of a `policy_record`."""
    arch = ml_collections.ConfigDict({k: tuple(v) if isinstance(v, list) else v for k, v in policy.items()})
    return ppo.make_networks(arch, policy["obs_size"], policy["action_size"])


def abstract_params(policy: dict, n_tasks: int) -> ExpertParams:
    """The ExpertParams (N, ...) shapes and dtypes of `n_tasks` experts of a `policy_record`."""
    networks = policy_networks(policy)
    one = jax.eval_shape(
        lambda: ExpertParams(ppo.init_normalizer(policy["obs_size"]), networks.policy_network.init(jax.random.key(0)))
    )
    return jax.tree.map(lambda a: jax.ShapeDtypeStruct((n_tasks, *a.shape), a.dtype), one)


def load_final_params(stage_dir: Path, policy: dict, n_tasks: int) -> ExpertParams:
    """The ExpertParams (N, ...) saved under stage_dir/final_params, of experts of a `policy_record`;
    ValueError naming it if unreadable."""
    import orbax.checkpoint as ocp  # noqa: PLC0415

    final = (Path(stage_dir) / "final_params").resolve()
    runio.verify_checksums(final)  # CorruptError (a ValueError) naming a changed file
    try:
        with ocp.StandardCheckpointer() as checkpointer:  # closed on leaving: no thread outlives the read
            return checkpointer.restore(final, abstract_params(policy, n_tasks))
    except Exception as err:  # noqa: BLE001 (orbax and tensorstore raise many kinds)
        reason = type(err).__name__
        raise ValueError(f"{final}: cannot read the trained experts ({reason}); rerun train-experts") from None


def load_family(cfg, run_dir: Path) -> Family:
    """The trained experts of a run, for behaviour cloning and replays: rebuilt from their record
    (`policy_record`) and final_params, not from the trainer that made them; `cfg` gives the env."""
    stage_dir = Path(run_dir) / "experts"
    record = runio.read_json(stage_dir / OUTPUT, "the experts' record: run train-experts first")
    env = tasks.make_env(cfg.task, cfg.env)
    policy = record.get("policy") or policy_record(cfg.experts.ppo, env)  # a record from before it was kept
    params = load_final_params(stage_dir, policy, len(cfg.experts.tasks))
    return Family(expert_policy(policy_networks(policy), env), params, np.asarray(cfg.experts.tasks, np.float64))


def own_context_rollouts(env, apply, params, targets, keys) -> tuple[dict, dict]:
    """Each expert on its own target, its keys' (E, R) noisy episodes: final metrics of (E, R)
    and, for an env that defines `posture`, its statistics averaged over the same episodes
    ({name: (E,)}; {} otherwise), from one rollout that records the bodies' positions."""
    if type(env).posture is task_env.ContextualEnv.posture:
        return evaluate.evaluate_experts(env, apply, params, targets, keys.shape[1], keys=keys), {}
    metrics, qpos = rollout.matched_fn(env, apply, record="qpos")(params, targets, targets, keys)
    posture = {k: np.asarray(v).mean(axis=1) for k, v in env.posture(np.asarray(qpos)).items()}
    return jax.tree.map(np.asarray, metrics), posture


def evaluate_on_own(cfg, programs: Compiled, params: ExpertParams) -> tuple[dict, dict]:
    """Every expert on its own context, `eval.repetitions` noisy episodes (`own_context_rollouts`)."""
    env, e = programs.env, cfg.experts
    targets = np.asarray(env.check_targets(e.tasks), np.float32)
    keys = rollout.repetition_keys(e.eval.seed, len(targets), e.eval.repetitions)  # evaluate_experts' keys
    return own_context_rollouts(env, task_expert_policy(cfg, programs), params, targets, keys)


# An expert whose training error fell by more than this fraction from one tenth of its updates to
# the last tenth was still learning when its budget ended.
STILL_FALLING = 0.05


def training_tail(progress: Path, unit: str = "m") -> dict | None:
    """Whether each expert was still learning at the end: from progress.csv (targets in `unit`),
    every expert's mean training `final_error` over its last tenth of updates (at least one) against
    the tenth before. None where there are fewer than two updates (or no log)."""
    import csv  # noqa: PLC0415

    if not progress.exists():
        return None
    target = csv_fields(unit)[2]
    curves: dict[str, list[float]] = {}
    with progress.open() as f:
        for row in csv.DictReader(f):
            curves.setdefault(row[target], []).append(float(row["final_error"]))
    n = min((len(c) for c in curves.values()), default=0)
    if n < 2:
        return None
    k = max(1, n // 10)
    before = np.array([np.mean(c[n - 2 * k : n - k]) for c in curves.values()])
    last = np.array([np.mean(c[n - k : n]) for c in curves.values()])
    falling = before - last > STILL_FALLING * np.abs(before)
    return {
        "updates_compared": k,
        "threshold": STILL_FALLING,
        "still_falling": int(falling.sum()),
        "n_experts": len(curves),
        "per_task_drop": (before - last).tolist(),  # in the order of progress.csv's first appearance
    }


def tail_line(tail: dict | None, unit: str) -> str:
    """The training tail in words, or "" without one."""
    if not tail:
        return ""
    k, pct = tail["updates_compared"], f"{tail['threshold']:.0%}"
    return (f"{tail['still_falling']} of {tail['n_experts']} experts were still learning when their budget ended "
            f"(training error over their last {k} updates below the {k} before by more than {pct}; "
            f"largest drop {max(tail['per_task_drop']):.3g} {unit}).\n")  # fmt: skip


def evaluate_experts(cfg, stage_dir: Path, params: ExpertParams, programs: Compiled, wall_s: float, say=print) -> dict:
    """Every expert on its own task (`eval.repetitions` noisy episodes each): experts.json and experts.md."""
    start = time.perf_counter()
    e = cfg.experts
    say(f"evaluating {len(e.tasks)} experts x {e.eval.repetitions} noisy episodes (compiling first)", flush=True)
    metrics, posture = evaluate_on_own(cfg, programs, params)
    record = evaluate.experts_record(e.tasks, metrics, programs.trainer.n_updates * programs.trainer.steps_per_update)
    task = tasks.get(cfg.task)
    centre_updates, _ = family_updates(cfg)
    if task.expert_start is None:  # every env step an expert cost is PPO's (its share of the centre's)
        made = (round_dir(stage_dir.parent, r) / "choice.json" for r in range(centre_rounds(cfg)))
        choices = [runio.read_json(path) for path in made if path.exists()]
        used = max(1, len(choices))  # rounds of candidates the run drew
        centre_steps = (
            stage_sections.centre_env_updates(e.family, used) * programs.trainer.steps_per_update
            if centre_updates
            else 0
        )
        record["env_steps_breakdown"] = {"ppo": record["env_steps"]}
        if centre_steps:
            record["env_steps_breakdown"]["family_centre_share"] = centre_steps // len(e.tasks)
            record["family_centre"] = {"context": task_env.context_json(e.tasks[family_centre(e.tasks)]),
                                       "updates": centre_updates, "choose_after": choice_update(cfg),
                                       "env_steps": centre_steps}  # fmt: skip
            if choices:  # every round's candidates and the one the family continued from (their episodes' steps)
                offset = sum(len(c["candidates"]) for c in choices[:-1])
                record["family_centre"].update(
                    chosen=offset + choices[-1]["chosen"],
                    candidates=[{**c, "round": r + 1} for r, ch in enumerate(choices) for c in ch["candidates"]],
                    repetitions=choices[-1]["repetitions"],
                    rounds=used,
                    choice_env_steps=sum(ch["env_steps"] for ch in choices),
                )
    else:
        record.update(task.expert_start.describe(cfg, stage_dir.parent, stage_dir, programs.env, record))
    known = [v for v in record["env_steps_breakdown"].values() if v is not None]
    record["env_steps_total"] = int(sum(known))  # per expert, the parts that are known
    record["family_check"] = evaluate.family_check(programs.env, e.tasks, metrics, posture)
    record["training_tail"] = training_tail(stage_dir / "progress.csv", programs.env.UNIT)
    record.update(runio.provenance(cfg.preset, wall_s + time.perf_counter() - start, config.resolved_env(cfg)))
    record.update(task=cfg.task, unit=task.unit, eval_repetitions=int(e.eval.repetitions))
    record["policy"] = policy_record(e.ppo, programs.env)  # what rebuilds the experts from final_params
    family = evaluate.family_table(record["family_check"], programs.env.UNIT)
    say(family)
    tail = tail_line(record["training_tail"], task.unit)
    if tail:
        say(tail)
    runio.write_text(stage_dir / "experts.md", task.report.experts(record) + "\n" + tail + "\n" + family)
    runio.write_json(stage_dir / OUTPUT, record)
    return record


def run(cfg, run_dir: Path, say=print) -> dict:
    """The stage: train (or resume) every expert, then evaluate them; returns experts.json's record."""
    stage_dir = Path(run_dir) / "experts"
    programs = compile_programs(cfg)
    n = len(cfg.experts.tasks)
    if (stage_dir / "final_params").exists():  # trained; a previous call stopped before its evaluation
        say(f"experts already trained ({stage_dir / 'final_params'}): evaluating them")
        params = load_final_params(stage_dir, policy_record(cfg.experts.ppo, programs.env), n)
        wall = 0.0
        rounds = [round_dir(run_dir, r).name for r in range(centre_rounds(cfg))]
        for clock_path in (stage_dir / part / "wall_time.json" for part in ("", *rounds, "centre_chosen")):
            clock = runio.read_json(clock_path) if clock_path.exists() else {}
            wall += max([0.0, *map(float, clock.values())])
    else:
        out = train(cfg, run_dir, programs, say)
        params, wall = expert_params(out["state"]), out["wall_s"]
    record = evaluate_experts(cfg, stage_dir, params, programs, wall, say)
    # The record and final_params hold everything later stages read: the training checkpoints
    # (most of a paper run directory's size) go, once final_params is verified.
    runio.verify_checksums(stage_dir / "final_params")
    start = tasks.get(cfg.task).expert_start
    for scratch in (
        "checkpoints",
        *(f"{round_dir(run_dir, r).name}/checkpoints" for r in range(centre_rounds(cfg))),
        "centre_chosen/checkpoints",
        *(() if start is None else start.scratch()),
    ):
        runio.remove(stage_dir / scratch)
    say(tasks.get(cfg.task).report.experts(record))
    return record
