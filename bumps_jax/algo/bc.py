"""Behaviour cloning: the contextual meta-policy fitted to the experts' pairs, and a policy's
mean fitted to given actions (an expert's start).

The meta-policy (BUMPS step 2): an MLP (tanh hidden layers, linear output) maps the contextual
observation to the action: for the kick (phase, normalised context) to the 22 joint targets, for
a closed-loop task (the cheetah) the state and the normalised context to the motor commands.
Loss: mean absolute error; Adam with a staircase decay per epoch; an epoch is one pass over the
shuffled pairs in batches, the last one partial (as the original's Keras `fit`): ceil(N / batch)
gradient steps. The pairs stay on the device; each chunk of epochs is one jitted lax.scan that shuffles epoch e with key
fold_in(seed key, e), so a resumed run draws the same batches as an uninterrupted one; seeds
are vmapped. The host syncs once per chunk: progress line, CSV row, orbax checkpoint.

An expert's start (`clone_policy`): full-batch Adam fits a Gaussian policy's mean to (T, A)
actions, e.g. a task's scripted motion.
"""

from __future__ import annotations

import contextlib
import functools
import time
from pathlib import Path
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

from bumps_jax.algo import ppo
from bumps_jax.pipeline import runio

CSV_FIELDS = ("epoch", "step", "lr", "loss_mean", "loss_last", "loss_best_seed", "seconds")
KEEP_CHECKPOINTS = 2


# -- the meta-policy ----------------------------------------------------------------------------


class Dataset(NamedTuple):
    """Behaviour-cloning pairs over experts, repetitions and steps (N = E * K * T)."""

    obs: np.ndarray  # (N, O) the contextual observation (kick: phase, normalised context of the expert's task)
    actions: np.ndarray  # (N, A) the expert's actions (kick: joint targets, rad)
    task: np.ndarray  # (N,) the expert's task (m; the cheetah's: m/s)


class MetaPolicy(nn.Module):
    """MLP: obs (..., O) -> actions (..., n_actions) (kick: (2,) -> 22 joint targets); `depth` tanh
    layers of `width`, linear output. With `obs_norm` ((O,) shift, (O,) scale, fixed numbers
    from the dataset: `obs_norm_of`), the net sees (obs - shift) / scale: a closed-loop task's
    states are not in [0, 1] as the kick's (phase, context) are; the kick's under `meta.inputs =
    "raw"`: `kick_raw_inputs`; "centred": `kick_centred_inputs`. None: obs as it is (the kick's by
    default)."""

    depth: int
    width: int
    n_actions: int = 22
    obs_norm: tuple | None = None

    @nn.compact
    def __call__(self, obs):
        x = obs
        if self.obs_norm is not None:
            shift, scale = (jnp.asarray(v, obs.dtype) for v in self.obs_norm)
            x = (x - shift) / scale
        for _ in range(self.depth):
            x = nn.tanh(nn.Dense(self.width)(x))
        return nn.Dense(self.n_actions)(x)


def kick_raw_inputs(n_steps: int, task_range, obs_size: int = 2) -> tuple:
    """`MetaPolicy.obs_norm` under which a kick net reads the paper's unscaled inputs (time step,
    target m) from the env's (phase = step / n_steps, (target - lo) / (hi - lo)): (obs - shift) /
    scale with shift (0, -lo / (hi - lo)) and scale (1 / n_steps, 1 / (hi - lo)); any further
    observations (proprioception) as they are."""
    lo, hi = (float(v) for v in task_range)
    shift = (0.0, -lo / (hi - lo)) + (0.0,) * (obs_size - 2)
    scale = (1.0 / n_steps, 1.0 / (hi - lo)) + (1.0,) * (obs_size - 2)
    return shift, scale


def kick_centred_inputs(obs_size: int = 2) -> tuple:
    """`MetaPolicy.obs_norm` under which a kick net reads (phase, normalised context) moved from
    [0, 1] to [-1, 1] (zero-centred, as tanh layers train best on); further observations as they are."""
    return (0.5, 0.5) + (0.0,) * (obs_size - 2), (0.5, 0.5) + (1.0,) * (obs_size - 2)


def obs_norm_of_record(record: dict) -> tuple | None:
    """A `MetaPolicy.obs_norm` from a record's `obs_norm_fields`: the stage's table1.json or a
    shipped net's entry in policies.json (None: the kick's inputs as they are)."""
    if "obs_shift" not in record:
        return None
    return tuple(map(float, record["obs_shift"])), tuple(map(float, record["obs_scale"]))


def obs_norm_fields(obs_norm: tuple | None) -> dict:
    """The record keys of a `MetaPolicy.obs_norm` (none for None), as `obs_norm_of_record` reads them."""
    return {} if obs_norm is None else {"obs_shift": list(obs_norm[0]), "obs_scale": list(obs_norm[1])}


def obs_norm_of(obs: np.ndarray, floor: float = 1e-2) -> tuple:
    """(shift, scale) of a dataset's observations (N, O) as `MetaPolicy.obs_norm` takes them:
    per-number mean and standard deviation (at least `floor`), as tuples of floats."""
    obs = np.asarray(obs, np.float64)
    return tuple(map(float, obs.mean(axis=0))), tuple(map(float, np.maximum(obs.std(axis=0), floor)))


def policy_apply(model: MetaPolicy):
    """apply_fn(params, obs (..., 2)) -> actions (..., 22): the policy interface of `rollout`."""

    def apply_fn(params, obs):
        return model.apply({"params": params}, obs)

    return apply_fn


def steps_per_epoch(train_cfg, n_rows: int) -> int:
    """Gradient steps in one pass over `n_rows` pairs in batches of train_cfg.batch_size."""
    return -(-int(n_rows) // int(train_cfg.batch_size))


def steps_unrolled(train_cfg, epoch_steps: int) -> int:
    """Gradient steps per iteration of an epoch's compiled loop: train_cfg.unroll, at most the epoch's."""
    return min(int(train_cfg.unroll), epoch_steps)


def lr_schedule(train_cfg, epoch_steps: int = 1) -> optax.Schedule:
    """lr(step) = lr0 * decay ** floor(epoch / decay_every), epoch = step // epoch_steps: the
    paper's staircase decay, applied per epoch as its Keras scheduler did."""
    return optax.exponential_decay(
        init_value=train_cfg.learning_rate,
        transition_steps=train_cfg.decay_every * epoch_steps,
        decay_rate=train_cfg.decay_rate,
        staircase=True,
    )


def mae(out, actions, weights=None) -> jax.Array:
    """Mean absolute error () of outputs against actions (B, A), over the joints and the rows;
    with weights (B,), the mean over the rows of weight 1."""
    per_row = jnp.mean(jnp.abs(out - actions), axis=-1)
    if weights is None:
        return jnp.mean(per_row)
    return jnp.sum(per_row * weights) / jnp.sum(weights)


def mae_loss(params, apply_fn, obs, actions, weights=None) -> jax.Array:
    """`mae` of the policy's actions on obs (B, O)."""
    return mae(apply_fn(params, obs), actions, weights)


def epoch_batches(seed_key, epoch, n: int, epoch_steps: int, batch_size: int) -> tuple[jax.Array, jax.Array]:
    """One epoch's batches: (row indices, slots), each (epoch_steps, batch_size), the rows shuffled
    with key fold_in(seed_key, epoch). Static shapes: every batch takes batch_size slots; the last,
    partial one's slots past the end (slot >= n) point at row 0 and carry weight 0, so its loss is
    the mean over its own rows (as Keras computes it)."""
    order = jax.random.permutation(jax.random.fold_in(seed_key, epoch), n)
    order = jnp.concatenate([order, jnp.zeros(epoch_steps * batch_size - n, order.dtype)])
    slots = jnp.arange(epoch_steps * batch_size).reshape(epoch_steps, batch_size)
    return order.reshape(epoch_steps, batch_size), slots


class TrainState(NamedTuple):
    """What a checkpoint holds. Leaves of params and opt_state carry the seed axis (S, ...)."""

    params: Any
    opt_state: Any
    step: jax.Array  # () int32: gradient steps done


class SeedCarry(NamedTuple):
    """The scan carry of one seed's training."""

    params: Any
    opt_state: Any


def _epoch(apply_fns, optimizers, batch_size, epoch_steps, unroll, obs, actions, seed_key, carry: dict, epoch):
    """One pass over the dataset, shuffled with key fold_in(seed_key, epoch), of every net of the
    dicts (name -> apply_fn / optimizer / SeedCarry) on the same batches: (carry, losses {name: (epoch_steps,)})."""
    n = obs.shape[0]

    def step(carry: dict, batch):
        idx, slot = batch
        weights = (slot < n).astype(obs.dtype)
        new, losses = {}, {}
        for name, c in carry.items():
            loss, grads = jax.value_and_grad(mae_loss)(c.params, apply_fns[name], obs[idx], actions[idx], weights)
            updates, opt_state = optimizers[name].update(grads, c.opt_state, c.params)
            new[name], losses[name] = SeedCarry(optax.apply_updates(c.params, updates), opt_state), loss
        return new, losses

    return jax.lax.scan(step, carry, epoch_batches(seed_key, epoch, n, epoch_steps, batch_size), unroll=unroll)


def make_joint_trainer(models: dict, train_cfg, n_rows: int, obs_size: int = 2):
    """(init, chunk) training every net of `models` (name -> MetaPolicy, observations of `obs_size`)
    in one compiled loop, each on the same batches as it would see alone (the shuffles depend on
    the seed only), so each ends exactly where its own trainer would: init(seed_keys (S,)) ->
    {name: TrainState}; chunk(states, obs (N, O), actions (N, A), seed_keys (S,)) -> (states after train_cfg.chunk
    more epochs, {name: losses (S, chunk epochs x steps per epoch)}). Both jitted.

    One loop for several nets: the loop is launch-bound (tiny nets, batches of 128), and the
    device can overlap the independent nets' kernels of one step."""
    epoch_steps = steps_per_epoch(train_cfg, n_rows)
    # Adam over one flat vector: the same update, elementwise, in fewer kernels per step.
    optimizers = {name: optax.flatten(optax.adam(lr_schedule(train_cfg, epoch_steps))) for name in models}
    apply_fns = {name: policy_apply(model) for name, model in models.items()}
    chunk_epochs = int(train_cfg.chunk)
    unroll = steps_unrolled(train_cfg, epoch_steps)

    def init_one(key):
        out = {}
        for name, model in models.items():
            params = model.init(key, jnp.zeros((1, obs_size)))["params"]
            out[name] = SeedCarry(params, optimizers[name].init(params))
        return out

    @jax.jit
    def init(seed_keys):
        carries = jax.vmap(init_one)(seed_keys)
        return {name: TrainState(c.params, c.opt_state, jnp.zeros((), jnp.int32)) for name, c in carries.items()}

    def chunk_one(carry, seed_key, obs, actions, epochs):
        body = functools.partial(
            _epoch, apply_fns, optimizers, train_cfg.batch_size, epoch_steps, unroll, obs, actions, seed_key
        )
        carry, losses = jax.lax.scan(body, carry, epochs)
        return carry, {name: v.reshape(-1) for name, v in losses.items()}

    @jax.jit
    def chunk(states: dict, obs, actions, seed_keys):
        if obs.shape[0] != n_rows:
            raise ValueError(f"the trainer was built for {n_rows} pairs, got {obs.shape[0]}")
        step = next(iter(states.values())).step
        epochs = step // epoch_steps + jnp.arange(chunk_epochs, dtype=jnp.int32)
        carry = {name: SeedCarry(s.params, s.opt_state) for name, s in states.items()}
        carry, losses = jax.vmap(chunk_one, in_axes=(0, 0, None, None, None))(carry, seed_keys, obs, actions, epochs)
        done = step + chunk_epochs * epoch_steps
        return {name: TrainState(c.params, c.opt_state, done) for name, c in carry.items()}, losses

    return init, chunk


def make_trainer(model: MetaPolicy, train_cfg, n_rows: int, obs_size: int = 2):
    """(init, chunk) for one net (`make_joint_trainer` of one): init(seed_keys (S,)) -> TrainState;
    chunk(state, obs (N, O), actions (N, A), seed_keys (S,)) -> (state after train_cfg.chunk
    more epochs, losses (S, chunk epochs x steps per epoch)). Both jitted."""
    init_all, chunk_all = make_joint_trainer({"net": model}, train_cfg, n_rows, obs_size)

    @jax.jit
    def init(seed_keys):
        return init_all(seed_keys)["net"]

    @jax.jit
    def chunk(state: TrainState, obs, actions, seed_keys):
        states, losses = chunk_all({"net": state}, obs, actions, seed_keys)
        return states["net"], losses["net"]

    return init, chunk


def seed_keys(train_cfg) -> jax.Array:
    """(n_seeds,) keys, one per initialisation trained side by side."""
    return jax.random.split(jax.random.key(train_cfg.seed), train_cfg.n_seeds)


def _progress_row(state: TrainState, losses: np.ndarray, epoch_steps: int, schedule, seconds: float) -> dict:
    """The CSV row of one chunk from its losses (S, steps)."""
    step = int(state.step)
    return {
        "epoch": step // epoch_steps,
        "step": step,
        "lr": float(schedule(step - 1)),
        "loss_mean": float(losses.mean()),
        "loss_last": float(losses[:, -1].mean()),
        "loss_best_seed": float(losses.mean(axis=1).min()),
        "seconds": round(seconds, 3),
    }


def train(model: MetaPolicy, data: Dataset, train_cfg, out_dir, say=print, max_chunks=None, trainer=None) -> TrainState:
    """Train (or resume) one architecture on data (N pairs): `train_nets` of one net, in out_dir.
    trainer: `make_joint_trainer({"net": model}, ...)`'s (init, chunk), to reuse its compiled programs."""
    return train_nets({"net": model}, data, train_cfg, {"net": out_dir}, say, max_chunks, trainer)["net"]


def train_nets(models: dict, data: Dataset, train_cfg, out_dirs: dict, say=print, max_chunks=None,
               trainer=None) -> dict:  # fmt: skip
    """Train (or resume) every net of `models` (name -> MetaPolicy) on data (N pairs) in one loop;
    returns {name: final TrainState}, whose `step` counts gradient steps (train_cfg.epochs x
    `steps_per_epoch`).

    trainer: (init, chunk) over dicts of nets (`make_joint_trainer`'s, the default, or
    `bc_stacked.make_stacked_trainer`'s). After every chunk each net writes
    out_dirs[name]/progress.csv and an orbax checkpoint in out_dirs[name]/checkpoints: one net's
    files are those of a net trained alone. A rerun resumes from the newest step every net holds
    readably and ends where an uninterrupted run would.
    max_chunks: stop after this many chunks in this call (tests of the resume path).
    """
    import orbax.checkpoint as ocp  # noqa: PLC0415

    names = list(models)
    out_dirs = {name: Path(out_dirs[name]).resolve() for name in names}
    for d in out_dirs.values():
        d.mkdir(parents=True, exist_ok=True)
    init, chunk = trainer or make_joint_trainer(models, train_cfg, len(data.obs), data.obs.shape[-1])
    epoch_steps = steps_per_epoch(train_cfg, len(data.obs))
    total_steps = train_cfg.epochs * epoch_steps
    keys = seed_keys(train_cfg)
    schedule = lr_schedule(train_cfg, epoch_steps)
    with contextlib.ExitStack() as managers_open:
        managers = {
            name: managers_open.enter_context(
                runio.checkpoint_manager(out_dirs[name] / "checkpoints", KEEP_CHECKPOINTS)
            )
            for name in names
        }
        fresh = init(keys)
        restore = {name: ocp.args.StandardRestore(fresh[name]) for name in names}
        step, states = runio.restore_latest_common(managers, restore, say)
        if step is None:
            states = fresh
        else:
            where = ", ".join(runio.shown(d) for d in out_dirs.values())
            say(f"  resumed from epoch {int(states[names[0]].step) // epoch_steps} in {where}")
        done = int(states[names[0]].step)
        for name in names:
            runio.trim_csv(out_dirs[name] / "progress.csv", CSV_FIELDS, "step", done)
        obs, actions = jnp.asarray(data.obs), jnp.asarray(data.actions)  # resident on the device
        done_chunks, pace = 0, runio.Clock(total_steps)
        with runio.stop_on_interrupt(say) as stop:
            while done < total_steps and (max_chunks is None or done_chunks < max_chunks):
                t0 = time.perf_counter()
                states, losses = chunk(states, obs, actions, keys)
                losses = {n: np.asarray(losses[n]) for n in names}  # waits for the chunk to finish
                seconds = time.perf_counter() - t0
                rows = {n: _progress_row(states[n], losses[n], epoch_steps, schedule, seconds) for n in names}
                for name in names:
                    runio.append_csv(out_dirs[name] / "progress.csv", CSV_FIELDS, [rows[name]])
                    managers[name].save(rows[name]["step"], args=ocp.args.StandardSave(states[name]))
                for manager in managers.values():
                    manager.wait_until_finished()
                done, done_chunks = rows[names[0]]["step"], done_chunks + 1
                eta = pace.tick(done)
                row = rows[names[0]]
                if len(names) == 1:
                    loss = f"loss {row['loss_mean']:.4f}  (last {row['loss_last']:.4f})"
                else:
                    loss = "loss " + ", ".join(f"{n} {rows[n]['loss_mean']:.4f}" for n in names)
                say(f"  epoch {row['epoch']:7d}/{train_cfg.epochs}  lr {row['lr']:.2e}  {loss}  {eta}")
                stop.check()
    return states


def load_policy(
    net_dir, depth: int, width: int, train_cfg, obs_size: int = 2, n_actions: int = 22, obs_norm=None
) -> tuple[Any, Any]:
    """(apply_fn, params stacked over seeds (S, ...)) from the newest checkpoint in net_dir/checkpoints,
    of a net from observations of `obs_size` (normalised by `obs_norm`) to `n_actions` (the kick's
    by default).

    ValueError naming the folder if it holds no checkpoint, or if its newest one is unreadable
    (an older one would be a policy trained less than the run says).
    """
    import orbax.checkpoint as ocp  # noqa: PLC0415

    path = Path(net_dir).resolve() / "checkpoints"
    if not path.is_dir():
        raise ValueError(f"{path}: no checkpoint folder (run meta-train first)")
    model = MetaPolicy(depth, width, n_actions, obs_norm)
    init, _ = make_trainer(model, train_cfg, 1, obs_size)  # the state's shapes do not depend on the data
    # Only the params: a policy does not need the optimiser's state, whose layout may differ
    # between versions of the trainer. (Real arrays, not `jax.eval_shape`: orbax restores a leaf
    # without a sharding as a NumPy array, and initialising these small nets takes milliseconds.)
    target = {"params": init(seed_keys(train_cfg)).params}
    restore_args = ocp.checkpoint_utils.construct_restore_args(target)
    args = ocp.args.PyTreeRestore(item=target, restore_args=restore_args, partial_restore=True)
    with runio.checkpoint_manager(path, KEEP_CHECKPOINTS, read_only=True) as manager:
        latest = manager.latest_step()
        if latest is None:
            raise ValueError(f"{path}: no checkpoint (run meta-train first)")
        try:
            restored = manager.restore(latest, args=args)
        except Exception as err:  # noqa: BLE001 (orbax and tensorstore raise many kinds)
            reason = str(err).strip().splitlines()[0][:160] if str(err).strip() else type(err).__name__
            raise ValueError(f"{path / str(latest)}: unreadable checkpoint ({reason}); rerun meta-train") from None
    return policy_apply(model), restored["params"]


# -- cloning a policy's mean onto given actions (an expert's start) ----------------------------


class BCCarry(NamedTuple):
    """The scan carry of `clone_policy`."""

    policy: Any  # policy network params
    opt_state: Any


def _clone_loss(networks, normalizer, policy, obs, actions):
    """Mean squared error of the policy mean against the actions."""
    return jnp.mean(jnp.square(ppo.policy_mean(networks, normalizer, policy, obs) - actions))


def _clone_step(networks, optimizer, normalizer, obs, actions, carry: BCCarry, _unused):
    """One full-batch Adam step: (carry, None) -> (carry, loss)."""
    loss, grads = jax.value_and_grad(_clone_loss, argnums=2)(networks, normalizer, carry.policy, obs, actions)
    updates, opt_state = optimizer.update(grads, carry.opt_state, carry.policy)
    return BCCarry(optax.apply_updates(carry.policy, updates), opt_state), loss


def clone_policy(networks, policy, obs, actions, steps: int, learning_rate: float):
    """Fit the policy mean to (obs (T, O), actions (T, A)). Returns (policy params, losses (steps,)).

    Only the mean's weights move: the log-std keeps its initial value (its gradient is zero).
    """
    # Cosine decay to 1% of the peak: the late small steps fit sharp actions closely.
    optimizer = optax.adam(optax.cosine_decay_schedule(learning_rate, steps, alpha=0.01))
    normalizer = ppo.init_normalizer(obs.shape[-1])
    body = functools.partial(_clone_step, networks, optimizer, normalizer, obs, actions)
    carry, losses = jax.lax.scan(body, BCCarry(policy, optimizer.init(policy)), None, steps)
    return carry.policy, losses
