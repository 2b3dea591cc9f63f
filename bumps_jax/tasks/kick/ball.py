"""The ball's closed forms: where a kicked ball comes to rest, and whether it rolls.

`rest_point` gives where a rolling ball comes to rest without simulating its 20-40 s roll.
"""

from __future__ import annotations

import jax.numpy as jnp

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
