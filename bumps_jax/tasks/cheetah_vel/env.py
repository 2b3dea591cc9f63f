"""HalfCheetah-Vel as a functional MJX environment: the half-cheetah runs at a target forward velocity.

The standard meta-RL benchmark (MAML, ProMP, PEARL), in PEARL's version: docs/cheetah_vel.md
cites each number. One episode is `episode_steps` (200) control steps of `ctrl_dt` (0.05 s, five
0.01 s physics steps); each step pays

    reward = -|v - target| - 0.05 * sum(clip(action, -1, 1) ** 2),   v = (x_after - x_before) / ctrl_dt

with x the torso's root slide joint. The observation is what PEARL's cheetah observes: the joint
positions but the root x (8), the joint velocities (9) and the torso's world position (3); it
holds no target. A meta-policy sees the target as its context beside it (`with_context`).

The model is Brax's half_cheetah.xml (Gym's cheetah with Brax's solver settings, and fewer floor
contacts, which `all_contacts` restores), stepped by the project's physics layer
(`physics.put_physics`: MJX-JAX or MuJoCo Warp). The target lives in the state, so one compiled
`step` serves a batch of episodes of different tasks: `jax.vmap(env.reset)(rngs, targets)`.
"""

from __future__ import annotations

import functools
import importlib.resources
import re

import jax
import jax.numpy as jnp
import ml_collections
import mujoco
import numpy as np
from brax.envs.base import State

from bumps_jax.envs import base as task_env

# The cheetah's total mass (kg): what the model's `settotalmass` sets (`load_model`).
TOTAL_MASS = 14.0
TORSO = "torso"
# The torso's forward slide joint is the model's first: qpos[0] is its x, which the observation leaves out.
ROOT_X = "rootx"
ROOT_X_QPOS = 0
# The torso's height (slide, m from its start) and pitch (hinge, rad; 0 upright) in qpos.
ROOT_Z_QPOS, ROOT_PITCH_QPOS = 1, 2
# A capsule touching the floor makes at most this many contacts (MuJoCo's capsule-plane test).
CONTACTS_PER_GEOM = 2
# Constraint rows of one contact: the pyramidal friction cone of condim 3.
ROWS_PER_CONTACT = 4
IMPLS = task_env.IMPLS


def default_config() -> ml_collections.ConfigDict:
    """Every number of the task, in one place; docs/cheetah_vel.md gives their sources."""
    cfg = ml_collections.ConfigDict()
    cfg.ctrl_dt = 0.05  # control step (s): Gym's frame_skip 5 x the model's 0.01 s
    # Physics step (s), a divisor of ctrl_dt; None: the model's own (0.01 s).
    cfg.physics_dt = ml_collections.FieldReference(None, field_type=float)
    # MJX backend that steps the physics: "warp" (MuJoCo Warp) or "jax" (MJX's JAX backend).
    cfg.impl = "warp"
    # Constraint-solver iterations; None: the model's own (Brax's 4; Gym's model: MuJoCo's 100).
    cfg.solver_iterations = ml_collections.FieldReference(None, field_type=int)
    # Warp only: contact slots of one physics call, shared by all its episodes; a call of more
    # episodes than fit (`max_episodes`) runs in chunks. Sized here for 4096 episodes at the
    # most contacts one episode can make (2 per colliding capsule).
    cfg.warp_contacts = CONTACTS_PER_GEOM * 8 * 4096
    # Warp only: constraint rows per episode: 4 per contact (2 x 8 capsules) + 6 joint limits.
    cfg.warp_constraints_per_world = ROWS_PER_CONTACT * CONTACTS_PER_GEOM * 8 + 6
    cfg.episode_steps = 200  # control steps per episode (10 s): MAML's and PEARL's horizon
    cfg.task_range = (0.0, 3.0)  # target velocities (m/s): PEARL's and ProMP's U[0, 3]
    # True: every body capsule collides with the floor, as in Gym's model that MAML, ProMP and
    # PEARL load. False: Brax's model as it is, whose torso and shins pass through the floor.
    cfg.all_contacts = True
    # True: the observation ends with the torso's world position (PEARL, MAML: 20 numbers), whose
    # x grows without bound over an episode. False: joint positions and velocities only (Gym's
    # HalfCheetah, ProMP: 17 numbers).
    cfg.torso_position = False
    # Reset noise: joint positions + U[-s, s], joint velocities + s * N(0, 1) (Gym's 0.1).
    cfg.reset_noise = 0.1
    cfg.reward = ml_collections.ConfigDict()
    cfg.reward.velocity = 1.0  # weight of -|forward velocity - target| (m/s)
    cfg.reward.ctrl = 0.05  # weight of -sum(action ** 2): the sources' 0.5 * 0.1
    return cfg


def make_config(config=None, overrides: dict | None = None) -> ml_collections.ConfigDict:
    """A locked copy of `config` (default: `default_config()`) with dotted `overrides`.

    Unknown keys raise at once, naming the key.
    """
    return task_env.locked_config(default_config() if config is None else config, overrides)


def validate_config(cfg: ml_collections.ConfigDict) -> None:
    """ValueError naming the first bad value of a cheetah env config."""
    task_env.validate_episode(cfg, ("episode_steps",))
    task_env.validate_nonnegative("env.reset_noise", cfg.reset_noise)
    task_env.validate_weights(cfg.reward)


def load_model(all_contacts: bool = True) -> mujoco.MjModel:
    """Brax's half-cheetah (C MuJoCo model); with `all_contacts` every body capsule collides
    with the floor, as in Gym's model.

    The file's deprecated `settotalmass="14"` is applied as a density scale instead (the same
    masses, inertias and model statistics), so that compiling it writes no warning and no log file.
    The contacts are set before compiling: the compiler derives per-body collision masks from the
    geoms' (`body_contype`), which C MuJoCo's broad phase reads.
    """
    xml = (importlib.resources.files("brax") / "envs/assets/half_cheetah.xml").read_text()
    spec = mujoco.MjSpec.from_string(re.sub(r'\s*settotalmass="[^"]*"', "", xml))
    scale = TOTAL_MASS / float(spec.compile().body_mass.sum())
    for geom in spec.geoms:
        geom.density *= scale
    if all_contacts:
        for body in spec.bodies[1:]:  # every body but the world (the floor)
            for geom in body.geoms:
                geom.contype = 1
    return spec.compile()


def colliding_geoms(model: mujoco.MjModel) -> int:
    """Body geoms that can touch the floor (the floor's conaffinity meets their contype)."""
    return int(np.sum((model.geom_bodyid > 0) & (model.geom_contype > 0)))


def check_targets(targets, task_range) -> np.ndarray:
    """Targets as a float array, or ValueError naming the first one outside `task_range`."""
    return task_env.check_targets(targets, task_range, "m/s")


def noise_free(cfg: ml_collections.ConfigDict) -> dict:
    """Overrides of an env config that switch its reset noise off."""
    return {"reset_noise": 0.0}


@functools.lru_cache(maxsize=4)
def contacts_per_episode(all_contacts: bool = True) -> int:
    """The most floor contacts one episode makes: 2 per colliding capsule (16 with `all_contacts`)."""
    return CONTACTS_PER_GEOM * colliding_geoms(load_model(all_contacts))


@functools.lru_cache(maxsize=4)
def _model_options(all_contacts: bool) -> tuple[float, int]:
    """The model's own (physics step (s), solver iterations)."""
    model = load_model(all_contacts)
    return float(model.opt.timestep), int(model.opt.iterations)


def resolved(env_cfg) -> dict:
    """A cheetah env config as plain data with its physics step and solver iterations resolved
    (None: the model's own), as records carry it."""
    return task_env.with_model_options(env_cfg, *_model_options(bool(env_cfg.get("all_contacts", True))))


def _reward_velocity(forward_vel: jax.Array, target: jax.Array) -> jax.Array:
    """-|forward velocity - target| (m/s), ()."""
    return -jnp.abs(forward_vel - target)


def _reward_ctrl(action: jax.Array) -> jax.Array:
    """-sum(action ** 2) of the clipped action (6,), ()."""
    return -jnp.sum(jnp.square(action))


def n_steps_of(cfg: ml_collections.ConfigDict) -> int:
    """Control steps of one episode under env config `cfg`."""
    return int(cfg.episode_steps)


class CheetahVelEnv(task_env.ContextualEnv):
    """The half-cheetah runs at a target forward velocity (m/s).

    reset(rng, target) -> State; step(state, action) -> State. `action` (6,): motor commands in
    [-1, 1] (clipped; each motor's gear turns it into a torque), the order of the model's actuators
    (bthigh, bshin, bfoot, fthigh, fshin, ffoot).
    """

    default_config = staticmethod(default_config)
    resolved = staticmethod(resolved)
    noise_free = staticmethod(noise_free)
    n_steps_of = staticmethod(n_steps_of)
    validate_config = staticmethod(validate_config)

    UNIT = "m/s"
    ACHIEVED = "mean_forward_vel"
    ACTION_BOUND = 1.0  # every motor's ctrlrange

    def __init__(self, config=None, config_overrides: dict | None = None):
        self.config = make_config(config, config_overrides)
        validate_config(self.config)
        cfg = self.config
        mj_model = load_model(cfg.all_contacts)
        self.contacts_per_episode = CONTACTS_PER_GEOM * colliding_geoms(mj_model)
        self._init_physics(mj_model)
        self.n_steps = int(cfg.episode_steps)
        self.torso_body = mujoco.mj_name2id(self.mj_model, mujoco.mjtObj.mjOBJ_BODY, TORSO)
        root_x = mujoco.mj_name2id(self.mj_model, mujoco.mjtObj.mjOBJ_JOINT, ROOT_X)
        if self.mj_model.jnt_qposadr[root_x] != ROOT_X_QPOS:
            raise ValueError(f"the model's {ROOT_X!r} joint is not its first coordinate")
        self._ctrl_lo = jnp.asarray(self.mj_model.actuator_ctrlrange[:, 0], jnp.float32)
        self._ctrl_hi = jnp.asarray(self.mj_model.actuator_ctrlrange[:, 1], jnp.float32)

    # -- brax's Env interface ------------------------------------------------------------
    @property
    def observation_size(self) -> int:
        return self.mj_model.nq - 1 + self.mj_model.nv + (3 if self.config.torso_position else 0)

    # -- the task --------------------------------------------------------------------------
    def reset(self, rng: jax.Array, target=None) -> State:
        """A new episode. target: scalar m/s; default: drawn from U[task_range].

        A concrete target outside `task_range` raises ValueError. A traced one cannot raise;
        it is clipped into the range and `metrics['target_clipped']` is set to 1.
        """
        cfg = self.config
        rng_task, rng_q, rng_v = jax.random.split(rng, 3)
        lo, hi = cfg.task_range
        if target is None:
            target = jax.random.uniform(rng_task, (), minval=lo, maxval=hi)
        elif not isinstance(target, jax.core.Tracer):
            check_targets(target, cfg.task_range)
        target = jnp.asarray(target, dtype=jnp.float32)
        clipped_target = jnp.clip(target, lo, hi)

        data, overflow = self.gym_start(rng_q, rng_v)
        zero = jnp.zeros((), jnp.float32)
        info = {
            "target": clipped_target,
            "step": jnp.zeros((), jnp.int32),
            "return": zero,  # sum of the rewards so far
            "vel_error_sum": zero,  # sum of |forward velocity - target| so far (m/s)
            # Each control step's forward velocity (m/s), 0 for steps not taken yet: scores the
            # episode against any other target (`error_against`, policy filtering).
            "forward_vels": jnp.zeros((self.n_steps,), jnp.float32),
            "overflow": overflow,
            "solver_limit_steps": jnp.zeros((), jnp.int32),
            # Brax's flag of an episode cut by its time limit: every episode ends so.
            "truncation": zero,
        }
        metrics = self._metrics(data, info, zero, zero, zero)
        metrics["target_clipped"] = (clipped_target != target).astype(jnp.float32)
        return State(pipeline_state=data, obs=self._observe(data), reward=zero, done=zero, metrics=metrics, info=info)

    def step(self, state: State, action: jax.Array) -> State:
        """One control step of `n_substeps` physics steps. action: (6,) in [-1, 1] (clipped)."""
        if action.shape != (self.action_size,):
            raise ValueError(f"action must have shape ({self.action_size},), got {action.shape}")
        info = dict(state.info)
        action = jnp.clip(action, self._ctrl_lo, self._ctrl_hi)

        before = state.pipeline_state
        data, overflow, limit_steps = self.physics_steps(
            before.replace(ctrl=action), info["overflow"], info["solver_limit_steps"]
        )

        forward_vel = (data.qpos[ROOT_X_QPOS] - before.qpos[ROOT_X_QPOS]) / self.config.ctrl_dt
        w = self.config.reward
        reward_velocity = w.velocity * _reward_velocity(forward_vel, info["target"])
        reward_ctrl = w.ctrl * _reward_ctrl(action)
        reward = reward_velocity + reward_ctrl
        step = info["step"] + 1
        done = (step >= self.n_steps).astype(jnp.float32)
        info.update(
            step=step,
            overflow=overflow,
            solver_limit_steps=limit_steps,
            truncation=done,
            vel_error_sum=info["vel_error_sum"] + jnp.abs(forward_vel - info["target"]),
            forward_vels=info["forward_vels"].at[jnp.minimum(info["step"], self.n_steps - 1)].set(forward_vel),
        )
        info["return"] = info["return"] + reward
        metrics = self._metrics(data, info, forward_vel, reward_velocity, reward_ctrl)
        metrics["target_clipped"] = state.metrics["target_clipped"]
        return State(pipeline_state=data, obs=self._observe(data), reward=reward, done=done, metrics=metrics, info=info)

    # -- pieces ------------------------------------------------------------------------------
    def _metrics(self, data, info, forward_vel, reward_velocity, reward_ctrl) -> dict:
        """The step's velocity and reward terms, and the episode's score so far (final at `done`)."""
        steps = jnp.maximum(info["step"], 1).astype(jnp.float32)
        mean_vel_error = info["vel_error_sum"] / steps
        return {
            # The episode's score: its return, and its mean |forward velocity - target| (m/s).
            "return": info["return"],
            "mean_vel_error": mean_vel_error,
            # The pipeline's score of a contextual task (task_env): the error against the target
            # (here the mean velocity error, m/s) and whether the episode counts (no overflow).
            "final_error": mean_vel_error,
            "valid": (~info["overflow"] & jnp.isfinite(mean_vel_error)).astype(jnp.float32),
            "mean_forward_vel": jnp.sum(info["forward_vels"]) / steps,  # m/s over the steps so far
            "forward_vels": info["forward_vels"],
            "forward_vel": forward_vel,  # this step's (m/s)
            "vel_error": jnp.abs(forward_vel - info["target"]) * (info["step"] > 0),
            # This step's reward terms, weighted: reward = reward_velocity + reward_ctrl.
            "reward_velocity": reward_velocity,
            "reward_ctrl": reward_ctrl,
            "x_position": data.qpos[ROOT_X_QPOS],
            # 1 when a Warp contact or constraint buffer overflowed: the physics dropped contacts.
            "overflow": info["overflow"].astype(jnp.float32),
            # Physics steps whose solver stopped at its iteration limit (Warp only; MJX-JAX: 0).
            "solver_limit_steps": info["solver_limit_steps"].astype(jnp.float32),
        }

    def _observe(self, data) -> jax.Array:
        """qpos without the root x (8), qvel (9), and with `torso_position` the torso's world
        position (3), as MuJoCo leaves it after a step: computed before the last physics step's
        integration, as Gym's `get_body_com` reads it."""
        parts = [data.qpos[1:], data.qvel]
        if self.config.torso_position:
            parts.append(data.xpos[self.torso_body])
        return jnp.concatenate(parts)

    def posture(self, qpos: np.ndarray) -> dict:
        """The torso's posture over episodes' steps, qpos (..., T, nq) -> {name: (...)}: its mean
        pitch (rad, 0 upright; beyond +-pi/2 on its back), the fraction of steps it spends on its
        back (|pitch| > pi/2), and its mean height (m, from its start)."""
        pitch = np.asarray(qpos, np.float64)[..., ROOT_PITCH_QPOS]
        return {
            "pitch_rad": pitch.mean(axis=-1),
            "flipped_fraction": (np.abs(pitch) > np.pi / 2).mean(axis=-1),
            "height_m": np.asarray(qpos, np.float64)[..., ROOT_Z_QPOS].mean(axis=-1),
        }

    @property
    def context_observation_size(self) -> int:
        """Size of what a contextual policy observes (`with_context`): the observation and its context."""
        return self.observation_size + 1

    def error_against(self, metrics: dict, targets) -> np.ndarray:
        """Mean velocity errors (m/s) of finished episodes against other targets (m/s), from their
        per-step velocities (`forward_vels` (..., n_steps)): shape of the metrics' episodes
        broadcast with `targets`, e.g. (C, R) episodes and targets (T, 1, 1) -> (T, C, R)."""
        vels = np.asarray(metrics["forward_vels"], np.float64)
        targets = np.asarray(targets, np.float64)[..., None]
        err = np.abs(vels - targets).mean(axis=-1)
        return np.where(np.asarray(metrics["valid"]) > 0, err, np.inf)

    def with_context(self, obs: jax.Array, context) -> jax.Array:
        """What a contextual (meta-)policy observes: obs (..., obs_size) with the normalised
        context (m/s) appended, (..., obs_size + 1). The env's own observation holds no target."""
        c = jnp.broadcast_to(self.normalise_context(jnp.asarray(context, obs.dtype)), obs.shape[:-1])
        return jnp.concatenate([obs, c[..., None]], axis=-1)
