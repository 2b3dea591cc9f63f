"""The kick task as a functional MJX environment: the NAO kicks a ball to a target distance.

One episode = a kick phase of `horizon_s` seconds at 50 Hz, after which the ball rolls to
rest. The rolling tail is not simulated step by step (a kicked ball rolls for 20-40 s): the
resting point follows from the ball's state at the end of the kick phase in closed form
(`rest_point`), which a test checks against the full simulation.

The target distance lives in the state, so one compiled `step` serves a batch of episodes of
different tasks: `jax.vmap(env.reset)(rngs, targets)`.
"""

from __future__ import annotations

import functools
import json

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from brax.envs.base import State
from mujoco import mjx

from bumps_jax.envs import base as task_env
from bumps_jax.envs import physics
from bumps_jax.envs.physics import read_flags, servo_ramp
from bumps_jax.tasks.kick import scene
from bumps_jax.tasks.kick.ball import rest_point, rolling


def meta_train_tasks() -> tuple[float, ...]:
    """The paper's 23 meta-training targets: 7.0, 7.5, ..., 18.0 m."""
    return tuple(round(7.0 + 0.5 * i, 1) for i in range(23))


def meta_test_tasks() -> tuple[float, ...]:
    """The paper's 110 meta-test targets: 7.1, 7.2, ..., 18.0 m."""
    return tuple(round(7.1 + 0.1 * i, 1) for i in range(110))


# The most contacts one episode makes: box-floor 4 per foot, 1 per sphere pair of the six pairs.
CONTACTS_PER_EPISODE = 12


def default_config() -> ml_collections.ConfigDict:
    """Every number of the task, in one place. See README of assets/nao_mjcf for the scene."""
    cfg = ml_collections.ConfigDict()
    cfg.ctrl_dt = 0.02  # 50 Hz, SimSpark's agent cycle
    # Physics step (s), a divisor of ctrl_dt; None: the scene's own (2.5 ms).
    cfg.physics_dt = ml_collections.FieldReference(None, field_type=float)
    # MJX backend that steps the physics: "warp" (MuJoCo Warp: C MuJoCo's physics, on a GPU or
    # the CPU) or "jax" (MJX's JAX backend: an approximation, see benchmarks/results/engines.json).
    cfg.impl = "warp"
    # Constraint-solver iterations; None: the scene's own (2, not converged). 4: converged for
    # our kicks (the engines check).
    cfg.solver_iterations = ml_collections.FieldReference(4, field_type=int)
    # Warp only: contact slots of one physics call, shared by all its episodes (Warp pools them
    # over the vmapped episodes). The scene's six contact pairs make at most CONTACTS_PER_EPISODE
    # per episode: this fits 6144 episodes (the experts' 23 x 256). Rollouts of more episodes run
    # in chunks (`rollout.in_chunks`); a training program that needs more is refused before it
    # compiles; a call that still runs out marks its episodes invalid (`metrics['overflow']`).
    # Unused slots cost time every step (14 % of the experts' speed at 12 x 16384 on a GPU).
    cfg.warp_contacts = CONTACTS_PER_EPISODE * 6144
    # Warp only: constraint rows per episode: 4 per contact (pyramidal cone, condim 3) x 12.
    cfg.warp_constraints_per_world = 48
    cfg.horizon_s = 1.5  # kick phase; the paper's kicks last 1.3-1.5 s
    cfg.task_range = (7.0, 18.0)  # metres; targets outside are refused
    cfg.tasks = meta_train_tasks()  # what brax-style `reset(rng)` draws from
    cfg.ball_offset = 0.2  # ball centre ahead of the kicking foot's centre (m)
    cfg.proprioception = False  # paper-faithful observation: (phase, target) only
    cfg.fall_height = 0.22  # torso centre below this (m) = fallen; standing is 0.37
    cfg.strike_speed = 0.5  # the ball must reach this speed (m/s) for a valid kick
    cfg.blowup_speed = 100.0  # any qvel above this (or NaN) = physics blow-up
    cfg.noise = ml_collections.ConfigDict()
    cfg.noise.ball_xy = 0.01  # uniform +- (m) on the ball's start
    cfg.noise.joint_angle = 0.01  # normal std (rad) on the initial joint angles
    cfg.noise.friction = 0.1  # uniform +- (relative) on every contact's friction
    cfg.noise.actuator_gain = 0.05  # uniform +- (relative) on the servo gains
    cfg.reward = ml_collections.ConfigDict()
    # The paper's per-step reward: the ball-target distance, scaled (paper: x 0.1).
    cfg.reward.distance = 0.1
    # Weight of the final resting error, paid at the last step: makes the return's maximum
    # the kick that stops on the target, not the one that gets near it fastest.
    cfg.reward.final_error = 10.0
    return cfg


def make_config(config=None, overrides: dict | None = None) -> ml_collections.ConfigDict:
    """A locked copy of `config` (default: `default_config()`) with dotted `overrides`.

    Unknown keys raise at once, naming the key.
    """
    return task_env.locked_config(default_config() if config is None else config, overrides)


IMPLS = task_env.IMPLS


def resolved(env_cfg) -> dict:
    """An env config as plain data with its physics step and solver iterations resolved (None:
    the scene's own), as records carry it; a record older than the backend keys reads as MJX-JAX."""
    d = task_env.with_model_options(env_cfg, scene.default_timestep(), _scene_iterations())
    # A record from before the backend keys existed was made on MJX-JAX at the scene's iterations.
    d.setdefault("impl", "jax")
    defaults = default_config()
    for key in ("warp_contacts", "warp_constraints_per_world"):
        d.setdefault(key, defaults[key])
    return json.loads(json.dumps(d, default=list))


@functools.lru_cache(maxsize=1)
def _scene_iterations() -> int:
    return int(scene.load_model().opt.iterations)


def validate_config(cfg: ml_collections.ConfigDict) -> None:
    """ValueError naming the first bad value of an env config."""
    task_env.validate_physics(cfg)
    if len(cfg.task_range) != 2:
        raise ValueError(f"env.task_range must be (low, high), got {tuple(cfg.task_range)}")
    lo, hi = cfg.task_range
    if not 0.0 < lo < hi:
        raise ValueError(f"env.task_range must be 0 < low < high, got {tuple(cfg.task_range)}")
    task_env.validate_physics_dt(cfg)
    if cfg.ctrl_dt <= 0 or cfg.horizon_s < cfg.ctrl_dt:
        raise ValueError(f"need 0 < env.ctrl_dt <= env.horizon_s, got {cfg.ctrl_dt}, {cfg.horizon_s}")
    if len(cfg.tasks) == 0:
        raise ValueError("env.tasks is empty: give at least one target distance")
    try:
        check_targets(cfg.tasks, cfg.task_range)
    except ValueError as err:
        raise ValueError(f"env.tasks: {err}") from None
    for name, value in cfg.noise.items():
        if value < 0:
            raise ValueError(f"env.noise.{name} must be >= 0, got {value}")


def noise_free(cfg: ml_collections.ConfigDict) -> dict:
    """Overrides of an env config that switch its noise off (the experts' recording, the paper's)."""
    return {f"noise.{name}": 0.0 for name in cfg.noise}


def check_targets(targets, task_range) -> np.ndarray:
    """Targets as a float array, or ValueError naming the first one outside `task_range`."""
    return task_env.check_targets(targets, task_range, "m")


def n_steps_of(cfg: ml_collections.ConfigDict) -> int:
    """Control steps of one episode under env config `cfg`."""
    return int(round(cfg.horizon_s / cfg.ctrl_dt))


class KickEnv(task_env.ContextualEnv):
    """The NAO kicks a ball to a target distance.

    reset(rng, target) -> State; step(state, action) -> State. `action` (22,) holds absolute
    joint target angles (rad) in SimSpark order; they are clipped to the joint limits, and the
    servo target moves toward them no faster than SimSpark's 6.1395 rad/s.
    """

    default_config = staticmethod(default_config)
    resolved = staticmethod(resolved)
    noise_free = staticmethod(noise_free)
    n_steps_of = staticmethod(n_steps_of)
    validate_config = staticmethod(validate_config)
    ACHIEVED = "distance"  # (...,): the ball's resting distance from the kick spot

    def __init__(self, config=None, config_overrides: dict | None = None):
        self.config = make_config(config, config_overrides)
        validate_config(self.config)
        cfg = self.config
        self.contacts_per_episode = CONTACTS_PER_EPISODE
        self._init_physics(scene.load_model())
        self.ids = scene.scene_ids(self.mj_model)
        self.n_steps = int(round(cfg.horizon_s / cfg.ctrl_dt))
        self.decel_rate = scene.rolling_decel_rate(timestep=cfg.physics_dt)
        self._qpos0 = jnp.asarray(scene.stance_qpos(self.mj_model))
        self._stance = jnp.asarray(scene.STANCE)
        self._lo = jnp.asarray(self.ids.joint_range[:, 0])
        self._hi = jnp.asarray(self.ids.joint_range[:, 1])
        self._max_delta = scene.MAX_JOINT_SPEED * cfg.ctrl_dt
        self._tasks = jnp.asarray(cfg.tasks, dtype=jnp.float32)

    # -- brax's Env interface ------------------------------------------------------------
    @property
    def observation_size(self) -> int:
        return 2 + (50 if self.config.proprioception else 0)

    @property
    def action_size(self) -> int:
        return scene.N_JOINTS

    # -- the task --------------------------------------------------------------------------
    def reset(self, rng: jax.Array, target=None) -> State:
        """A new episode. target: scalar metres; default: drawn from `config.tasks`.

        A concrete target outside `task_range` raises ValueError. A traced one cannot raise;
        it is clipped into the range and `metrics['target_clipped']` is set to 1.
        """
        cfg = self.config
        rng_task, rng_ball, rng_q, rng_f, rng_g = jax.random.split(rng, 5)
        if target is None:
            target = jax.random.choice(rng_task, self._tasks)
        elif not isinstance(target, jax.core.Tracer):
            check_targets(target, cfg.task_range)
        target = jnp.asarray(target, dtype=jnp.float32)
        lo, hi = cfg.task_range
        clipped_target = jnp.clip(target, lo, hi)

        qpos = self._qpos0
        jitter = cfg.noise.ball_xy * jax.random.uniform(rng_ball, (2,), minval=-1.0, maxval=1.0)
        ball_xy = qpos[self.ids.ball_qpos : self.ids.ball_qpos + 2]
        qpos = qpos.at[self.ids.ball_qpos : self.ids.ball_qpos + 2].add(jitter)
        joint_noise = cfg.noise.joint_angle * jax.random.normal(rng_q, (scene.N_JOINTS,))
        qpos = qpos.at[self.ids.joint_qpos].set(jnp.clip(self._stance + joint_noise, self._lo, self._hi))

        blank = physics.blank_data(self.mjx_model, self._warp_data)
        data = blank.replace(qpos=qpos, ctrl=self._stance)
        info = {
            "target": clipped_target,
            # The target point: `target` metres ahead of the nominal ball start.
            "target_xy": ball_xy + jnp.array([1.0, 0.0]) * clipped_target,
            "step": jnp.zeros((), jnp.int32),
            "command": self._stance,
            "friction_scale": 1.0 + cfg.noise.friction * jax.random.uniform(rng_f, (), minval=-1.0, maxval=1.0),
            "gain_scale": 1.0 + cfg.noise.actuator_gain * jax.random.uniform(rng_g, (), minval=-1.0, maxval=1.0),
            "max_ball_speed": jnp.zeros(()),
            # Strongly typed, as step returns it: a weak leaf would make a jitted step compile twice.
            "min_torso_z": jnp.full((), jnp.inf, jnp.float32),
            "blown_up": jnp.zeros((), bool),
            "nan_action": jnp.zeros((), bool),
            "overflow": jnp.zeros((), bool),
            "solver_limit_steps": jnp.zeros((), jnp.int32),
        }
        data, overflow, _ = read_flags(mjx.forward(self._episode_model(info), data))
        info["overflow"] = overflow
        metrics = self._outcome(data, info)
        metrics["target_clipped"] = (clipped_target != target).astype(jnp.float32)
        return State(
            pipeline_state=data,
            obs=self._observe(data, info),
            reward=jnp.zeros(()),
            done=jnp.zeros(()),
            metrics=metrics,
            info=info,
        )

    def step(self, state: State, action: jax.Array) -> State:
        """One 20 ms control step. action: (22,) joint targets (rad).

        A NaN in the action holds the previous servo target for that joint and marks the
        episode as an invalid kick (`metrics['valid'] = 0`).
        """
        if action.shape[-1:] != (scene.N_JOINTS,) or action.ndim != 1:
            raise ValueError(f"action must have shape ({scene.N_JOINTS},), got {action.shape}")
        info = dict(state.info)
        nan = jnp.isnan(action)
        wanted = jnp.where(nan, info["command"], action)
        ramp = servo_ramp(info["command"], wanted, self._lo, self._hi, self._max_delta, self.n_substeps)
        command = ramp[-1]
        model = self._episode_model(info)

        def substep(carry, ctrl):
            data, overflow, limit_steps = carry
            data, overflowed, hit_limit = read_flags(mjx.step(model, data.replace(ctrl=ctrl)))
            return (data, overflow | overflowed, limit_steps + hit_limit.astype(jnp.int32)), None

        carry = (state.pipeline_state, info["overflow"], info["solver_limit_steps"])
        (data, overflow, limit_steps), _ = jax.lax.scan(substep, carry, ramp)

        ball_vel = data.qvel[self.ids.ball_qvel : self.ids.ball_qvel + 3]
        finite = jnp.all(jnp.isfinite(data.qpos)) & jnp.all(jnp.isfinite(data.qvel))
        blown_up = info["blown_up"] | ~finite | (jnp.max(jnp.abs(jnp.nan_to_num(data.qvel))) > self.config.blowup_speed)
        info.update(
            step=info["step"] + 1,
            command=command,
            max_ball_speed=jnp.maximum(info["max_ball_speed"], jnp.linalg.norm(ball_vel)),
            min_torso_z=jnp.minimum(info["min_torso_z"], data.xpos[self.ids.torso_body, 2]),
            blown_up=blown_up,
            nan_action=info["nan_action"] | jnp.any(nan),
            overflow=overflow,
            solver_limit_steps=limit_steps,
        )
        done = info["step"] >= self.n_steps
        metrics = self._outcome(data, info)
        metrics["target_clipped"] = state.metrics["target_clipped"]
        reward = self._reward(data, info, metrics, done)
        return State(
            pipeline_state=data,
            obs=self._observe(data, info),
            reward=reward,
            done=done.astype(jnp.float32),
            metrics=metrics,
            info=info,
        )

    # -- pieces ------------------------------------------------------------------------------
    def _episode_model(self, info) -> mjx.Model:
        """The MJX model with this episode's friction and servo-gain jitter applied."""
        m = self.mjx_model
        kp_scale = jnp.ones_like(m.actuator_gainprm).at[:, 0].set(info["gain_scale"])
        bias_scale = jnp.ones_like(m.actuator_biasprm).at[:, 1].set(info["gain_scale"])
        return m.replace(
            pair_friction=m.pair_friction * info["friction_scale"],
            actuator_gainprm=m.actuator_gainprm * kp_scale,
            actuator_biasprm=m.actuator_biasprm * bias_scale,
        )

    def _ball_state(self, data):
        q, v = self.ids.ball_qpos, self.ids.ball_qvel
        pos = data.qpos[q : q + 3]
        # MuJoCo's free-joint angular velocity is in the body frame: rotate it to the world.
        quat = data.qpos[q + 3 : q + 7]
        angvel = physics.rotate(data.qvel[v + 3 : v + 6], quat)
        return pos, data.qvel[v : v + 3], angvel

    def _outcome(self, data, info) -> dict:
        """What the kick would score if the kick phase ended now (final at `done`)."""
        cfg = self.config
        pos, vel, angvel = self._ball_state(data)
        rest = rest_point(pos, vel, angvel, self.decel_rate)
        error = jnp.linalg.norm(rest - info["target_xy"])
        # A blown-up simulation scores as a ball that never moved: error = the target distance.
        error = jnp.where(info["blown_up"], info["target"], jnp.nan_to_num(error, nan=info["target"]))
        struck = info["max_ball_speed"] >= cfg.strike_speed
        fallen = info["min_torso_z"] < cfg.fall_height
        valid = struck & ~fallen & ~info["blown_up"] & ~info["nan_action"] & ~info["overflow"]
        return {
            "final_error": error,
            "rel_error": error / info["target"],
            # Where the ball rests relative to its nominal start: along the kick line (m) and to
            # its left (m); `error_against` scores them against any target.
            "distance": jnp.nan_to_num(rest[0]) - (info["target_xy"][0] - info["target"]),
            "lateral": jnp.nan_to_num(rest[1]) - info["target_xy"][1],
            "valid": valid.astype(jnp.float32),
            "struck": struck.astype(jnp.float32),
            "fallen": fallen.astype(jnp.float32),
            "blown_up": info["blown_up"].astype(jnp.float32),
            # 1 when the ball rolls: then the resting point is exact, not an approximation.
            "ball_rolling": rolling(vel, angvel).astype(jnp.float32),
            # 1 when a Warp contact or constraint buffer overflowed: the physics dropped
            # contacts, so the episode is invalid (`config.warp_contacts`).
            "overflow": info["overflow"].astype(jnp.float32),
            # Physics steps whose solver stopped at its iteration limit unconverged (Warp only:
            # MJX-JAX does not report it, 0).
            "solver_limit_steps": info["solver_limit_steps"].astype(jnp.float32),
            "rest_x": jnp.nan_to_num(rest[0]),
            "rest_y": jnp.nan_to_num(rest[1]),
        }

    def with_context(self, obs: jax.Array, context) -> jax.Array:
        """The observation (obs_size,) with its context replaced by `context` (m): a policy asked
        for another distance than the task the env scores (policy filtering)."""
        return obs.at[1].set(self.normalise_context(context))

    def error_against(self, metrics: dict, targets) -> np.ndarray:
        """Final errors (m) of finished kicks against other targets (m): the module's
        `error_against` of their resting points (`distance`, `lateral`, `blown_up`)."""
        return error_against(metrics["distance"], metrics["lateral"], metrics["blown_up"], targets)

    def _reward(self, data, info, metrics, done) -> jax.Array:
        """Paper's per-step term: -scale * |ball - target|; at the end, -w * final error."""
        w = self.config.reward
        ball_xy = data.qpos[self.ids.ball_qpos : self.ids.ball_qpos + 2]
        distance = jnp.linalg.norm(ball_xy - info["target_xy"])
        distance = jnp.where(info["blown_up"], info["target"], jnp.nan_to_num(distance, nan=info["target"]))
        return -w.distance * distance - jnp.where(done, w.final_error * metrics["final_error"], 0.0)

    def _observe(self, data, info) -> jax.Array:
        phase = info["step"].astype(jnp.float32) / self.n_steps
        context = self.normalise_context(info["target"])
        obs = jnp.stack([phase, context])
        if not self.config.proprioception:
            return obs
        torso_quat = data.qpos[3:7]
        gravity = physics.rotate(jnp.array([0.0, 0.0, -1.0]), physics.conjugate(torso_quat))
        ball_rel = data.qpos[self.ids.ball_qpos : self.ids.ball_qpos + 3] - data.qpos[:3]
        extra = jnp.concatenate([
            data.qpos[self.ids.joint_qpos],
            0.1 * data.qvel[self.ids.joint_qvel],
            gravity,
            ball_rel,
        ])  # fmt: skip
        return jnp.nan_to_num(jnp.concatenate([obs, extra]))


def error_against(distance, lateral, blown_up, targets):
    """The env's final error of kicks that rest at (distance, lateral) (..., as in the metrics)
    against other targets (m): broadcasts, e.g. distance (C, R) with targets (T, 1, 1) -> (T, C, R).
    A blown-up episode scores the target distance, as the env scores it."""
    err = np.hypot(np.asarray(distance, np.float64) - targets, np.asarray(lateral, np.float64))
    return np.where(np.asarray(blown_up) > 0, np.broadcast_to(targets, err.shape), err)
