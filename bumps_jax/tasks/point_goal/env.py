"""PointGoal as a functional MJX environment: a point mass on a plane reaches a goal position.

The context is the goal (x, y) in m, a vector of two numbers (`CONTEXT_SIZE = 2`): goals lie on a
disc of radius `goal_radius` (1 m) about the start; the task range (-1, 1) m bounds each of its
coordinates (the box that filtering's context grid spans). The model is a 1 kg sphere on two
slide joints (x, y) with viscous damping, pushed by one motor per joint (force = gear x action,
action in [-1, 1]); nothing collides. One episode is `episode_steps` (30) control steps of
`ctrl_dt` (0.1 s, five 0.02 s physics steps); each step pays

    reward = -|p - goal| - ctrl * sum(clip(action, -1, 1) ** 2),   p the mass's (x, y) after the step

and the episode's score is its final distance to the goal (`final_error`, m). The observation
is the mass's position and velocity (4); it holds no goal. A meta-policy sees the goal as its
context beside it (`with_context`). The final position (`final_position`, the `ACHIEVED` metric)
scores the same episode against any other goal (`error_against`).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import ml_collections
import mujoco
import numpy as np
from brax.envs.base import State

from bumps_jax.envs import base as task_env

# The model: a 1 kg sphere on slide joints x and y (damped), one motor per joint, no contacts.
XML = """
<mujoco model="point_goal">
  <option timestep="{timestep}" integrator="implicitfast"/>
  <worldbody>
    <body name="mass">
      <joint name="x" type="slide" axis="1 0 0" damping="{damping}"/>
      <joint name="y" type="slide" axis="0 1 0" damping="{damping}"/>
      <geom name="mass" type="sphere" size="0.05" mass="1" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <actuator>
    <motor joint="x" gear="{gear}" ctrlrange="-1 1" ctrllimited="true"/>
    <motor joint="y" gear="{gear}" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>
"""
MODEL_TIMESTEP = 0.02  # s: the model's own physics step
CONTEXT_SIZE = 2


def default_config() -> ml_collections.ConfigDict:
    """Every number of the task, in one place."""
    # A 0.1 s control step; the model's 0.02 s physics step; MJX's JAX backend (nothing collides).
    cfg = task_env.physics_config(ctrl_dt=0.1, impl="jax")
    cfg.episode_steps = 30  # control steps per episode (3 s)
    cfg.task_range = (-1.0, 1.0)  # m: each goal coordinate's range (the box around the disc)
    cfg.goal_radius = 1.0  # m: goals drawn by `reset` without one lie uniformly on this disc
    cfg.gear = 2.0  # N per unit of action
    cfg.damping = 1.0  # N s/m on each slide joint
    # Reset noise: position + U[-s, s] m and velocity + U[-s, s] m/s on each axis.
    cfg.reset_noise = 0.05
    cfg.reward = ml_collections.ConfigDict()
    cfg.reward.distance = 1.0  # weight of -|position - goal| (m)
    cfg.reward.ctrl = 0.01  # weight of -sum(action ** 2)
    return cfg


def make_config(config=None, overrides: dict | None = None) -> ml_collections.ConfigDict:
    """A locked copy of `config` (default: `default_config()`) with dotted `overrides`."""
    return task_env.locked_config(default_config() if config is None else config, overrides)


def validate_config(cfg: ml_collections.ConfigDict) -> None:
    """ValueError naming the first bad value of a point-goal env config."""
    task_env.validate_episode(cfg, ("episode_steps",))
    lo, hi = cfg.task_range
    if not 0 < cfg.goal_radius <= min(-lo, hi):
        raise ValueError(f"env.goal_radius must be in (0, {min(-lo, hi)}] (inside the task range), "
                         f"got {cfg.goal_radius!r}")  # fmt: skip
    for key in ("gear", "damping", "reset_noise"):
        task_env.validate_nonnegative(f"env.{key}", cfg[key])
    task_env.validate_weights(cfg.reward)


def load_model(gear: float = 2.0, damping: float = 1.0) -> mujoco.MjModel:
    """The point mass's C MuJoCo model."""
    return mujoco.MjModel.from_xml_string(XML.format(timestep=MODEL_TIMESTEP, gear=gear, damping=damping))


def noise_free(cfg: ml_collections.ConfigDict) -> dict:
    """Overrides of an env config that switch its reset noise off."""
    return {"reset_noise": 0.0}


def resolved(env_cfg) -> dict:
    """An env config as plain data with its physics step and solver iterations resolved (None:
    the model's own), as records carry it."""
    return task_env.with_model_options(env_cfg, MODEL_TIMESTEP, _model_iterations())


@functools.cache
def _model_iterations() -> int:
    return int(load_model().opt.iterations)


def disc_goals(n: int, radius: float = 1.0, seed: int = 0) -> tuple[tuple[float, float], ...]:
    """`n` goals (x, y) drawn uniformly on the disc of `radius` m, rounded to 3 decimals: a fixed
    set from `seed` (numpy's default_rng), as a config holds contexts (a tuple of tuples)."""
    rng = np.random.default_rng(seed)
    r, a = radius * np.sqrt(rng.uniform(size=n)), rng.uniform(0, 2 * np.pi, size=n)
    return tuple((round(float(x), 3), round(float(y), 3)) for x, y in zip(r * np.cos(a), r * np.sin(a), strict=True))


def n_steps_of(cfg: ml_collections.ConfigDict) -> int:
    """Control steps of one episode under env config `cfg`."""
    return int(cfg.episode_steps)


class PointGoalEnv(task_env.ContextualEnv):
    """A point mass reaches a goal (x, y) m on a disc.

    reset(rng, goal (2,)) -> State; step(state, action (2,) in [-1, 1]) -> State.
    """

    default_config = staticmethod(default_config)
    resolved = staticmethod(resolved)
    noise_free = staticmethod(noise_free)
    n_steps_of = staticmethod(n_steps_of)
    validate_config = staticmethod(validate_config)

    UNIT = "m"
    ACHIEVED = "final_position"  # (..., 2): where the mass is at the episode's end
    CONTEXT_SIZE = CONTEXT_SIZE

    def __init__(self, config=None, config_overrides: dict | None = None):
        self.config = make_config(config, config_overrides)
        validate_config(self.config)
        cfg = self.config
        self.contacts_per_episode = 1  # nothing collides; one slot keeps Warp's arithmetic whole
        self._init_physics(load_model(cfg.gear, cfg.damping))
        self.n_steps = int(cfg.episode_steps)

    # -- brax's Env interface ------------------------------------------------------------
    @property
    def observation_size(self) -> int:
        return self.mj_model.nq + self.mj_model.nv

    # -- the task --------------------------------------------------------------------------
    def reset(self, rng: jax.Array, target=None) -> State:
        """A new episode. target: the goal (2,) m; default: drawn uniformly on the goal disc.

        A concrete goal outside the task range raises ValueError. A traced one cannot raise; it
        is clipped into the range and `metrics['target_clipped']` is set to 1.
        """
        cfg = self.config
        rng_goal, rng_q, rng_v = jax.random.split(rng, 3)
        lo, hi = cfg.task_range
        if target is None:
            r = cfg.goal_radius * jnp.sqrt(jax.random.uniform(rng_goal))
            a = jax.random.uniform(jax.random.fold_in(rng_goal, 1), minval=0.0, maxval=2 * jnp.pi)
            target = jnp.stack([r * jnp.cos(a), r * jnp.sin(a)])
        elif not isinstance(target, jax.core.Tracer):
            self.check_targets(target)
        target = jnp.asarray(target, jnp.float32)
        goal = jnp.clip(target, lo, hi)
        s = cfg.reset_noise
        qpos = jax.random.uniform(rng_q, (2,), minval=-s, maxval=s)
        qvel = jax.random.uniform(rng_v, (2,), minval=-s, maxval=s)
        data, overflow = self.start_data(qpos, qvel)
        zero = jnp.zeros((), jnp.float32)
        info = {
            "target": goal,
            "step": jnp.zeros((), jnp.int32),
            "return": zero,
            "overflow": overflow,
            "truncation": zero,  # Brax's flag of an episode cut by its time limit: every episode ends so
        }
        metrics = self._metrics(data, info, zero, zero)
        metrics["target_clipped"] = jnp.any(goal != target).astype(jnp.float32)
        return State(pipeline_state=data, obs=self._observe(data), reward=zero, done=zero, metrics=metrics, info=info)

    def step(self, state: State, action: jax.Array) -> State:
        """One control step of `n_substeps` physics steps. action: (2,) in [-1, 1] (clipped)."""
        if action.shape != (self.action_size,):
            raise ValueError(f"action must have shape ({self.action_size},), got {action.shape}")
        info = dict(state.info)
        action = jnp.clip(action, -1.0, 1.0)

        data, overflow, _ = self.physics_steps(
            state.pipeline_state.replace(ctrl=action), info["overflow"], jnp.zeros((), jnp.int32)
        )
        w = self.config.reward
        reward_distance = -w.distance * jnp.linalg.norm(data.qpos - info["target"])
        reward_ctrl = -w.ctrl * jnp.sum(jnp.square(action))
        reward = reward_distance + reward_ctrl
        step = info["step"] + 1
        done = (step >= self.n_steps).astype(jnp.float32)
        info.update(step=step, overflow=overflow, truncation=done)
        info["return"] = info["return"] + reward
        metrics = self._metrics(data, info, reward_distance, reward_ctrl)
        metrics["target_clipped"] = state.metrics["target_clipped"]
        return State(pipeline_state=data, obs=self._observe(data), reward=reward, done=done, metrics=metrics, info=info)

    # -- pieces ------------------------------------------------------------------------------
    def _metrics(self, data, info, reward_distance, reward_ctrl) -> dict:
        """The step's reward terms and the episode's score so far (final at `done`)."""
        distance = jnp.linalg.norm(data.qpos - info["target"])
        return {
            "return": info["return"],
            # The pipeline's score: the distance to the goal now (m), final at the episode's end.
            "final_error": distance,
            "valid": (~info["overflow"] & jnp.isfinite(distance)).astype(jnp.float32),
            "final_position": data.qpos,  # (2,) m: scores the episode against any goal
            "reward_distance": reward_distance,
            "reward_ctrl": reward_ctrl,
            "overflow": info["overflow"].astype(jnp.float32),
        }

    def _observe(self, data) -> jax.Array:
        """The mass's position (2) and velocity (2)."""
        return jnp.concatenate([data.qpos, data.qvel])

    @property
    def context_observation_size(self) -> int:
        """What a contextual policy observes (`with_context`): the observation and the goal."""
        return self.observation_size + CONTEXT_SIZE

    def error_against(self, metrics: dict, targets) -> np.ndarray:
        """Final distances (m) to other goals (`task_env.goal_errors`)."""
        return task_env.goal_errors(metrics, targets)

    def with_context(self, obs: jax.Array, context) -> jax.Array:
        """What a contextual (meta-)policy observes: obs (..., 4) with the normalised goal
        (`normalise_context`, (..., 2) or one goal (2,) for every obs) appended: (..., 6)."""
        c = self.normalise_context(jnp.asarray(context, obs.dtype))
        c = jnp.broadcast_to(c, (*obs.shape[:-1], CONTEXT_SIZE))
        return jnp.concatenate([obs, c], axis=-1)
