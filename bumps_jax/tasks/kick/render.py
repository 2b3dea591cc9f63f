"""Offscreen pictures of the scene (MuJoCo's renderer: EGL on a GPU, OSMesa on a CPU)."""

from __future__ import annotations

from pathlib import Path

import mujoco

from bumps_jax.algo import rollout
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import scene


def check_gl() -> None:
    """ValueError in one line, before any long work, if MuJoCo cannot open an offscreen GL context
    (the backend MUJOCO_GL named when mujoco was imported: `cli.choose_gl`)."""
    import os  # noqa: PLC0415

    backend = os.environ.get("MUJOCO_GL")
    try:
        model = mujoco.MjModel.from_xml_string("<mujoco/>")
        with mujoco.Renderer(model, height=8, width=8) as renderer:
            renderer.update_scene(mujoco.MjData(model))
            renderer.render()
    except Exception as err:  # noqa: BLE001 (GLFW, EGL and OSMesa fail in many ways)
        reason = str(err).strip().splitlines()[0][:120] if str(err).strip() else type(err).__name__
        raise ValueError(
            f"cannot render offscreen (MUJOCO_GL={backend or 'unset'}: {reason}): this host needs an EGL or "
            "OSMesa library; set MUJOCO_GL=egl or MUJOCO_GL=osmesa to the one it has"
        ) from None


def _camera(lookat, distance=1.1, azimuth=215.0, elevation=-18.0) -> mujoco.MjvCamera:
    cam = mujoco.MjvCamera()
    cam.lookat[:] = lookat
    cam.distance, cam.azimuth, cam.elevation = distance, azimuth, elevation
    return cam


def stance_picture(path: str | Path, width: int = 960, height: int = 720) -> Path:
    """A PNG of the robot in its stance beside the ball."""
    import imageio.v3 as iio

    model = scene.load_model()
    data = scene.mj_data_for(model)
    with mujoco.Renderer(model, height=height, width=width) as renderer:
        renderer.update_scene(data, camera=_camera([0.1, 0.0, 0.22]))
        pixels = renderer.render()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, pixels)
    return path


# -- a GIF of kicks ----------------------------------------------------------------------------

# Seconds of rolling shown after the kick phase, and how much faster than real time: a ball
# decelerating at 0.08/s rolls for tens of seconds.
ROLL_SECONDS = 40.0
ROLL_SPEEDUP = 10.0


def kick_states_fn(env: kick_env.KickEnv, apply_fn):
    """Jitted (params, context m, target m, key) -> (qpos (T, nq) after each control step, rest_xy (2,)).

    The kick phase as the policy plays it (the policy sees `context`, the env scores `target`),
    and where the env's closed form puts the ball at rest.
    """
    import jax  # noqa: PLC0415

    episode = rollout.episode_fn(env, apply_fn, record="qpos")

    def run(params, context, target, key):
        metrics, qpos = episode(params, context, target, key)
        return qpos, jax.numpy.stack([metrics["rest_x"], metrics["rest_y"]])

    return jax.jit(run)


def _target_marker(scene_, xy, rgba=(0.9, 0.1, 0.1, 0.9)) -> None:
    """A flat disc on the floor at `xy`, drawn into an updated mjvScene."""
    import numpy as np

    if scene_.ngeom >= scene_.maxgeom:
        return
    geom = scene_.geoms[scene_.ngeom]
    mujoco.mjv_initGeom(
        geom,
        mujoco.mjtGeom.mjGEOM_CYLINDER,
        np.array([0.25, 0.003, 0.0]),
        np.array([xy[0], xy[1], 0.003]),
        np.eye(3).ravel(),
        np.asarray(rgba, np.float32),
    )
    scene_.ngeom += 1


def kick_frames(env, qpos, rest_xy, target_xy, label: str, fps: int, width: int, height: int) -> list:
    """RGB frames (PIL images) of one kick: the kick phase in real time, then the roll to rest
    time-lapsed, the camera following the ball, the target marked in red."""
    import numpy as np
    from PIL import Image, ImageDraw

    model = env.mj_model
    data = mujoco.MjData(model)
    ball = env.ids.ball_qpos
    ctrl_dt = env.config.ctrl_dt
    kick_t = np.arange(0.0, len(qpos) * ctrl_dt, 1.0 / fps)
    poses = [qpos[min(int(t / ctrl_dt), len(qpos) - 1)] for t in kick_t]
    # After the kick the ball approaches its resting point as a rolling ball does,
    # x(t) = x_rest - (x_rest - x_end) e^{-c t}, shown ROLL_SPEEDUP times faster.
    c = env.decel_rate
    end = np.array(qpos[-1], np.float64)
    start_xy = end[ball : ball + 2].copy()
    n_roll = int(ROLL_SECONDS / ROLL_SPEEDUP * fps)
    for i in range(1, n_roll + 1):  # the last frame at the resting point itself
        frac = (1.0 - np.exp(-c * ROLL_SECONDS * i / n_roll)) / (1.0 - np.exp(-c * ROLL_SECONDS))
        q = end.copy()
        q[ball : ball + 2] = start_xy + frac * (np.asarray(rest_xy) - start_xy)
        poses.append(q)
    x0 = float(qpos[0][ball])  # distances are measured from the ball's start
    frames = []
    with mujoco.Renderer(model, height=height, width=width) as renderer:
        for k, q in enumerate(poses):
            data.qpos[:] = q
            mujoco.mj_forward(model, data)
            bx = float(q[ball])
            cam = _camera([bx + 0.3, 0.0, 0.1], distance=1.6 + 0.25 * max(bx - x0, 0.0), azimuth=220.0, elevation=-20.0)
            renderer.update_scene(data, camera=cam)
            _target_marker(renderer.scene, target_xy)
            img = Image.fromarray(renderer.render())
            draw = ImageDraw.Draw(img)
            phase = "kick" if k < len(kick_t) else f"rolling, {ROLL_SPEEDUP:.0f}x faster"
            draw.text((8, 8), f"{label}\nball {bx - x0:5.1f} m ({phase})", fill=(255, 255, 255))
            frames.append(img)
    return frames


def kick_gif(path, env, apply_fn, params, contexts, targets, seed: int = 0, fps: int = 20, size=(400, 300),
             keys=None) -> Path:  # fmt: skip
    """A GIF of one noisy kick per (context, target), panels side by side. Returns the path.
    keys: each kick's noise key (default: split from `seed`), e.g. a kick already measured."""
    import jax
    import numpy as np
    from PIL import Image

    if len(contexts) != len(targets) or len(targets) == 0:
        raise ValueError(f"need as many contexts as targets (at least one), got {len(contexts)} and {len(targets)}")
    run = kick_states_fn(env, apply_fn)
    keys = jax.random.split(jax.random.key(seed), len(targets)) if keys is None else keys
    ball = env.ids.ball_qpos
    panels = []
    for context, target, key in zip(contexts, targets, keys, strict=True):
        qpos, rest = run(params, float(context), float(target), key)
        qpos, rest = np.asarray(qpos), np.asarray(rest)
        start = qpos[0][ball : ball + 2]
        error = float(np.linalg.norm(rest - (start + np.array([target, 0.0]))))
        rests = float(rest[0] - start[0])  # along the kick line, as `kick` prints each kick
        label = f"target {target:.1f} m, context {context:.2f} m: rests at {rests:.2f} m, error {error:.2f} m"
        target_xy = start + np.array([target, 0.0])
        panels.append(kick_frames(env, qpos, rest, target_xy, label, fps, *size))
    n = max(len(p) for p in panels)
    frames = []
    for i in range(n):
        row = Image.new("RGB", (size[0] * len(panels), size[1]))
        for j, p in enumerate(panels):
            row.paste(p[min(i, len(p) - 1)], (j * size[0], 0))
        frames.append(row)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=int(1000 / fps), loop=0)
    return path
