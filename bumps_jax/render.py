"""Offscreen pictures and videos of the scene (MuJoCo's renderer: EGL on a GPU, OSMesa on a CPU)."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

from bumps_jax import kick_env, scene


def _camera(lookat, distance=1.1, azimuth=215.0, elevation=-18.0) -> mujoco.MjvCamera:
    cam = mujoco.MjvCamera()
    cam.lookat[:] = lookat
    cam.distance, cam.azimuth, cam.elevation = distance, azimuth, elevation
    return cam


def stance_picture(path: str | Path, width: int = 960, height: int = 720) -> Path:
    """A PNG of the robot in its stance beside the ball."""
    import imageio.v3 as iio

    model = scene.load_model()
    data = kick_env.mj_data_for(model)
    with mujoco.Renderer(model, height=height, width=width) as renderer:
        renderer.update_scene(data, camera=_camera([0.1, 0.0, 0.22]))
        pixels = renderer.render()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, pixels)
    return path


def kick_frames(actions: np.ndarray, width: int = 640, height: int = 480, follow_s: float = 1.0):
    """Frames (T, H, W, 3) of a noiseless kick replayed in C MuJoCo, 50 Hz.

    actions: (n_steps, 22) joint targets; the same servo ramp as the env. After the kick
    phase the camera follows the ball for `follow_s` seconds.
    """
    model = scene.load_model()
    ids = scene.scene_ids(model)
    data = kick_env.mj_data_for(model)
    n_sub = int(round(0.02 / model.opt.timestep))
    lo, hi = ids.joint_range[:, 0], ids.joint_range[:, 1]
    command = scene.STANCE.copy()
    frames = []
    hold = actions[-1]
    schedule = list(actions) + [hold] * int(follow_s / 0.02)
    with mujoco.Renderer(model, height=height, width=width) as renderer:
        for t, action in enumerate(schedule):
            ramp = kick_env.servo_ramp(command, np.asarray(action), lo, hi, scene.MAX_JOINT_SPEED * 0.02, n_sub)
            command = ramp[-1]
            for ctrl in ramp:
                data.ctrl[:] = ctrl
                mujoco.mj_step(model, data)
            ball = data.qpos[ids.ball_qpos : ids.ball_qpos + 3]
            lookat = [0.1, 0.0, 0.22] if t < len(actions) else [0.5 * (0.1 + ball[0]), 0.0, 0.15]
            renderer.update_scene(data, camera=_camera(lookat, distance=1.1 + 0.6 * max(0.0, ball[0] - 0.3)))
            frames.append(renderer.render())
    return np.stack(frames)
