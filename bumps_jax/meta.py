"""Meta-training: the contextual meta-policy by behaviour cloning of the experts (BUMPS, step 2).

1. Dataset: every expert (one per meta-training task) is rolled out K times (the paper: K = 1
   with the noise off); each step's (observation, action) is recorded with the observation's
   context set to the expert's own task. X (N, 2) = (phase, normalised target), Y (N, 22).
2. Meta-policy: an MLP (tanh hidden layers, linear output) maps X to the 22 joint targets.
   The paper's two nets: 4 x 256 and 11 x 128. Loss: mean absolute error; Adam at 3e-4,
   x 0.8 every 5000 epochs (staircase); batch 128; 150,000 epochs. An epoch is one pass over
   the shuffled dataset in batches of 128, the last one partial (the original trains with
   Keras `fit`): ceil(N / 128) gradient steps, 14 for the paper's 23 experts x 75 steps.
3. Training runs on the device: the data stays there, each chunk of gradient steps is one
   jitted lax.scan over epochs that shuffles with key fold_in(seed key, epoch) (a resumed run
   draws the same batches as an uninterrupted one); seeds are vmapped. The host
   syncs once per chunk: progress line, CSV row, orbax checkpoint.
4. Evaluation, unfiltered: every meta-policy on the 110 meta-test tasks x 100 noisy
   repetitions (context = target), one vmapped program; Table 1 rows 2-3 via
   `evaluate.table_row`.

Run layout (out_dir): config.json, dataset.npz, <net>/progress.csv, <net>/checkpoints/,
table1.json, table1.md.
"""

from __future__ import annotations

import csv
import functools
import importlib
import json
import time
from pathlib import Path
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
import orbax.checkpoint as ocp

from bumps_jax import evaluate, kick_env, results, synthetic_experts

NETS = ("meta_4x256", "meta_11x128")


# -- configuration ----------------------------------------------------------------------------


def default_config() -> ml_collections.ConfigDict:
    """The paper preset: every number of meta-training and its evaluation, in one place."""
    cfg = ml_collections.ConfigDict()
    cfg.preset = "paper"
    # name -> (hidden layers, width); the paper's two meta-policies.
    cfg.nets = ml_collections.ConfigDict({"meta_4x256": (4, 256), "meta_11x128": (11, 128)})
    cfg.dataset = ml_collections.ConfigDict()
    cfg.dataset.repetitions = 1  # K rollouts per expert; K = 1 runs noise-free (the paper)
    cfg.dataset.seed = 0
    cfg.train = ml_collections.ConfigDict()
    cfg.train.learning_rate = 3e-4
    cfg.train.decay_rate = 0.8
    cfg.train.decay_every = 5000  # epochs
    cfg.train.batch_size = 128
    cfg.train.epochs = 150_000  # passes over the dataset (see `steps_per_epoch`)
    cfg.train.chunk = 2500  # epochs per host sync (progress, CSV, checkpoint)
    cfg.train.n_seeds = 1  # vmapped ensemble of initialisations; row = seed 0, all seeds reported
    cfg.train.seed = 0
    cfg.eval = ml_collections.ConfigDict()
    cfg.eval.tasks = kick_env.meta_test_tasks()
    cfg.eval.repetitions = 100
    cfg.eval.seed = 1
    return cfg


def tiny_config() -> ml_collections.ConfigDict:
    """A CPU-sized run of the whole stage: a few thousand steps, 11 test tasks, 2 repetitions."""
    cfg = default_config()
    cfg.preset = "tiny"
    cfg.train.epochs = 2000  # 3 experts x 75 steps: 2 steps per epoch
    # 4000 steps at the paper's 3e-4 left the (4, 256) net at 0.026 rad MAE, and its kicks never
    # struck the ball (CPU demo: accuracy 0.00); at 3e-3 both nets kick (accuracy 1.00 / 0.95).
    cfg.train.learning_rate = 3e-3
    cfg.train.decay_every = 500
    cfg.train.chunk = 500
    cfg.eval.tasks = kick_env.meta_test_tasks()[9::10]
    cfg.eval.repetitions = 2
    return cfg


PRESETS = {"paper": default_config, "tiny": tiny_config}


def make_config(preset: str = "paper", overrides: dict | None = None) -> ml_collections.ConfigDict:
    """The locked preset with dotted overrides; ValueError naming an unknown preset or key."""
    cfg = kick_env.make_preset_config(PRESETS, preset, overrides)
    validate_config(cfg)
    return cfg


def validate_config(cfg: ml_collections.ConfigDict) -> None:
    """ValueError naming the first bad value; called before anything compiles."""
    t = cfg.train
    for key in ("batch_size", "epochs", "chunk", "n_seeds", "decay_every"):
        if not isinstance(t[key], int | np.integer) or t[key] < 1:
            raise ValueError(f"train.{key} must be a positive integer, got {t[key]!r}")
    if t.epochs % t.chunk:
        raise ValueError(f"train.epochs {t.epochs} must be a multiple of train.chunk {t.chunk}")
    if not t.learning_rate > 0:
        raise ValueError(f"train.learning_rate must be > 0, got {t.learning_rate!r}")
    if not 0 < t.decay_rate <= 1:
        raise ValueError(f"train.decay_rate must be in (0, 1], got {t.decay_rate!r}")
    if not isinstance(cfg.dataset.repetitions, int) or cfg.dataset.repetitions < 1:
        raise ValueError(f"dataset.repetitions must be a positive integer, got {cfg.dataset.repetitions!r}")
    if not isinstance(cfg.eval.repetitions, int) or cfg.eval.repetitions < 1:
        raise ValueError(f"eval.repetitions must be a positive integer, got {cfg.eval.repetitions!r}")
    if len(cfg.eval.tasks) == 0:
        raise ValueError("eval.tasks is empty: give at least one target distance")
    kick_env.check_targets(cfg.eval.tasks, kick_env.default_config().task_range)
    for name, arch in cfg.nets.items():
        if len(arch) != 2 or min(arch) < 1:
            raise ValueError(f"nets.{name} must be (hidden layers >= 1, width >= 1), got {tuple(arch)!r}")


# -- dataset ----------------------------------------------------------------------------------


class Dataset(NamedTuple):
    """Behaviour-cloning pairs, aggregated over experts, repetitions and steps (N = E * K * T)."""

    obs: np.ndarray  # (N, 2) phase, normalised context (= the expert's task)
    actions: np.ndarray  # (N, 22) the expert's joint targets (rad)
    task: np.ndarray  # (N,) the expert's task (m)


def dataset_env(repetitions: int, env_config=None) -> kick_env.KickEnv:
    """The env the experts are recorded in: noise-free for K = 1 (the paper), noisy for K > 1."""
    overrides = {}
    if repetitions == 1:
        overrides = {f"noise.{name}": 0.0 for name in kick_env.default_config().noise}
    return kick_env.KickEnv(env_config, overrides)


def collect_dataset(env: kick_env.KickEnv, experts, repetitions: int, seed: int = 0) -> tuple[Dataset, dict]:
    """Roll each expert out `repetitions` times on its own task; returns (Dataset, metrics (E, K)).

    experts: an `ExpertFamily`-like (apply_fn, params stacked over E, tasks (E,)).
    """
    tasks = kick_env.check_targets(experts.tasks, env.config.task_range).astype(np.float32)
    if repetitions < 1:
        raise ValueError(f"repetitions must be >= 1, got {repetitions!r}")
    n_experts = len(tasks)
    trajectory = evaluate.trajectory_fn(env, experts.apply_fn)
    over_reps = jax.vmap(trajectory, in_axes=(None, None, None, 0))
    rollout = jax.jit(jax.vmap(over_reps, in_axes=(0, 0, 0, 0)))
    keys = evaluate.repetition_keys(seed, n_experts, repetitions)
    obs, actions, metrics = rollout(experts.params, tasks, tasks, keys)  # (E, K, T, ...)
    n = obs.shape[0] * obs.shape[1] * obs.shape[2]
    task = np.broadcast_to(tasks[:, None, None], obs.shape[:3]).reshape(n)
    data = Dataset(
        obs=np.asarray(obs, np.float32).reshape(n, obs.shape[-1]),
        actions=np.asarray(actions, np.float32).reshape(n, actions.shape[-1]),
        task=np.asarray(task, np.float32),
    )
    return data, {k: np.asarray(v) for k, v in metrics.items()}


def save_dataset(path, data: Dataset) -> Path:
    """npz with obs, actions, task; written atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **data._asdict())
    tmp.replace(path)
    return path


def load_dataset(path) -> Dataset:
    with np.load(path) as f:
        return Dataset(**{name: f[name] for name in Dataset._fields})


# -- the meta-policy --------------------------------------------------------------------------


class MetaPolicy(nn.Module):
    """MLP: obs (..., 2) -> joint targets (..., 22); `depth` tanh layers of `width`, linear output."""

    depth: int
    width: int
    n_actions: int = 22

    @nn.compact
    def __call__(self, obs):
        x = obs
        for _ in range(self.depth):
            x = nn.tanh(nn.Dense(self.width)(x))
        return nn.Dense(self.n_actions)(x)


def policy_apply(model: MetaPolicy):
    """apply_fn(params, obs) -> action, the policy interface of `evaluate`."""

    def apply_fn(params, obs):
        return model.apply({"params": params}, obs)

    return apply_fn


def steps_per_epoch(train_cfg, n_rows: int) -> int:
    """Gradient steps in one pass over `n_rows` pairs in batches of train_cfg.batch_size."""
    return -(-int(n_rows) // int(train_cfg.batch_size))


def lr_schedule(train_cfg, epoch_steps: int = 1) -> optax.Schedule:
    """lr(step) = lr0 * decay ** floor(epoch / decay_every), epoch = step // epoch_steps: the
    paper's staircase decay, applied per epoch as its Keras scheduler did."""
    return optax.exponential_decay(
        init_value=train_cfg.learning_rate,
        transition_steps=train_cfg.decay_every * epoch_steps,
        decay_rate=train_cfg.decay_rate,
        staircase=True,
    )


def mae_loss(params, apply_fn, obs, actions, weights=None) -> jax.Array:
    """Mean absolute error over the joints and the batch's rows (those with weight 1)."""
    per_row = jnp.mean(jnp.abs(apply_fn(params, obs) - actions), axis=-1)
    if weights is None:
        return jnp.mean(per_row)
    return jnp.sum(per_row * weights) / jnp.sum(weights)


class TrainState(NamedTuple):
    """What a checkpoint holds. Leaves of params and opt_state carry the seed axis (S, ...)."""

    params: Any
    opt_state: Any
    step: jax.Array  # () int32: gradient steps done


class SeedCarry(NamedTuple):
    """The scan carry of one seed's training."""

    params: Any
    opt_state: Any


def _epoch(apply_fn, optimizer, batch_size, epoch_steps, obs, actions, seed_key, carry: SeedCarry, epoch):
    """One pass over the dataset, shuffled with key fold_in(seed_key, epoch): (carry, losses)."""
    n = obs.shape[0]
    order = jax.random.permutation(jax.random.fold_in(seed_key, epoch), n)
    # Static shapes: every batch takes batch_size slots; the last, partial one masks the
    # slots past the end, so its loss is the mean over its own rows (as Keras computes it).
    order = jnp.concatenate([order, jnp.zeros(epoch_steps * batch_size - n, order.dtype)])
    slots = jnp.arange(epoch_steps * batch_size).reshape(epoch_steps, batch_size)

    def step(carry: SeedCarry, batch):
        idx, slot = batch
        weights = (slot < n).astype(obs.dtype)
        loss, grads = jax.value_and_grad(mae_loss)(carry.params, apply_fn, obs[idx], actions[idx], weights)
        updates, opt_state = optimizer.update(grads, carry.opt_state, carry.params)
        return SeedCarry(optax.apply_updates(carry.params, updates), opt_state), loss

    return jax.lax.scan(step, carry, (order.reshape(epoch_steps, batch_size), slots))


def make_trainer(model: MetaPolicy, train_cfg, n_rows: int):
    """(init, chunk) for a dataset of `n_rows` pairs: init(seed_keys (S,)) -> TrainState;
    chunk(state, obs, actions, seed_keys) -> (state after train_cfg.chunk more epochs,
    losses (S, chunk epochs x steps per epoch)). Both jitted."""
    epoch_steps = steps_per_epoch(train_cfg, n_rows)
    # Adam over one flat vector: the same update, elementwise, in fewer kernels per step. The
    # BC loop is launch-bound (tiny nets, batch 128): on an H100 this is 1.12x steps/s for the
    # (11, 128) net; unrolling the epoch or CUDA-graph loops gained nothing.
    optimizer = optax.flatten(optax.adam(lr_schedule(train_cfg, epoch_steps)))
    apply_fn = policy_apply(model)
    chunk_epochs = int(train_cfg.chunk)

    def init_one(key):
        params = model.init(key, jnp.zeros((1, 2)))["params"]
        return params, optimizer.init(params)

    @jax.jit
    def init(seed_keys):
        params, opt_state = jax.vmap(init_one)(seed_keys)
        return TrainState(params, opt_state, jnp.zeros((), jnp.int32))

    def chunk_one(params, opt_state, seed_key, obs, actions, epochs):
        body = functools.partial(_epoch, apply_fn, optimizer, train_cfg.batch_size, epoch_steps, obs, actions, seed_key)
        carry, losses = jax.lax.scan(body, SeedCarry(params, opt_state), epochs)
        return carry.params, carry.opt_state, losses.reshape(-1)

    @jax.jit
    def chunk(state: TrainState, obs, actions, seed_keys):
        if obs.shape[0] != n_rows:
            raise ValueError(f"the trainer was built for {n_rows} pairs, got {obs.shape[0]}")
        epochs = state.step // epoch_steps + jnp.arange(chunk_epochs, dtype=jnp.int32)
        params, opt_state, losses = jax.vmap(chunk_one, in_axes=(0, 0, 0, None, None, None))(
            state.params, state.opt_state, seed_keys, obs, actions, epochs
        )
        return TrainState(params, opt_state, state.step + chunk_epochs * epoch_steps), losses

    return init, chunk


def seed_keys(train_cfg) -> jax.Array:
    return jax.random.split(jax.random.key(train_cfg.seed), train_cfg.n_seeds)


def train(
    model: MetaPolicy,
    data: Dataset,
    train_cfg,
    out_dir,
    verbose: bool = True,
    max_chunks: int | None = None,
    trainer=None,
) -> TrainState:
    """Train (or resume training) one architecture; returns the final TrainState (its `step`
    counts gradient steps: train_cfg.epochs x `steps_per_epoch`).

    Writes out_dir/progress.csv and orbax checkpoints in out_dir/checkpoints after every chunk.
    A rerun resumes from the latest checkpoint and ends where an uninterrupted run would.
    max_chunks: stop after this many chunks in this call (for tests of the resume path).
    """
    out_dir = Path(out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    init, chunk = trainer or make_trainer(model, train_cfg, len(data.obs))
    epoch_steps = steps_per_epoch(train_cfg, len(data.obs))
    total_steps = train_cfg.epochs * epoch_steps
    keys = seed_keys(train_cfg)
    state = init(keys)
    options = ocp.CheckpointManagerOptions(max_to_keep=2, enable_async_checkpointing=False)
    csv_path = out_dir / "progress.csv"
    fields = ["epoch", "step", "lr", "loss_mean", "loss_last", "loss_best_seed", "seconds"]
    with ocp.CheckpointManager(out_dir / "checkpoints", options=options) as manager:
        latest = manager.latest_step()
        if latest is not None:
            state = manager.restore(latest, args=ocp.args.StandardRestore(state))
        _truncate_csv(csv_path, fields, int(state.step))
        obs, actions = jnp.asarray(data.obs), jnp.asarray(data.actions)  # resident on the device
        schedule = lr_schedule(train_cfg, epoch_steps)
        done_chunks = 0
        while int(state.step) < total_steps and (max_chunks is None or done_chunks < max_chunks):
            t0 = time.perf_counter()
            state, losses = chunk(state, obs, actions, keys)
            losses = np.asarray(losses)  # the host sync of this chunk
            step = int(state.step)
            row = [
                step // epoch_steps,
                step,
                float(schedule(step - 1)),
                float(losses.mean()),
                float(losses[:, -1].mean()),
                float(losses.mean(axis=1).min()),
                round(time.perf_counter() - t0, 3),
            ]
            with open(csv_path, "a", newline="") as f:
                csv.writer(f).writerow(row)
            manager.save(step, args=ocp.args.StandardSave(state))
            done_chunks += 1
            if verbose:
                print(
                    f"  epoch {row[0]:7d}/{train_cfg.epochs}  lr {row[2]:.2e}  loss {row[3]:.4f}"
                    f"  (last {row[4]:.4f})  {row[6]:.1f} s",
                    flush=True,
                )
        manager.wait_until_finished()
    return state


def _truncate_csv(path: Path, fields, step: int) -> None:
    """Keep the header and the rows up to `step`: a resumed run appends after what it restored."""
    rows = []
    if path.exists():
        with open(path, newline="") as f:
            rows = [r for r in csv.reader(f)][1:]
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(fields)
        w.writerows(r for r in rows if r and int(r[1]) <= step)


def load_policy(net_dir, depth: int, width: int, train_cfg) -> tuple[Any, Any]:
    """(apply_fn, params stacked over seeds) from the latest checkpoint in net_dir/checkpoints."""
    model = MetaPolicy(depth, width)
    init, _ = make_trainer(model, train_cfg, n_rows=1)  # the state's shapes do not depend on the data
    # Only the params: a policy does not need the optimiser's state, whose layout may differ
    # between versions of the trainer. (Real arrays, not `jax.eval_shape`: orbax restores a leaf
    # without a sharding as a NumPy array, and initialising these small nets takes milliseconds.)
    target = {"params": init(seed_keys(train_cfg)).params}
    restore_args = ocp.checkpoint_utils.construct_restore_args(target)
    path = Path(net_dir).resolve() / "checkpoints"
    with ocp.CheckpointManager(path, options=ocp.CheckpointManagerOptions(read_only=True)) as manager:
        latest = manager.latest_step()
        if latest is None:
            raise ValueError(f"no checkpoint in {path}")
        args = ocp.args.PyTreeRestore(item=target, restore_args=restore_args, partial_restore=True)
        restored = manager.restore(latest, args=args)
    return policy_apply(model), restored["params"]


# -- evaluation (Table 1) ---------------------------------------------------------------------


def evaluate_unfiltered(env, apply_fn, params, tasks, repetitions: int, seed: int, grid=None) -> dict:
    """Metrics (P, n_tasks, R) of each stacked policy on each task with context = target."""
    tasks = kick_env.check_targets(tasks, env.config.task_range).astype(np.float32)
    grid = grid or evaluate.grid_fn(env, apply_fn)
    keys = evaluate.repetition_keys(seed, len(tasks), repetitions)
    out = grid(params, tasks, tasks, keys)
    return {k: np.asarray(v) for k, v in out.items()}


def experts_row_from_json(path) -> tuple[dict, dict | None]:
    """The experts' Table 1 row from their evaluation JSON (`evaluate.experts_record`: the row
    at the top level; or `rows.experts`), and their per-task errors if it lists them."""
    payload = json.loads(Path(path).read_text())
    for candidate in (payload.get("rows", {}).get("experts"), payload):
        if isinstance(candidate, dict) and "accuracy_mean" in candidate:
            keys = (*TABLE1_COLUMNS, "tasks_above_threshold", "n_tasks")
            row = {k: candidate[k] for k in keys if k in candidate}
            per_task = None
            if isinstance(payload.get("per_task"), list):
                per_task = {
                    "tasks": [r["target_m"] for r in payload["per_task"]],
                    "error_mean_m": [r["error_mean_m"] for r in payload["per_task"]],
                }
            return {**row, "source": str(path)}, per_task
    raise ValueError(f"{path}: no experts row (need accuracy_mean at the top level or rows.experts)")


TABLE1_COLUMNS = ("accuracy_mean", "accuracy_std", "error_mean_m", "error_std_m", "error_mean_all_m")


def table1_markdown(rows: dict) -> str:
    head = "| policy | accuracy | error (acc > 0.7) m | error (all tasks) m | tasks > 0.7 |\n|---|---|---|---|---|\n"
    lines = []
    for name, r in rows.items():
        lines.append(
            f"| {name} | {r['accuracy_mean']:.2f} +- {r['accuracy_std']:.2f} | "
            f"{r['error_mean_m']:.2f} +- {r['error_std_m']:.2f} | {r['error_mean_all_m']:.2f} | "
            f"{r.get('tasks_above_threshold', '-')}/{r.get('n_tasks', '-')} |"
        )
    return "# Table 1: experts and unfiltered meta-policies\n\n" + head + "\n".join(lines) + "\n"


# -- the stage --------------------------------------------------------------------------------


def load_experts(spec: str, path: str | None, tasks=None):
    """`synthetic` (prior-based stand-ins) or `module:function`, called with `path`, returning an
    ExpertFamily-like (apply_fn, params stacked over experts, tasks)."""
    if spec == "synthetic":
        return synthetic_experts.synthetic_experts(kick_env.meta_train_tasks() if tasks is None else tasks)
    module, _, fn = spec.partition(":")
    if not fn:
        raise ValueError(f"experts spec {spec!r} must be 'synthetic' or 'module:function'")
    return getattr(importlib.import_module(module), fn)(path)


def run(cfg, out_dir, experts, experts_json=None, verbose: bool = True) -> dict:
    """The whole stage: dataset, both nets trained (resumable), Table 1. Returns the payload."""
    t_start = time.perf_counter()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    _check_same_config(out_dir / "config.json", cfg)
    say = print if verbose else (lambda *a, **k: None)

    ds_path = out_dir / "dataset.npz"
    if ds_path.exists():
        data = load_dataset(ds_path)
        say(f"dataset: {ds_path} ({len(data.obs)} pairs, reused)")
    else:
        t0 = time.perf_counter()
        env = dataset_env(cfg.dataset.repetitions)
        data, rec = collect_dataset(env, experts, cfg.dataset.repetitions, cfg.dataset.seed)
        save_dataset(ds_path, data)
        say(
            f"dataset: {len(data.obs)} pairs from {len(experts.tasks)} experts x {cfg.dataset.repetitions}"
            f" in {time.perf_counter() - t0:.1f} s; expert error in the recording env"
            f" {rec['final_error'].mean():.2f} m"
        )

    env = kick_env.KickEnv()
    rows, per_task = {}, {"tasks": [float(t) for t in cfg.eval.tasks]}
    if experts_json:
        rows["experts"], experts_per_task = experts_row_from_json(experts_json)
        if experts_per_task:
            per_task["experts"] = experts_per_task
    else:
        t0 = time.perf_counter()
        m = evaluate.evaluate_experts(
            env, experts.apply_fn, experts.params, experts.tasks, cfg.eval.repetitions, cfg.eval.seed
        )
        rows["experts"] = {**evaluate.table_row(evaluate.summarise_tasks(m)), "source": "evaluated here"}
        per_task["experts"] = {
            "tasks": [float(t) for t in experts.tasks],
            "error_mean_m": evaluate.summarise_tasks(m)["error_mean_m"].tolist(),
        }
        say(f"experts: evaluated on their own tasks in {time.perf_counter() - t0:.1f} s")

    seeds_rows, timings = {}, {}
    # The paper's order first (ConfigDict sorts its keys), then any extra nets.
    names = [n for n in NETS if n in cfg.nets] + sorted(n for n in cfg.nets if n not in NETS)
    for name in names:
        depth, width = cfg.nets[name]
        say(f"{name}: {depth} x {width}, {cfg.train.epochs} epochs, {cfg.train.n_seeds} seed(s)")
        t0 = time.perf_counter()
        state = train(MetaPolicy(depth, width), data, cfg.train, out_dir / name, verbose=verbose)
        # Includes compiling and checkpoints; a resumed run times only what it trained.
        timings[name] = {"train_wall_s": time.perf_counter() - t0}
        t0 = time.perf_counter()
        m = evaluate_unfiltered(
            env,
            policy_apply(MetaPolicy(depth, width)),
            state.params,
            cfg.eval.tasks,
            cfg.eval.repetitions,
            cfg.eval.seed,
        )
        summaries = [evaluate.summarise_tasks({k: v[s] for k, v in m.items()}) for s in range(cfg.train.n_seeds)]
        rows[name] = evaluate.table_row(summaries[0])
        seeds_rows[name] = [evaluate.table_row(s) for s in summaries]
        per_task[name] = {
            "error_mean_m": summaries[0]["error_mean_m"].tolist(),
            "accuracy": summaries[0]["accuracy"].tolist(),
        }
        timings[name]["eval_wall_s"] = time.perf_counter() - t0
        r = rows[name]
        kept = "no task" if np.isnan(r["error_mean_m"]) else f"{r['error_mean_m']:.2f} m"
        say(
            f"{name}: evaluated in {timings[name]['eval_wall_s']:.1f} s: accuracy {r['accuracy_mean']:.2f},"
            f" error {kept} over tasks with accuracy > 0.7, {r['error_mean_all_m']:.2f} m over all"
        )

    payload = {
        "rows": rows,
        "rows_per_seed": seeds_rows,
        "per_task": per_task,
        "eval": {"repetitions": cfg.eval.repetitions, "n_tasks": len(cfg.eval.tasks), "seed": cfg.eval.seed},
        "dataset_pairs": len(data.obs),
        "timings": timings,
        **results.provenance(cfg.preset, time.perf_counter() - t_start, physics_dt_s=env.physics_dt),
    }
    results.write_json(out_dir / "table1.json", json_safe(payload))
    (out_dir / "table1.md").write_text(table1_markdown(rows))
    return payload


def json_safe(obj):
    """NaN / inf -> None, recursively: strict JSON (a row with no task above 0.7 has no error)."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def _check_same_config(path: Path, cfg) -> None:
    """A run folder belongs to one config: resuming with another one would mix two runs."""
    text = cfg.to_json(indent=2, sort_keys=True)
    if path.exists() and json.loads(path.read_text()) != json.loads(text):
        raise ValueError(f"{path} holds a different config; use a new --out or the same preset/overrides")
    path.write_text(text + "\n")
