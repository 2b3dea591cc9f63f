"""The kick env's control loop replayed in C MuJoCo, the reference engine, without noise.

MJX's JAX backend and C MuJoCo step the same scene differently enough that one kick can rest
metres apart in the two. This plays a kick's actions as `KickEnv.step` applies them (the same
servo ramp over the env's substeps of its control step, at its physics step) in C MuJoCo, and
scores the ball as the env does: `kick_env.rest_point` with the env's rolling deceleration,
distance along the kick line and sideways offset from the ball's nominal start. Nothing is
random: the robot starts in the exact stance, frictions and servo gains are nominal; only the
ball's start can be moved (`ball_offset`).

    outcome = c_replay.replay(env, actions)       # actions (T, 22) rad
    outcome.distance, outcome.lateral             # m, as the env's metrics

`Replay` steps one control step at a time, for callers that look inside the episode.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import NamedTuple

import mujoco
import numpy as np

from bumps_jax.envs import physics
from bumps_jax.tasks.kick import ball, scene

# on_substep(model, data, control_step) runs after every physics substep.
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model

# on_substep(model, data, control_step) runs after every physics substep.
SubstepHook = Callable[[mujoco.MjModel, mujoco.MjData, int], None]


class Outcome(NamedTuple):
    """A replayed kick, scored as the env's final metrics score it."""

    distance: float  # m: resting point along the kick line, from the ball's nominal start
    lateral: float  # m: resting point to the left of the kick line
    rest_x: float  # m: resting point, world frame
    rest_y: float
    valid: bool  # struck, not fallen, not blown up (the env's `valid`)
    struck: bool  # the ball reached env.config.strike_speed at the end of some control step
    fallen: bool  # the torso went below env.config.fall_height
    blown_up: bool  # non-finite state, a speed over env.config.blowup_speed, or MuJoCo's reset
    max_ball_speed: float  # m/s, over the ends of the control steps
    min_torso_z: float  # m, likewise
    ball_pos: np.ndarray  # (3,) m, world frame, after the last control step replayed
    ball_vel: np.ndarray  # (3,) m/s, world frame
    ball_angvel: np.ndarray  # (3,) rad/s, world frame


def scene_model(env: kick_env.KickEnv, iterations: int | None = None, model: mujoco.MjModel | None = None):
    """A copy of the C model to replay in: `model` (a variant of the scene) or env.mj_model, with
    `iterations` constraint-solver iterations if given. ValueError for a physics step other than
    the env's (its substeps would not fill its control step) or iterations < 1."""
    model = copy.deepcopy(env.mj_model if model is None else model)
    if not np.isclose(model.opt.timestep, env.physics_dt, rtol=1e-9):
        raise ValueError(
            f"model timestep {model.opt.timestep} s differs from the env's physics step {env.physics_dt} s"
        )
    if iterations is not None:
        if isinstance(iterations, bool) or not isinstance(iterations, int | np.integer) or iterations < 1:
            raise ValueError(f"iterations must be a positive integer, got {iterations!r}")
        model.opt.iterations = int(iterations)
    return model


class Replay:
    """One noise-free C MuJoCo episode, stepped as `KickEnv.step` steps the MJX one."""

    def __init__(
        self,
        env: kick_env.KickEnv,
        ball_offset=(0.0, 0.0),
        iterations: int | None = None,
        model: mujoco.MjModel | None = None,
        on_substep: SubstepHook | None = None,
    ):
        """ball_offset: (dx, dy) m added to the ball's nominal start; iterations, model: `scene_model`."""
        offset = np.asarray(ball_offset, np.float64)
        if offset.shape != (2,) or not np.all(np.isfinite(offset)):
            raise ValueError(f"ball_offset must be two finite numbers (m), got {ball_offset!r}")
        self.env, self.on_substep = env, on_substep
        self.model = scene_model(env, iterations, model)
        self.ids = scene.scene_ids(self.model)
        qpos = scene.stance_qpos(self.model)
        q = self.ids.ball_qpos
        self.ball_start = qpos[q : q + 2].copy()  # nominal: the env's distance is measured from it
        qpos[q : q + 2] += offset
        self.data = mujoco.MjData(self.model)
        self.data.qpos[:] = qpos
        self.data.ctrl[:] = scene.STANCE
        mujoco.mj_forward(self.model, self.data)
        self.command = scene.STANCE.copy()
        self.low, self.high = self.ids.joint_range[:, 0], self.ids.joint_range[:, 1]
        self.max_delta = scene.MAX_JOINT_SPEED * env.config.ctrl_dt
        self.steps, self.max_ball_speed, self.min_torso_z, self.blown_up = 0, 0.0, np.inf, False

    def step(self, action) -> None:
        """One control step: the servo ramp toward `action` (22,) rad over env.n_substeps physics steps."""
        action = np.asarray(action, np.float64)
        if action.shape != (scene.N_JOINTS,) or not np.all(np.isfinite(action)):
            raise ValueError(f"action must be {scene.N_JOINTS} finite joint targets, got shape {action.shape}")
        ramp = physics.servo_ramp(
            self.command, action, self.low, self.high, self.max_delta, self.env.n_substeps
        )  # fmt: skip
        for ctrl in ramp:
            self.data.ctrl[:] = ctrl
            mujoco.mj_step(self.model, self.data)
            if self.on_substep is not None:
                self.on_substep(self.model, self.data, self.steps)
        self.command = ramp[-1]
        self.steps += 1
        cfg, data, v = self.env.config, self.data, self.ids.ball_qvel
        finite = np.all(np.isfinite(data.qpos)) and np.all(np.isfinite(data.qvel))
        reset = data.warning[int(mujoco.mjtWarning.mjWARN_BADQACC)].number > 0  # MuJoCo reset a diverged state
        self.blown_up |= bool(not finite or reset or np.max(np.abs(np.nan_to_num(data.qvel))) > cfg.blowup_speed)
        self.max_ball_speed = max(self.max_ball_speed, float(np.linalg.norm(data.qvel[v : v + 3])))
        self.min_torso_z = min(self.min_torso_z, float(data.xpos[self.ids.torso_body, 2]))

    def ball_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The ball's (pos, vel, angvel), each (3,), world frame (MuJoCo keeps angvel in the body frame)."""
        q, v = self.ids.ball_qpos, self.ids.ball_qvel
        angvel = np.zeros(3)
        mujoco.mju_rotVecQuat(angvel, self.data.qvel[v + 3 : v + 6], self.data.qpos[q + 3 : q + 7])
        return self.data.qpos[q : q + 3].copy(), self.data.qvel[v : v + 3].copy(), angvel

    def outcome(self) -> Outcome:
        """The kick scored now, as the env scores its final state (see `Outcome`)."""
        cfg = self.env.config
        pos, vel, angvel = self.ball_state()
        rest = np.asarray(ball.rest_point(pos, vel, angvel, self.env.decel_rate), np.float64)
        struck = self.max_ball_speed >= cfg.strike_speed
        fallen = self.min_torso_z < cfg.fall_height
        return Outcome(
            distance=float(rest[0] - self.ball_start[0]),
            lateral=float(rest[1] - self.ball_start[1]),
            rest_x=float(rest[0]),
            rest_y=float(rest[1]),
            valid=bool(struck and not fallen and not self.blown_up),
            struck=bool(struck),
            fallen=bool(fallen),
            blown_up=self.blown_up,
            max_ball_speed=self.max_ball_speed,
            min_torso_z=self.min_torso_z,
            ball_pos=pos,
            ball_vel=vel,
            ball_angvel=angvel,
        )


def replay(
    env: kick_env.KickEnv,
    actions,
    ball_offset=(0.0, 0.0),
    iterations: int | None = None,
    model: mujoco.MjModel | None = None,
    on_substep: SubstepHook | None = None,
) -> Outcome:
    """A kick's actions (T, 22) rad, one per control step (T = env.n_steps for a whole episode),
    replayed without noise in C MuJoCo; see `Replay` for the options."""
    actions = np.asarray(actions, np.float64)
    if actions.ndim != 2 or actions.shape[1] != scene.N_JOINTS or len(actions) == 0:
        raise ValueError(f"actions must have shape (T, {scene.N_JOINTS}) with T >= 1, got {actions.shape}")
    sim = Replay(env, ball_offset, iterations, model, on_substep)
    for action in actions:
        sim.step(action)
    return sim.outcome()


def kick_actions(env: kick_env.KickEnv, params) -> np.ndarray:
    """A keyframe kick's actions (env.n_steps, 22) rad at the env's control step. params: (14,)."""
    return np.asarray(kick_model.keyframes_to_actions(np.asarray(params, np.float32), env.n_steps, env.config.ctrl_dt))
