"""The single-task expert policies: behaviour cloning of the kick prior, then PPO, all tasks at once.

Every expert is a Gaussian MLP policy over (phase, context). It starts by regressing its mean
onto the keyframe prior's 75 joint-target vectors (the paper imitates an initial kick before
PPO), then `ppo` refines it on its own target distance. Both stages are vmapped over the
tasks: one compiled program trains all experts.

The host loop runs jitted chunks of `updates_per_chunk` PPO updates; between chunks it prints
progress, appends `progress.csv`, and saves an orbax checkpoint. A killed run restarts from
the last checkpoint and ends exactly where an uninterrupted one would: every random number
comes from the carried `TrainState.rng`.

    python -m bumps_jax.experts --preset tiny --run-dir runs/experts_tiny
"""

from __future__ import annotations

import csv
import functools
import json
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
import orbax.checkpoint as ocp

from bumps_jax import evaluate, kick_env, ppo, prior, results, sharding, synthetic_experts

PRESETS = ("tiny", "paper")


def default_config() -> ml_collections.ConfigDict:
    """Every number of expert training, in one place (the `tiny` preset's values)."""
    cfg = ml_collections.ConfigDict()
    cfg.preset = "tiny"
    cfg.tasks = (8.0, 12.0, 16.0)  # target distances (m), one expert each
    cfg.seed = 0
    cfg.updates_per_chunk = 2  # PPO updates per jitted chunk (progress + checkpoint between)
    cfg.keep_checkpoints = 2
    # The kick prior record (`prior.load_prior`) the experts start from; "" is the committed asset
    # (prior.PRIOR_JSON). The command line sets a run's own (<run>/prior/prior.RUN_PRIOR_JSON) when
    # the run made one: the asset is global, and a kick-prior run elsewhere may rewrite it.
    cfg.prior_path = ""
    cfg.bc = ml_collections.ConfigDict()
    # Full-batch Adam steps on the prior's 75 (obs, action) rows, cosine-decayed: 2000 steps at
    # 3e-3 left 0.15 rad errors at the swing's corners and the kick missed the ball; 20000 at
    # 1e-2 fit within 0.05 rad and kicked as the prior does (CPU trial, 4 s).
    cfg.bc.steps = 20000
    cfg.bc.learning_rate = 1e-2
    # Clone the prior's blended kick at the strength calibrated for each task (its committed
    # sweep, `prior.kick_for`), so every expert starts near its own distance; False clones the
    # one 12 m kick for all, as the paper's multi-task baseline did.
    cfg.bc.per_task_strength = True
    # CMA-ES on each task's starting kick before cloning it (`starting_kicks`), all tasks in one
    # vmapped program; 0 generations clones the blended prior as it is.
    cfg.tune = ml_collections.ConfigDict()
    cfg.tune.generations = 1
    cfg.tune.sigma_init = 0.5  # in units of the prior's PARAM_SCALE, around each task's start
    cfg.tune.population_size = 4
    cfg.tune.repetitions = 2  # noisy kicks per candidate per generation
    cfg.tune.eval_repetitions = 4  # fresh kicks to choose between start and tuned
    cfg.tune.seed = 0
    # Start each task's search from the best of its blended kick and the prior's three anchors
    # (short, 12 m, long), scored on `eval_repetitions` noisy kicks at the task's distance: the
    # blend is not monotone between the anchors (with the 2.5 ms physics step, from 11.8 m at
    # strength 0.5 it falls to 9.0 m at 0.58 and jumps to 21-28 m from 0.625; a CPU sweep).
    cfg.tune.anchor_starts = False
    cfg.ppo = ppo.default_config()
    cfg.ppo.num_envs = 8
    cfg.ppo.num_minibatches = 2
    cfg.ppo.num_epochs = 4
    cfg.ppo.total_env_steps = 8 * 75 * 4  # 4 updates
    # CPU trials (16 episodes per update): lr 1e-3 or 3e-4 broke the kick within a few updates
    # (KL 20-200: with sigma ~0.02 rad a small step of the mean is a large KL).
    cfg.ppo.learning_rate = 3e-5
    # CPU-sized runs explore more than the paper's sigma = 0.0025 rad (log-std -6).
    cfg.ppo.init_log_std = -4.0
    cfg.eval = ml_collections.ConfigDict()
    cfg.eval.repetitions = 8  # paper: 100
    cfg.eval.seed = 1
    return cfg


def paper_config() -> ml_collections.ConfigDict:
    """The GPU preset: the paper's 23 tasks and budgets, batches scaled to a GPU.

    Paper (Baselines PPO1, one CPU simulator): 4096 steps per batch, minibatch 1024, 30 epochs,
    12M steps per expert -> ~2930 updates x 4 minibatches x 30 epochs = 352k Adam steps.
    Ours: 256 episodes x 75 steps = 19200 steps per batch, 16 minibatches of 16 episodes
    (1200 steps, ~ the paper's 1024), 30 epochs, 12M steps -> 625 updates x 16 x 30 = 300k
    Adam steps: the same number and size of gradient steps, so the paper's lr 1e-6 carries over.
    """
    return make_config(
        overrides={
            "preset": "paper",
            "tasks": kick_env.meta_train_tasks(),
            "updates_per_chunk": 25,  # 625 updates = 25 chunks
            "keep_checkpoints": 3,
            # From the best of blend and anchors, steps of 2 scale units for 60 generations: a
            # search from the 12 m anchor this way (H100, 70 generations, 2.5 ms physics) left
            # 0.51 m of mean error over the 23 tasks, the best of the three anchors' 0.38 m
            # (experiments/results/strike_search_all_tasks_dt2.5ms_gpu.json).
            "tune.anchor_starts": True,
            "tune.sigma_init": 2.0,
            "tune.generations": 60,
            "tune.population_size": 32,
            "tune.repetitions": 8,
            "tune.eval_repetitions": 32,
            "ppo.num_envs": 256,  # paper: 4096 steps per batch
            "ppo.num_minibatches": 16,  # paper: minibatch 1024 steps; ours 16 x 75 = 1200
            "ppo.num_epochs": 30,  # paper: 30
            "ppo.total_env_steps": 256 * 75 * 625,  # 12.0M, paper: 12M per expert
            # Paper: 1e-6, constant. Tried on an H100 (a whole run, its prior re-optimised too):
            # 3e-5 decayed linearly to 0 (ppo.anneal_learning_rate) gave experts of 0.73 m mean
            # error against 0.77 m, but the 4x256 meta-policy cloned from them erred 1.36 m
            # against 0.92 m (experiments/results/experts_lr3e-5_anneal_h100.json): kept 1e-6.
            "ppo.learning_rate": 1e-6,
            "ppo.init_log_std": -6.0,  # paper: -6
            "ppo.reward_scaling": 0.01,  # paper: 0.1, which the env applies already (see ppo.py)
            "eval.repetitions": 100,  # paper: 100
        }
    )


def preset_config(name: str) -> ml_collections.ConfigDict:
    if name == "tiny":
        return make_config()
    if name == "paper":
        return paper_config()
    raise ValueError(f"unknown preset {name!r}; choose one of {PRESETS}")


def make_config(config=None, overrides: dict | None = None) -> ml_collections.ConfigDict:
    """A locked copy of `config` (default: `default_config()`) with dotted `overrides`."""
    return kick_env.make_config(default_config() if config is None else config, overrides)


def validate_config(cfg: ml_collections.ConfigDict, env: kick_env.KickEnv) -> None:
    """ValueError naming the first bad value; runs before anything compiles."""
    if len(cfg.tasks) == 0:
        raise ValueError("tasks is empty: give at least one target distance (m)")
    kick_env.check_targets(cfg.tasks, env.config.task_range)
    for key in ("updates_per_chunk", "keep_checkpoints", "bc.steps", "eval.repetitions"):
        node, leaf = (cfg, key) if "." not in key else (cfg[key.split(".")[0]], key.split(".")[1])
        value = node[leaf]
        if not isinstance(value, int | np.integer) or value < 1:
            raise ValueError(f"{key} must be a positive integer, got {value!r}")
    if not np.isfinite(cfg.bc.learning_rate) or cfg.bc.learning_rate <= 0:
        raise ValueError(f"bc.learning_rate must be > 0, got {cfg.bc.learning_rate!r}")
    ppo.validate_config(cfg.ppo, env.n_steps)
    total = ppo.n_updates(cfg.ppo, env.n_steps)
    if total % cfg.updates_per_chunk:
        raise ValueError(
            f"updates_per_chunk {cfg.updates_per_chunk} must divide the {total} updates that "
            f"ppo.total_env_steps {cfg.ppo.total_env_steps} buys (one compiled chunk size)"
        )


# -- behaviour cloning ------------------------------------------------------------------------


class BCCarry(NamedTuple):
    policy: Any  # policy network params
    opt_state: Any


def bc_dataset(env: kick_env.KickEnv, target, prior_params) -> tuple[jax.Array, jax.Array]:
    """The prior's kick as (obs (T, 2), actions (T, 22)) for an expert of `target` m.

    obs[k] is what the env shows before step k: (k / T, normalised target); actions[k] the
    prior's joint targets for step k.
    """
    lo, hi = env.config.task_range
    phase = jnp.arange(env.n_steps, dtype=jnp.float32) / env.n_steps
    context = jnp.full_like(phase, (jnp.asarray(target, jnp.float32) - lo) / (hi - lo))
    actions = prior.keyframes_to_actions(prior_params, env.n_steps, env.dt)
    return jnp.stack([phase, context], axis=-1), actions


def _bc_loss(networks, normalizer, policy, obs, actions):
    """Mean squared error (rad^2) of the policy mean against the prior's actions."""
    return jnp.mean(jnp.square(ppo.policy_mean(networks, normalizer, policy, obs) - actions))


def _bc_step(networks, optimizer, normalizer, obs, actions, carry: BCCarry, _unused):
    """One full-batch Adam step: (carry, None) -> (carry, loss)."""
    loss, grads = jax.value_and_grad(_bc_loss, argnums=2)(networks, normalizer, carry.policy, obs, actions)
    updates, opt_state = optimizer.update(grads, carry.opt_state, carry.policy)
    return BCCarry(optax.apply_updates(carry.policy, updates), opt_state), loss


def behaviour_clone(networks, policy, obs, actions, steps: int, learning_rate: float):
    """Fit the policy mean to (obs (T, 2), actions (T, 22)). Returns (policy params, losses (steps,)).

    Only the mean's weights move: the log-std keeps its initial value (its gradient is zero).
    """
    # Cosine decay to 1% of the peak: the kick's sharp swing (0.1 rad errors at its corners
    # with a constant rate) needs the late small steps to be fitted closely enough to strike.
    optimizer = optax.adam(optax.cosine_decay_schedule(learning_rate, steps, alpha=0.01))
    normalizer = ppo.init_normalizer(obs.shape[-1])
    body = functools.partial(_bc_step, networks, optimizer, normalizer, obs, actions)
    carry, losses = jax.lax.scan(body, BCCarry(policy, optimizer.init(policy)), None, steps)
    return carry.policy, losses


def prior_file(cfg: ml_collections.ConfigDict) -> Path:
    """The kick prior record `cfg.prior_path` names (the committed asset if empty); ValueError
    naming the path if there is no such file.

    Checked here, where the prior is read, not in `validate_config`: that also runs when a
    finished run's experts are reloaded from its config.json, which needs no prior and may
    name one on the machine that trained them.
    """
    path = Path(cfg.prior_path) if cfg.prior_path else prior.PRIOR_JSON
    if not path.is_file():
        raise ValueError(f"prior_path: no kick prior record at {str(path)!r}")
    return path


def starting_kicks(cfg: ml_collections.ConfigDict, verbose: bool = True) -> tuple[np.ndarray, dict]:
    """The keyframe kick (T, 14) each expert clones before PPO, and a record of how it was made.

    The blended prior at the strength calibrated for the task (or the one 12 m kick, as the
    paper's baseline did), or with `tune.anchor_starts` the best of that blend and the prior's
    three anchors at the task's distance. Then, if `tune.generations` > 0, CMA-ES on every
    task's kick at once (`prior.tune_for_tasks`): between the prior's sweep points the blend is
    erratic, and PPO with the paper's small steps does not move a kick metres.
    """
    record = prior.load_prior(prior_file(cfg))
    targets = np.asarray(cfg.tasks, np.float32)
    keys = ("population_size", "repetitions", "eval_repetitions", "seed")
    tune_cfg = prior.make_config(None, {k: cfg.tune[k] for k in keys})
    info = {"tasks_m": targets.tolist(), "tuned": False}
    if cfg.bc.per_task_strength:
        anchors = jnp.asarray(record["anchors"], jnp.float32)  # short, 12 m, long
        table = jnp.asarray(prior.calibration(record))  # (strength, distance) from the prior's sweep
        starts = np.asarray(jax.vmap(lambda t: prior.kick_for(anchors, table, t))(jnp.asarray(targets)))
        if cfg.tune.anchor_starts:
            candidates = np.concatenate([starts[:, None], np.broadcast_to(anchors, (len(targets), *anchors.shape))], 1)
            starts, chosen, costs = prior.best_starts(targets, candidates, tune_cfg, cfg.tune.eval_repetitions)
            names = ("blend", *prior.ANCHORS)
            info.update(candidates=list(names), candidate_costs=costs.tolist(), chosen=[names[i] for i in chosen])
            if verbose:
                print(
                    "starting kicks chosen from blend and anchors:",
                    dict(zip(targets.tolist(), info["chosen"], strict=True)),
                )
    else:
        starts = np.tile(np.asarray(record["params"], np.float32), (len(targets), 1))
    if cfg.tune.generations > 0:
        t0 = time.perf_counter()
        out = prior.tune_for_tasks(targets, starts, tune_cfg, cfg.tune.generations, cfg.tune.sigma_init, verbose)
        starts = out["params"]
        info = {
            **info,
            "tuned": True,
            "wall_s": time.perf_counter() - t0,
            "episodes": out["episodes"],
            "start_cost": out["start_cost"].tolist(),
            "tuned_cost": out["tuned_cost"].tolist(),
            "improved": out["improved"].tolist(),
            "history_best_cost": out["history"].tolist(),
        }
    info["params"] = np.asarray(starts).tolist()
    return np.asarray(starts, np.float32), info


def read_starting_kicks(path, targets) -> dict[float, np.ndarray]:
    """Each of `targets`' (m) kick params (14,) from a run's starting_kicks.json (`starting_kicks`'
    record); ValueError naming the targets the record lacks."""
    record = json.loads(Path(path).read_text())
    tasks = [float(t) for t in record["tasks_m"]]
    missing = [t for t in targets if t not in tasks]
    if missing:
        raise ValueError(f"targets {missing} not among the kicks' tasks {tasks}")
    return {t: np.asarray(record["params"][tasks.index(t)], np.float32) for t in targets}


def make_init(cfg: ml_collections.ConfigDict, env: kick_env.KickEnv, trainer: ppo.Trainer):
    """A pure fn (rng, target, kick params (14,)) -> (TrainState after behaviour cloning of that
    kick, BC losses (steps,)). vmap over tasks."""

    def init(rng, target, kick):
        rng_state, rng_policy = jax.random.split(rng)
        policy = trainer.networks.policy_network.init(rng_policy)
        obs, actions = bc_dataset(env, target, kick)
        policy, losses = behaviour_clone(trainer.networks, policy, obs, actions, cfg.bc.steps, cfg.bc.learning_rate)
        return trainer.init(rng_state, policy), losses

    return init


# -- the expert policy ------------------------------------------------------------------------


class ExpertParams(NamedTuple):
    """What a deterministic expert needs: observation statistics and policy params."""

    normalizer: Any
    policy: Any


def expert_params(state: ppo.TrainState) -> ExpertParams:
    return ExpertParams(state.normalizer, state.params.policy)


def expert_policy(networks):
    """apply_fn(ExpertParams, obs (2,)) -> action (22,): the Gaussian's mean.

    Usable with `evaluate.episode_fn(env, expert_policy(networks))`.
    """

    def apply(params: ExpertParams, obs):
        return ppo.policy_mean(networks, params.normalizer, params.policy, obs)

    return apply


# -- training ---------------------------------------------------------------------------------


class Compiled(NamedTuple):
    """The jitted, task-vmapped programs of one config."""

    env: kick_env.KickEnv
    trainer: ppo.Trainer
    mesh: Any  # the devices the task axis is split over (`sharding.device_mesh`)
    # Both take and return batches whose task axis N is a multiple of the mesh size (`run_init`
    # and `train_experts` pad and unpad):
    init: Any  # (rngs (N, 2), targets (N,), kicks (N, 14)) -> (TrainState (N,...), BC losses (N, steps))
    chunk: Any  # (TrainState (N,...), targets (N,)) -> (TrainState, UpdateMetrics (N, chunk))


def compile_programs(
    cfg: ml_collections.ConfigDict, env: kick_env.KickEnv | None = None, mesh=None, method: str = "jit"
) -> Compiled:
    """Validate `cfg` and build the jitted task-vmapped programs, split over `mesh` (default:
    every device) along the task axis (`sharding.over_batch`'s `method`); compiled on first call."""
    env = env or kick_env.KickEnv()
    validate_config(cfg, env)
    mesh = mesh or sharding.device_mesh()
    trainer = ppo.make_train(cfg.ppo, env)
    init = sharding.over_batch(jax.vmap(make_init(cfg, env, trainer)), mesh, (True, True, True), method=method)
    n = int(cfg.updates_per_chunk)
    chunk = jax.vmap(lambda state, target: trainer.run_updates(state, target, n))
    return Compiled(env, trainer, mesh, init, sharding.over_batch(chunk, mesh, (True, True), method=method))


def run_init(programs: Compiled, rngs, targets, kicks):
    """BC of `kicks` (N, 14) for any number N of tasks: (TrainState (N, ...), BC losses (N, steps))."""
    n = len(targets)
    size = sharding.padded_size(n, programs.mesh)
    args = (rngs, jnp.asarray(targets, jnp.float32), jnp.asarray(kicks, jnp.float32))
    out = programs.init(*sharding.place(sharding.pad(args, size), programs.mesh))
    # Strong dtypes throughout (Adam starts its count weakly typed): the chunk program then
    # sees one input type from the first chunk on and compiles once.
    return jax.tree.map(lambda x: x.astype(x.dtype), sharding.unpad(out, n))


def run_chunk(programs: Compiled, state: ppo.TrainState, targets):
    """One chunk of PPO updates for any number of tasks: (TrainState (N, ...), UpdateMetrics (N, chunk))."""
    n = len(targets)
    size = sharding.padded_size(n, programs.mesh)
    args = sharding.pad((state, jnp.asarray(targets, jnp.float32)), size)
    out = programs.chunk(*sharding.place(args, programs.mesh))
    return sharding.unpad(out, n)


def task_rngs(seed: int, n_tasks: int) -> jax.Array:
    """(n_tasks, 2) raw keys, one per expert: expert i's run is the same alone or in a batch."""
    return jax.random.split(jax.random.PRNGKey(seed), n_tasks)


CSV_FIELDS = ("update", "env_steps", "target_m", *ppo.UpdateMetrics._fields)


def _checkpoint_manager(run_dir: Path, keep: int) -> ocp.CheckpointManager:
    # Orbax writes each step to a temporary folder and renames it when complete: a run killed
    # mid-save leaves the previous checkpoint as the latest.
    options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=True)
    return ocp.CheckpointManager((run_dir / "checkpoints").resolve(), options=options)


def _to_host(tree):
    return jax.tree_util.tree_map(np.asarray, tree)


def _trim_csv(path: Path, update: int) -> None:
    """Keep only rows up to `update`: rows of a chunk whose checkpoint never landed are redone."""
    if not path.exists():
        return
    with path.open() as f:
        rows = [r for r in csv.DictReader(f) if int(r["update"]) <= update]
    _write_csv(path, rows, "w")


def _write_csv(path: Path, rows, mode: str) -> None:
    new = mode == "w" or not path.exists()
    with path.open(mode, newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        if new:
            writer.writeheader()
        writer.writerows(rows)


def chunk_rows(state_before: ppo.TrainState, metrics: ppo.UpdateMetrics, tasks, steps_per_update: int) -> list:
    """CSV rows of one chunk: metrics (N tasks, n updates) -> N x n dicts."""
    m = _to_host(metrics)
    first = np.asarray(state_before.update)
    rows = []
    for i, target in enumerate(tasks):
        for j in range(m.episode_return.shape[1]):
            update = int(first[i]) + j + 1
            row = {"update": update, "env_steps": update * steps_per_update, "target_m": float(target)}
            row.update({k: float(getattr(m, k)[i, j]) for k in ppo.UpdateMetrics._fields})
            rows.append(row)
    return rows


def print_progress(tasks, metrics: ppo.UpdateMetrics, update: int, total: int, wall_s: float) -> None:
    """A rich table: every expert's last mean return, final error and valid fraction."""
    from rich.console import Console
    from rich.table import Table

    m = _to_host(metrics)
    table = Table(title=f"update {update}/{total}  ({wall_s:.0f} s)")
    for col in ("target (m)", "return", "final error (m)", "valid", "std (rad)"):
        table.add_column(col, justify="right")
    for i, target in enumerate(tasks):
        table.add_row(
            f"{target:.1f}",
            f"{m.episode_return[i, -1]:.2f}",
            f"{m.final_error[i, -1]:.2f}",
            f"{m.valid[i, -1]:.2f}",
            f"{m.policy_std[i, -1]:.4f}",
        )
    Console().print(table)


def train_experts(
    config, run_dir, verbose: bool = True, stop_after_chunks: int | None = None, programs: Compiled | None = None
) -> dict:
    """Train every task's expert (BC, then PPO) under `run_dir`; resumes from its last checkpoint.

    Writes run_dir/checkpoints/<update>/ (orbax), run_dir/progress.csv (one row per update and
    task) and, when done, run_dir/final_params/. `stop_after_chunks` stops early after that
    many chunks in this call (to test resuming). Returns {"state": TrainState (N, ...),
    "bc_losses": (N, steps) or None when resumed, "finished": bool, "wall_s": seconds of training
    over every call of the run}.
    """
    cfg = make_config(config)
    programs = programs or compile_programs(cfg)
    trainer = programs.trainer
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    tasks = tuple(float(t) for t in cfg.tasks)
    targets = jnp.asarray(tasks, jnp.float32)
    n_tasks = len(tasks)
    total = trainer.n_updates
    start = time.perf_counter()

    (run_dir / "config.json").write_text(cfg.to_json(indent=2) + "\n")
    manager = _checkpoint_manager(run_dir, cfg.keep_checkpoints)
    progress = run_dir / "progress.csv"
    no_kicks = jnp.zeros((n_tasks, prior.N_PARAMS))
    abstract = jax.eval_shape(functools.partial(run_init, programs), task_rngs(cfg.seed, n_tasks), targets, no_kicks)[0]
    bc_losses = None
    # Training seconds up to each checkpoint, carried across resumes: a resumed run reports
    # the time its checkpoints cost, not just its last call's (work redone after a kill is
    # counted once).
    clock_path = run_dir / "wall_time.json"
    clock = json.loads(clock_path.read_text()) if clock_path.exists() else {}
    previous = 0.0
    if manager.latest_step() is not None:
        previous = float(clock.get(str(manager.latest_step()), float("nan")))
        state = manager.restore(manager.latest_step(), args=ocp.args.StandardRestore(abstract))
        _trim_csv(progress, manager.latest_step())
        if verbose:
            print(f"resumed from update {manager.latest_step()} in {run_dir}")
    else:
        kicks, info = starting_kicks(cfg, verbose)
        results.write_json(run_dir / "starting_kicks.json", info)
        state, bc_losses = run_init(programs, task_rngs(cfg.seed, n_tasks), targets, kicks)
        manager.save(0, args=ocp.args.StandardSave(state))
        manager.wait_until_finished()
        clock = {"0": time.perf_counter() - start}
        results.write_json(clock_path, clock)
        progress.unlink(missing_ok=True)
        if verbose:
            print(f"behaviour cloning: final mse per task {np.asarray(bc_losses[:, -1]).round(6).tolist()} rad^2")

    chunks = 0
    while int(np.asarray(state.update)[0]) < total:
        if stop_after_chunks is not None and chunks >= stop_after_chunks:
            break
        before = state
        state, metrics = run_chunk(programs, state, targets)
        update = int(np.asarray(state.update)[0])
        # The CSV rows go first: if the run dies before the checkpoint lands, the resume trims
        # them and redoes the chunk, so the file never misses or repeats an update.
        _write_csv(progress, chunk_rows(before, metrics, tasks, trainer.steps_per_update), "a")
        manager.save(update, args=ocp.args.StandardSave(state))
        manager.wait_until_finished()
        clock[str(update)] = previous + time.perf_counter() - start
        results.write_json(clock_path, clock)
        chunks += 1
        if verbose:
            print_progress(tasks, metrics, update, total, time.perf_counter() - start)

    finished = int(np.asarray(state.update)[0]) >= total
    if finished:
        final = (run_dir / "final_params").resolve()
        # The checkpointer writes asynchronously: leaving its context waits for the write.
        with ocp.StandardCheckpointer() as checkpointer:
            checkpointer.save(final, expert_params(state), force=True)
    manager.close()
    # NaN when resumed from a checkpoint without a recorded time (a run older than this record).
    wall_s = previous + time.perf_counter() - start
    return {"state": state, "bc_losses": bc_losses, "finished": finished, "wall_s": wall_s}


def load_final_params(run_dir, programs: Compiled, n_tasks: int) -> ExpertParams:
    """The ExpertParams (N tasks, ...) that `train_experts` saved under run_dir/final_params."""
    args = (task_rngs(0, n_tasks), jnp.zeros(n_tasks), jnp.zeros((n_tasks, prior.N_PARAMS)))
    abstract = jax.eval_shape(functools.partial(run_init, programs), *args)[0]
    final = (Path(run_dir) / "final_params").resolve()
    return ocp.StandardCheckpointer().restore(final, expert_params(abstract))


def load_run_config(run_dir) -> ml_collections.ConfigDict:
    """The config an experts run saved (run_dir/config.json), laid over today's defaults.

    A run made before a config key existed lacks it; the key then takes its default, which is
    what such a run did (new keys default to the old behaviour, e.g. `ppo.anneal_learning_rate`).
    """
    cfg = default_config()
    cfg.update(json.loads((Path(run_dir) / "config.json").read_text()))
    return make_config(cfg)


def family(run_dir) -> synthetic_experts.ExpertFamily:
    """The trained experts of `run_dir` for meta-training: `--experts bumps_jax.experts:family
    --experts-path runs/experts/paper`."""

    cfg = load_run_config(run_dir)
    programs = compile_programs(cfg)
    params = load_final_params(run_dir, programs, len(cfg.tasks))
    return synthetic_experts.ExpertFamily(
        expert_policy(programs.trainer.networks), params, np.asarray(cfg.tasks, np.float64)
    )


def evaluate_run(config, run_dir, state: ppo.TrainState, programs: Compiled, wall_s: float) -> dict:
    """Score every expert on its own task (`eval.repetitions` noisy kicks each) and write
    run_dir/experts.json and run_dir/experts.md (the paper's Table 1, first row)."""
    cfg = make_config(config)
    start = time.perf_counter()
    apply = expert_policy(programs.trainer.networks)
    metrics = evaluate.evaluate_experts(
        programs.env, apply, expert_params(state), cfg.tasks, cfg.eval.repetitions, cfg.eval.seed
    )
    env_steps = int(np.asarray(state.env_steps)[0])
    record = evaluate.experts_record(cfg.tasks, metrics, env_steps)
    wall_s += time.perf_counter() - start
    record.update(results.provenance(cfg.preset, wall_s, physics_dt_s=programs.env.physics_dt))
    record["eval_repetitions"] = int(cfg.eval.repetitions)
    evaluate.write_experts_table(record, run_dir)
    return record
