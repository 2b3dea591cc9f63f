"""Offscreen pictures of the scene (MuJoCo's renderer: EGL on a GPU, OSMesa on a CPU)."""

from __future__ import annotations

from pathlib import Path

import mujoco

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
