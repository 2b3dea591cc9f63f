"""Behaviour cloning: the contextual meta-policy fitted to the experts' pairs, and a policy's
mean fitted to given actions (an expert's start).

The meta-policy (BUMPS step 2): an MLP (tanh hidden layers, linear output) maps the contextual
observation to the action: for the kick (phase, normalised context) to the 22 joint targets, for
a closed-loop task (the cheetah) the state and the normalised context to the motor commands.
Loss: mean absolute error; Adam with a staircase decay per epoch; an epoch is one pass over the
shuffled pairs in batches, the last one partial (as the original's Keras `fit`): ceil(N / batch)
gradient steps. Every net of a stage trains in one program, the nets padded and stacked, with a
hand-written backward pass (`make_trainer`): `jax.grad`'s optimisation in fewer kernels a step.
The pairs stay on the device; each chunk of epochs is one jitted lax.scan that shuffles epoch e
with key fold_in(seed key, e), so a resumed run draws the same batches as an uninterrupted one;
seeds are vmapped. The host syncs once per chunk: progress line, CSV row, orbax checkpoint.

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
from jax.flatten_util import ravel_pytree

from bumps_jax import resumable, runio
from bumps_jax.algo import ppo, sharding

# Gradient steps per iteration of the compiled epoch loop (lax.scan's unroll; at most an epoch's):
# the same steps on the same batches in fewer loop iterations.
UNROLL = 14
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
    states are not in [0, 1] as the kick's (phase, context) are. None: obs as it is (the kick's)."""

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


def steps_unrolled(epoch_steps: int) -> int:
    """Gradient steps per iteration of an epoch's compiled loop: `UNROLL`, at most the epoch's."""
    return min(UNROLL, epoch_steps)


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


# -- the trainer: every net padded and stacked in one program ------------------------------------
#
# The BC loop is launch-bound: a step of a tiny net at batch 128 is some 70-80 small kernels run
# one after another (docs/decisions.md, "Meta-policies and filtering"). Every net is padded to the
# largest depth and width and the nets are stacked on a leading axis, so that each layer of every
# net is one batched matmul: a step costs the kernels of one net of the largest depth.
#
# The padding changes nothing but rounding. Width: a net's padded units have zero weights in and
# out, so their pre-activation is 0, tanh(0) = 0, and every padded weight's gradient is exactly 0;
# Adam then leaves it at 0 (its moments stay 0). Depth: a shallower net's extra hidden layers pass
# their input through unchanged (`jnp.where` on a per-net mask), so their weights get zero
# gradients too. Each net's loss is its own mean absolute error on the same batch, and the
# gradient of their sum with respect to one net's weights is that net's gradient alone.


def _shape_of(models: dict) -> tuple[int, int, int, tuple | None]:
    """(largest depth, largest width, n_actions, obs_norm) of the nets, which must share the last two."""
    actions = {m.n_actions for m in models.values()}
    norms = {m.obs_norm for m in models.values()}
    if len(actions) != 1 or len(norms) != 1:
        raise ValueError("stacked nets must share n_actions and obs_norm")
    return max(m.depth for m in models.values()), max(m.width for m in models.values()), actions.pop(), norms.pop()


def stack_params(models: dict, params: dict) -> dict:
    """{name: flax params of `bc.MetaPolicy`} -> the stacked layout: w0 (N, O, W), b0 (N, W), wh (N, D-1, W, W),
    bh (N, D-1, W), wo (N, W, A), bo (N, A), zero where a net is narrower or shallower."""
    depth, width, _, _ = _shape_of(models)

    def one(model, p):
        w, d = model.width, model.depth
        obs_size, n_actions = p["Dense_0"]["kernel"].shape[0], p[f"Dense_{d}"]["kernel"].shape[1]
        dtype = p["Dense_0"]["kernel"].dtype
        out = {
            "w0": jnp.zeros((obs_size, width), dtype).at[:, :w].set(p["Dense_0"]["kernel"]),
            "b0": jnp.zeros((width,), dtype).at[:w].set(p["Dense_0"]["bias"]),
            "wh": jnp.zeros((depth - 1, width, width), dtype),
            "bh": jnp.zeros((depth - 1, width), dtype),
            "wo": jnp.zeros((width, n_actions), dtype).at[:w].set(p[f"Dense_{d}"]["kernel"]),
            "bo": p[f"Dense_{d}"]["bias"],
        }
        for layer in range(1, d):
            out["wh"] = out["wh"].at[layer - 1, :w, :w].set(p[f"Dense_{layer}"]["kernel"])
            out["bh"] = out["bh"].at[layer - 1, :w].set(p[f"Dense_{layer}"]["bias"])
        return out

    per_net = [one(model, params[name]) for name, model in models.items()]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *per_net)


def unstack_params(models: dict, stacked: dict) -> dict:
    """The inverse of `stack_params`: {name: flax params}."""
    out = {}
    for i, (name, model) in enumerate(models.items()):
        w, d = model.width, model.depth
        p = {"Dense_0": {"kernel": stacked["w0"][i, :, :w], "bias": stacked["b0"][i, :w]}}
        for layer in range(1, d):
            p[f"Dense_{layer}"] = {
                "kernel": stacked["wh"][i, layer - 1, :w, :w],
                "bias": stacked["bh"][i, layer - 1, :w],
            }
        p[f"Dense_{d}"] = {"kernel": stacked["wo"][i, :w], "bias": stacked["bo"][i]}
        out[name] = p
    return out


def _ravel(tree) -> jax.Array:
    """A pytree as one vector: the vector `optax.flatten` keeps (it ravels with `ravel_pytree` too)."""
    return ravel_pytree(tree)[0]


def _unravel(template, flat) -> dict:
    """`_ravel`'s inverse, shaped like `template`."""
    return ravel_pytree(template)[1](flat)


def stack_opt_states(models: dict, params: dict, opt_states: dict):
    """Each net's `optax.flatten(optax.adam)` state -> the stacked params' state of the same kind:
    a vector over a net's params (Adam's moments) is laid out as `stack_params` lays the params;
    a scalar (the step count, the same for every net) is kept."""
    names = list(models)

    def leaf(*xs):
        if xs[0].ndim == 0:
            return xs[0]
        trees = {name: _unravel(params[name], x) for name, x in zip(names, xs, strict=True)}
        return _ravel(stack_params(models, trees))

    return jax.tree.map(leaf, *(opt_states[name] for name in names))


def unstack_opt_states(models: dict, stacked_params: dict, stacked_state) -> dict:
    """The inverse of `stack_opt_states`: {name: that net's flattened Adam state}."""

    def per_net(x) -> dict:  # one leaf of the stacked state -> {name: that net's leaf}
        if x.ndim == 0:
            return {name: x for name in models}
        return {name: _ravel(t) for name, t in unstack_params(models, _unravel(stacked_params, x)).items()}

    leaves, treedef = jax.tree.flatten(stacked_state)
    split = [per_net(x) for x in leaves]
    return {name: jax.tree.unflatten(treedef, [s[name] for s in split]) for name in models}


def _layout(models: dict) -> tuple[int, jax.Array, tuple | None]:
    """(largest depth, active (N, depth - 1): hidden layer l + 1 is one of net n's own, obs_norm)."""
    depth, _, _, obs_norm = _shape_of(models)
    active = jnp.asarray([[layer + 1 < m.depth for layer in range(depth - 1)] for m in models.values()])
    return depth, active, obs_norm


def _normalised(obs, obs_norm):
    if obs_norm is None:
        return obs
    shift, scale = (jnp.asarray(v, obs.dtype) for v in obs_norm)
    return (obs - shift) / scale


def _forward_one(p: dict, active, x) -> tuple[jax.Array, list, list]:
    """One net's (output (B, A), hidden values [h_0 ... h_(D-1)], the stacked layers' tanh [t_0 ...]):
    h_0 = tanh(x w0 + b0); t_l = tanh(h_l wh_l + bh_l); h_(l+1) = t_l where the layer is the net's
    own, else h_l; the output reads h_(D-1)."""
    hidden, outputs = [jnp.tanh(x @ p["w0"] + p["b0"])], []
    for layer in range(p["wh"].shape[0]):
        outputs.append(jnp.tanh(hidden[-1] @ p["wh"][layer] + p["bh"][layer]))
        hidden.append(jnp.where(active[layer], outputs[-1], hidden[-1]))
    return hidden[-1] @ p["wo"] + p["bo"], hidden, outputs


def make_forward(models: dict):
    """apply(stacked params, obs (B, O)) -> actions (N, B, A) of every net on the same observations."""
    _, active, obs_norm = _layout(models)

    def apply(stacked, obs):
        one = lambda p, act, x: _forward_one(p, act, x)[0]  # noqa: E731
        return jax.vmap(one, in_axes=(0, 0, None))(stacked, active, _normalised(obs, obs_norm))

    return apply


def _grads_one(p: dict, active, x, actions, weights) -> tuple[jax.Array, dict]:
    """One net's (loss, gradient) written out by hand: the backward pass of `_forward_one` and
    `bc.mae`, with the stacked hidden layers' weight gradients as one batched matmul over the
    layers (and their bias gradients as one sum) instead of a matmul and a sum per layer."""
    out, hidden, outputs = _forward_one(p, active, x)
    loss = mae(out, actions, weights)
    # d|r|/dr = sign(r) (0 at 0, as jax.grad of jnp.abs), over A joints and the rows of weight 1
    d_out = jnp.sign(out - actions) * (weights / (out.shape[-1] * jnp.sum(weights)))[:, None]
    grads = {"wo": hidden[-1].T @ d_out, "bo": jnp.sum(d_out, axis=0)}
    g, dz = d_out @ p["wo"].T, [None] * len(outputs)  # g: the gradient at the current hidden value
    for layer in reversed(range(len(outputs))):
        dz[layer] = jnp.where(active[layer], g * (1 - outputs[layer] ** 2), 0.0)
        g = jnp.where(active[layer], dz[layer] @ p["wh"][layer].T, g)  # a layer not the net's passes g on
    if outputs:  # (D - 1, B, W) each: every stacked layer's input and pre-activation gradient at once
        hs, dzs = jnp.stack(hidden[:-1]), jnp.stack(dz)
        grads["wh"], grads["bh"] = jnp.einsum("lbi,lbj->lij", hs, dzs), jnp.sum(dzs, axis=1)
    else:
        grads["wh"], grads["bh"] = jnp.zeros_like(p["wh"]), jnp.zeros_like(p["bh"])
    dz0 = g * (1 - hidden[0] ** 2)
    grads["w0"], grads["b0"] = x.T @ dz0, jnp.sum(dz0, axis=0)
    return loss, grads


def make_loss_and_grads(models: dict):
    """fn(stacked params, obs (B, O), actions (B, A), weights (B,)) -> (each net's loss (N,), the
    gradient of their sum, written out by hand: `_grads_one`, `jax.grad`'s numbers up to rounding
    in fewer kernels)."""
    _, active, obs_norm = _layout(models)

    def fn(stacked, obs, actions, weights):
        x = _normalised(obs, obs_norm)
        return jax.vmap(_grads_one, in_axes=(0, 0, None, None, None))(stacked, active, x, actions, weights)

    return fn


def make_trainer(models: dict, train_cfg, n_rows: int, obs_size: int = 2):
    """(init, chunk) training every net of `models` (name -> MetaPolicy, observations of
    `obs_size`) stacked in one compiled loop, each on the same batches as it would see alone (the
    shuffles depend on the seed only): init(seed_keys (S,)) -> {name: TrainState};
    chunk(states, obs (N, O), actions (N, A), seed_keys (S,)) -> (states after train_cfg.chunk
    more epochs, {name: losses (S, chunk epochs x steps per epoch)}). Both jitted.

    Each net starts from flax's initialisation and steps with Adam over its own flat vector
    (`optax.flatten`), as `jax.grad` of its own MAE would move it: the gradient is written out by
    hand (`_grads_one`), the nets padded and stacked so that each layer of every net is one
    batched matmul, and `steps_unrolled` steps run per iteration of the epoch's loop. A state
    holds each net's own flax params and flattened Adam state (the stacking is inside a chunk)."""
    names = list(models)
    epoch_steps = steps_per_epoch(train_cfg, n_rows)
    optimizer = optax.flatten(optax.adam(lr_schedule(train_cfg, epoch_steps)))
    loss_and_grads = make_loss_and_grads(models)
    # A batch holds at most the whole dataset: a larger batch_size would pad every step to its size.
    batch_size, chunk_epochs = min(int(train_cfg.batch_size), int(n_rows)), int(train_cfg.chunk)
    unroll = steps_unrolled(epoch_steps)

    def init_one(key):
        params = {name: model.init(key, jnp.zeros((1, obs_size)))["params"] for name, model in models.items()}
        return params, {name: optimizer.init(p) for name, p in params.items()}

    @jax.jit
    def init(seed_keys):
        params, opt_states = jax.vmap(init_one)(seed_keys)
        zero = jnp.zeros((), jnp.int32)
        return {name: TrainState(params[name], opt_states[name], zero) for name in names}

    def epoch(obs, actions, seed_key, carry, epoch_index):
        n = obs.shape[0]

        def step(carry, batch):
            params, opt_state = carry
            idx, slot = batch
            weights = (slot < n).astype(obs.dtype)
            per_net, grads = loss_and_grads(params, obs[idx], actions[idx], weights)
            updates, opt_state = optimizer.update(grads, opt_state, params)
            return (optax.apply_updates(params, updates), opt_state), per_net

        batches = epoch_batches(seed_key, epoch_index, n, epoch_steps, batch_size)
        return jax.lax.scan(step, carry, batches, unroll=unroll)

    def chunk_one(params: dict, opt_states: dict, seed_key, obs, actions, epochs):
        stacked = stack_params(models, params)
        carry = (stacked, stack_opt_states(models, params, opt_states))
        (stacked, opt_state), losses = jax.lax.scan(functools.partial(epoch, obs, actions, seed_key), carry, epochs)
        losses = losses.reshape(-1, len(names))  # (epochs x steps, N)
        unstacked = unstack_params(models, stacked)
        return unstacked, unstack_opt_states(models, stacked, opt_state), {n: losses[:, i] for i, n in enumerate(names)}

    @jax.jit
    def chunk(states: dict, obs, actions, seed_keys):
        if obs.shape[0] != n_rows:
            raise ValueError(f"the trainer was built for {n_rows} pairs, got {obs.shape[0]}")
        step = states[names[0]].step
        epochs = step // epoch_steps + jnp.arange(chunk_epochs, dtype=jnp.int32)
        params = {name: states[name].params for name in names}
        opt_states = {name: states[name].opt_state for name in names}
        params, opt_states, losses = jax.vmap(chunk_one, in_axes=(0, 0, 0, None, None, None))(
            params, opt_states, seed_keys, obs, actions, epochs
        )
        done = step + chunk_epochs * epoch_steps
        return {name: TrainState(params[name], opt_states[name], done) for name in names}, losses

    return init, chunk


def shared_chunk(chunk, states: dict, own: list, names: list, inputs: tuple, loss_shape: tuple) -> tuple[dict, dict]:
    """One chunk of the nets `own` (this process's share, maybe none), then every net's state and
    losses from the process that trained it (`sharding.from_owners`): (states, {name: losses})."""
    mine, losses = chunk({n: states[n] for n in own}, *inputs) if own else ({}, {})
    states = {**states, **mine}
    blank = np.zeros(loss_shape, np.float32)  # another process's net: its shapes only
    shared = dict(zip(names, sharding.from_owners([(states[n], np.asarray(losses.get(n, blank))) for n in names]),
                      strict=True))  # fmt: skip
    return {n: s for n, (s, _) in shared.items()}, {n: x for n, (_, x) in shared.items()}


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
    trainer: `make_trainer({"net": model}, ...)`'s (init, chunk), to reuse its compiled programs."""
    return train_nets({"net": model}, data, train_cfg, {"net": out_dir}, say, max_chunks, trainer)["net"]


def train_nets(models: dict, data: Dataset, train_cfg, out_dirs: dict, say=print, max_chunks=None,
               trainer=None) -> dict:  # fmt: skip
    """Train (or resume) every net of `models` (name -> MetaPolicy) on data (N pairs) in one loop
    (with several processes, each process's share of the nets: `shared_chunk`); returns {name:
    final TrainState} on every process, whose `step` counts gradient steps (train_cfg.epochs x
    `steps_per_epoch`).

    trainer: `make_trainer`'s (init, chunk) for these nets, to reuse its compiled programs. After
    every chunk each net writes
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
    init, chunk = trainer or make_trainer(models, train_cfg, len(data.obs), data.obs.shape[-1])
    # With several processes each trains its share of the nets (`sharding.owner`), and after
    # every chunk every process takes each net's state and losses from its owner.
    own = sharding.own_items(names) if len(names) > 1 else names
    if own and own != names:
        _, chunk = make_trainer({n: models[n] for n in own}, train_cfg, len(data.obs), data.obs.shape[-1])
    epoch_steps = steps_per_epoch(train_cfg, len(data.obs))
    total_steps = train_cfg.epochs * epoch_steps
    keys = seed_keys(train_cfg)
    schedule = lr_schedule(train_cfg, epoch_steps)
    with contextlib.ExitStack() as managers_open:
        managers = {
            name: managers_open.enter_context(
                resumable.checkpoint_manager(out_dirs[name] / "checkpoints", KEEP_CHECKPOINTS)
            )
            for name in names
        }
        fresh = init(keys)
        restore = {name: ocp.args.StandardRestore(fresh[name]) for name in names}
        step, states = resumable.restore_latest_common(managers, restore, say)
        if step is None:
            states = fresh
        else:
            where = ", ".join(runio.shown(d) for d in out_dirs.values())
            say(f"  resumed from epoch {int(states[names[0]].step) // epoch_steps} in {where}")
        done = int(states[names[0]].step)
        for name in names:
            runio.trim_csv(out_dirs[name] / "progress.csv", CSV_FIELDS, "step", done)
        loss_shape = (len(keys), int(train_cfg.chunk) * epoch_steps)  # a chunk's losses of one net
        obs, actions = jnp.asarray(data.obs), jnp.asarray(data.actions)  # resident on the device
        done_chunks, pace = 0, resumable.Clock(total_steps)
        with resumable.stop_on_interrupt(say) as stop:
            while done < total_steps and (max_chunks is None or done_chunks < max_chunks):
                t0 = time.perf_counter()
                if own == names:
                    states, losses = chunk(states, obs, actions, keys)
                    losses = {n: np.asarray(losses[n]) for n in names}  # waits for the chunk to finish
                else:
                    states, losses = shared_chunk(chunk, states, own, names, (obs, actions, keys), loss_shape)
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
    init, _ = make_trainer({"net": model}, train_cfg, 1, obs_size)  # the state's shapes do not depend on the data
    # Only the params: a policy does not need the optimiser's state, whose layout may differ
    # between versions of the trainer. (Real arrays, not `jax.eval_shape`: orbax restores a leaf
    # without a sharding as a NumPy array, and initialising these small nets takes milliseconds.)
    target = {"params": init(seed_keys(train_cfg))["net"].params}
    restore_args = ocp.checkpoint_utils.construct_restore_args(target)
    args = ocp.args.PyTreeRestore(item=target, restore_args=restore_args, partial_restore=True)
    with resumable.checkpoint_manager(path, KEEP_CHECKPOINTS, read_only=True) as manager:
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
