"""The physics under the kick env: the MJX backend (JAX or MuJoCo Warp) and the ball's closed forms.

`put_physics` builds the MJX model (and, for Warp, the blank data whose buffers every episode
of a program shares); `read_flags` reads Warp's overflow and solver-limit flags after a step.
`rest_point` gives where a rolling ball comes to rest without simulating its 20-40 s roll.
"""

from __future__ import annotations

import os
import sys

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from bumps_jax.tasks.kick import scene

GRAVITY = 9.81


def rest_point(pos, vel, angvel, decel_rate, radius=scene.BALL_RADIUS, rest_speed=scene.BALL_REST_SPEED):
    """Where a ball in state (pos, vel, angvel) comes to rest on the floor.

    pos, vel, angvel: (..., 3), world frame. Returns (..., 2), the resting x, y.

    1. A ball in the air flies ballistically until it touches the floor.
    2. From then on, friction at the contact point and the normal force through it cannot
       change the ball's angular momentum about that point, so slipping and bouncing end in
       rolling at v = (m r v_h - I z x w_h) / (m r + I / r), I = 2/5 m r^2 (solid sphere).
    3. Rolling obeys dv/dt = -c v: it covers (|v| - v_rest) / c more before resting.
    Exact (to the simulator's accuracy) for a rolling ball, which is what a kick leaves at the
    end of the kick phase; for a ball still slipping or in flight it ignores the distance
    gained while slipping (tests/test_scene.py measures both).
    """
    height = jnp.maximum(pos[..., 2] - radius, 0.0)
    vz = vel[..., 2]
    t_land = (vz + jnp.sqrt(vz**2 + 2.0 * GRAVITY * height)) / GRAVITY
    landing = pos[..., :2] + vel[..., :2] * t_land[..., None]
    # z x w for horizontal components: (-w_y, w_x).
    z_cross_w = jnp.stack([-angvel[..., 1], angvel[..., 0]], axis=-1)
    roll_vel = (vel[..., :2] - 0.4 * radius * z_cross_w) / 1.4
    speed = jnp.linalg.norm(roll_vel, axis=-1)
    direction = roll_vel / jnp.maximum(speed, 1e-9)[..., None]
    distance = jnp.maximum(speed - rest_speed, 0.0) / decel_rate
    return landing + direction * distance[..., None]


def rolling(vel, angvel, radius=scene.BALL_RADIUS, tolerance=0.05):
    """Whether the ball rolls without slipping (contact-point speed under `tolerance` m/s).

    vel, angvel: (..., 3) world frame. Returns (...) bool.
    """
    z_cross_w = jnp.stack([-angvel[..., 1], angvel[..., 0]], axis=-1)
    slip = vel[..., :2] + radius * z_cross_w
    return (jnp.linalg.norm(slip, axis=-1) < tolerance) & (jnp.abs(vel[..., 2]) < tolerance)


def put_physics(mj_model: mujoco.MjModel, cfg) -> tuple[mjx.Model, mjx.Data | None]:
    """The MJX model of `mj_model` for backend `cfg.impl`, and for Warp the blank episode data
    (its buffers sized by `cfg.warp_contacts` and `cfg.warp_constraints_per_world`); for JAX
    None (`mjx.make_data` sizes them from the model)."""
    if cfg.impl == "jax":
        return mjx.put_model(mj_model), None
    _init_warp()
    model = mjx.put_model(mj_model, impl="warp")
    # Overflows and unconverged solves are read from the data (`read_flags`), not printed.
    model = model.tree_replace({"opt._impl.warn_overflow": 0})
    data = mjx.make_data(mj_model, impl="warp", naconmax=cfg.warp_contacts, njmax=cfg.warp_constraints_per_world)
    return model, data


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
