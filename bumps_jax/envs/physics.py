"""The physics under every env: the MJX backend (JAX or MuJoCo Warp), servo limits and rotations.

`put_physics` builds the MJX model (and, for Warp, the blank data whose buffers every episode
of a program shares); `read_flags` reads Warp's overflow and solver-limit flags after a step.
"""

from __future__ import annotations

import os
import sys

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx


def local_device() -> jax.Device:
    """This process's first device: where MJX puts a model and its data (MJX's own default is
    the first device of every process, another process's in a multi-process run)."""
    return jax.local_devices()[0]


def put_physics(mj_model: mujoco.MjModel, cfg) -> tuple[mjx.Model, mjx.Data | None]:
    """The MJX model of `mj_model` for backend `cfg.impl`, and for Warp the blank episode data
    (its buffers sized by `cfg.warp_contacts` and `cfg.warp_constraints_per_world`); for JAX
    None (`blank_data` sizes them from the model)."""
    if cfg.impl == "jax":
        return mjx.put_model(mj_model, device=local_device()), None
    _init_warp()
    model = mjx.put_model(mj_model, impl="warp", device=local_device())
    # Overflows and unconverged solves are read from the data (`read_flags`), not printed.
    model = model.tree_replace({"opt._impl.warn_overflow": 0})
    data = mjx.make_data(mj_model, impl="warp", naconmax=cfg.warp_contacts, njmax=cfg.warp_constraints_per_world,
                         device=local_device())  # fmt: skip
    return model, data


def blank_data(model: mjx.Model, warp_data: mjx.Data | None) -> mjx.Data:
    """An episode's blank data: Warp's, sized by `put_physics`, or JAX's made from the model."""
    return mjx.make_data(model, device=local_device()) if warp_data is None else warp_data


def read_flags(data: mjx.Data) -> tuple[mjx.Data, jax.Array, jax.Array]:
    """(data with Warp's overflow mask cleared, a buffer overflowed (), the solver stopped at
    its iteration limit ()) after one physics call; JAX data: (data, False, False)."""
    if not hasattr(data._impl, "overflow"):
        return data, jnp.zeros((), bool), jnp.zeros((), bool)
    from mujoco.mjx.warp import mjwp_types  # noqa: PLC0415 (present where the data is Warp's)

    bits = mjwp_types.OverflowType
    flags = data._impl.overflow
    # Every bit but the solver's and its line search's iteration limits names a full buffer.
    overflowed = (flags & ~int(bits.ITERATIONS | bits.LS_ITERATIONS)) != 0
    hit_limit = (flags & int(bits.ITERATIONS)) != 0
    return data.tree_replace({"_impl.overflow": jnp.zeros_like(flags)}), overflowed, hit_limit


def _init_warp() -> None:
    """Start Warp without its banner and per-kernel load lines on stdout, and without the native
    driver warning a host with no CUDA driver prints on stderr."""
    import warp  # noqa: PLC0415

    warp.config.log_level = warp.LOG_WARNING
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            warp.init()
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def servo_ramp(command, wanted, low, high, max_delta, n_substeps):
    """The servo targets for each physics substep of one control step: (n_substeps, 22).

    SimSpark's motors turn at most 6.1395 rad/s. We emulate that on the target: it moves from
    `command` toward `wanted` (clipped to the joint limits) by at most `max_delta` per control
    step, as a ramp over the substeps rather than a jump, so that the servo tracks a target
    moving at the speed limit instead of chasing steps (which made joints overshoot it).
    Works on numpy and jax arrays alike.
    """
    xp = jnp if isinstance(command, jax.Array) or isinstance(wanted, jax.Array) else np
    delta = xp.clip(xp.clip(wanted, low, high) - command, -max_delta, max_delta)
    fractions = xp.arange(1, n_substeps + 1) / n_substeps
    return command + fractions[:, None] * delta


def conjugate(quat):
    return quat * jnp.array([1.0, -1.0, -1.0, -1.0])


def rotate(vec, quat):
    """vec (3,) rotated by the unit quaternion quat (4,), MuJoCo's (w, x, y, z) order."""
    w, u = quat[0], quat[1:]
    return vec + 2.0 * jnp.cross(u, jnp.cross(u, vec) + w * vec)
