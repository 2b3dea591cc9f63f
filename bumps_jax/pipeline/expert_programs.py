"""The experts' compiled programs: every expert's PPO init and chunk of updates vmapped over the
tasks and split over the devices and processes (`sharding.over_batch`), their deterministic
policies, and the chunked training loop over them (`resumable.ChunkedTraining`) with its
progress.csv rows and progress lines. Used by the experts stage (`stages/experts.py`) and the
family's centre (`family.py`)."""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax import resumable
from bumps_jax.algo import evaluate, ppo, rollout, sharding
from bumps_jax.envs import base as task_env
from bumps_jax.pipeline.programs import stage_env
from bumps_jax.tasks import registry as tasks


class ExpertParams(NamedTuple):
    """What a deterministic expert needs: observation statistics and policy params."""

    normalizer: Any
    policy: Any


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
    env = env or stage_env(cfg.env, cfg.task)
    mesh = mesh or sharding.device_mesh(impl=env.config.impl)
    trainer = ppo.make_train(cfg.experts.ppo, env, prefix="experts.ppo.")
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


def own_context_rollouts(env, apply, params, targets, keys) -> tuple[dict, dict]:
    """Each expert on its own target, its keys' (E, R) noisy episodes: final metrics of (E, R)
    and, for an env that defines `posture`, its statistics averaged over the same episodes
    ({name: (E,)}; {} otherwise), from one rollout that records the bodies' positions."""
    if type(env).posture is task_env.ContextualEnv.posture:
        return evaluate.evaluate_experts(env, apply, params, targets, keys.shape[1], keys=keys), {}
    metrics, qpos = rollout.matched_fn(env, apply, record="qpos")(params, targets, targets, keys)
    posture = {k: np.asarray(v).mean(axis=1) for k, v in env.posture(np.asarray(qpos)).items()}
    return jax.tree.map(np.asarray, metrics), posture
