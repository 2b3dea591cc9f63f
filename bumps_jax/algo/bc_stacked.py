"""Several meta-policies trained in one stacked program: the same optimisation as
`bc.make_joint_trainer`, in fewer kernels a step.

The BC loop is launch-bound: a step of a tiny net at batch 128 is some 70-80 small kernels run
one after another, and two nets in one loop (`bc.make_joint_trainer`) run theirs one after the
other too (docs/decisions.md, "Meta-policies and filtering"). Here every net is padded to the
largest depth and width and the nets are stacked on a leading axis, so that each layer of every
net is one batched matmul: a step costs the kernels of one net of the largest depth.

The padding changes nothing but rounding. Width: a net's padded units have zero weights in and
out, so their pre-activation is 0, tanh(0) = 0, and every padded weight's gradient is exactly 0;
Adam then leaves it at 0 (its moments stay 0). Depth: a shallower net's extra hidden layers pass
their input through unchanged (`jnp.where` on a per-net mask), so their weights get zero
gradients too. Each net's loss is its own mean absolute error on the same batch, and the
gradient of their sum with respect to one net's weights is that net's gradient alone.

`make_stacked_trainer` has `bc.make_joint_trainer`'s interface and its states (each net's flax
params and flattened Adam state): a chunk converts them to the stacked layout and back, so either
trainer resumes the other's checkpoints.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import optax
from jax.flatten_util import ravel_pytree

from bumps_jax.algo import bc


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
    loss = bc.mae(out, actions, weights)
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


def make_loss_and_grads(models: dict, backward: str = "autodiff"):
    """fn(stacked params, obs (B, O), actions (B, A), weights (B,)) -> (each net's loss (N,), the
    gradient of their sum). backward "autodiff": `jax.grad`; "batched": `_grads_one`, the same
    numbers up to rounding in fewer kernels."""
    _, active, obs_norm = _layout(models)
    if backward == "autodiff":
        forward = make_forward(models)

        def total(stacked, obs, actions, weights):
            per_net = jax.vmap(bc.mae, in_axes=(0, None, None))(forward(stacked, obs), actions, weights)
            return jnp.sum(per_net), per_net

        def fn(stacked, obs, actions, weights):
            (_, per_net), grads = jax.value_and_grad(total, has_aux=True)(stacked, obs, actions, weights)
            return per_net, grads

        return fn
    if backward == "batched":

        def fn(stacked, obs, actions, weights):
            x = _normalised(obs, obs_norm)
            return jax.vmap(_grads_one, in_axes=(0, 0, None, None, None))(stacked, active, x, actions, weights)

        return fn
    raise ValueError(f"backward must be 'autodiff' or 'batched', got {backward!r}")


def make_stacked_trainer(models: dict, train_cfg, n_rows: int, obs_size: int = 2, backward: str = "autodiff"):
    """`bc.make_joint_trainer`'s (init, chunk), with the nets stacked in one program: the same
    initial params (flax's), batches, schedule and Adam, so each net ends where its own trainer
    would up to float rounding. `backward`: how the gradient is computed (`make_loss_and_grads`).
    Both jitted."""
    names = list(models)
    epoch_steps = bc.steps_per_epoch(train_cfg, n_rows)
    stacked_opt = optax.flatten(optax.adam(bc.lr_schedule(train_cfg, epoch_steps)))
    loss_and_grads = make_loss_and_grads(models, backward)
    joint_init, _ = bc.make_joint_trainer(models, train_cfg, n_rows, obs_size)
    batch_size, chunk_epochs = int(train_cfg.batch_size), int(train_cfg.chunk)
    unroll = bc.steps_unrolled(train_cfg, epoch_steps)

    def epoch(obs, actions, seed_key, carry, epoch_index):
        n = obs.shape[0]

        def step(carry, batch):
            params, opt_state = carry
            idx, slot = batch
            weights = (slot < n).astype(obs.dtype)
            per_net, grads = loss_and_grads(params, obs[idx], actions[idx], weights)
            updates, opt_state = stacked_opt.update(grads, opt_state, params)
            return (optax.apply_updates(params, updates), opt_state), per_net

        batches = bc.epoch_batches(seed_key, epoch_index, n, epoch_steps, batch_size)
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
        return {name: bc.TrainState(params[name], opt_states[name], done) for name in names}, losses

    # init is the joint trainer's: each net's flax params and flattened Adam state, as there
    return joint_init, chunk
