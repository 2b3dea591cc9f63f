"""Ant-Goal as a functional MJX environment: the ant walks its torso to a goal position (x, y).

The meta-RL benchmark of ProMP (Rothfuss et al., 2019) and PEARL (Rakelly et al., 2019), in
PEARL's version (`AntGoalEnv`, which copies ProMP's `AntRandGoalEnv`); docs/ant_goal.md cites each
number. Goals lie on a disc of radius `goal_radius` (3 m) about the start: angle U[0, 2 pi),
radius 3 sqrt(U[0, 1]), uniform over the disc. One episode is `episode_steps` (200) control steps
of `ctrl_dt` (0.05 s, five 0.01 s physics steps), never ended early; each step pays

    reward = -|p - goal|_1 - 0.1 * sum(a ** 2) - 0.5e-3 * sum(clip(cfrc_ext, -1, 1) ** 2) + 0

with p the torso's (x, y) after the step (MuJoCo's body position as a step leaves it, PEARL's
`get_body_com("torso")`), `a` the action clipped to the motors' [-1, 1], `cfrc_ext` the
external (contact) wrench on every body (14 x 6) and a survive reward of 0 (PEARL's, ProMP's).
MJX steps do not compute `cfrc_ext` (nor does C MuJoCo since 2.0: PEARL's MuJoCo 1.50 did on
every step); the env computes it after each control step's last physics step with the backends'
own `rne_postconstraint` (MJX-JAX: `mjx.rne_postconstraint`; Warp: its `run_rne_postconstraint`
option), as C MuJoCo's `mj_rnePostConstraint` does, and only when its weight is not 0.

The pipeline's score of an episode (`final_error`) is the Euclidean distance (m) of the torso's
final (x, y) to the goal; PEARL and ProMP score returns. The final position (`final_position`, the
`ACHIEVED` metric) scores the same episode against any other goal (`error_against`).

The observation is the joint positions (`qpos`, 15: the torso's position, its quaternion and the
8 joint angles) and velocities (`qvel`, 14), 29 numbers, as PEARL's and ProMP's but without their
84 clipped contact forces; with `torso_xy=False`, Gym's ant's 27 (`qpos[2:]`, `qvel`), which
leaves out where the torso is and with it how far the goal is. It holds no goal: a meta-policy
sees the goal as its context beside it (`with_context`).

The model is Brax's ant.xml (Gym's ant with Brax's solver settings and contacts on the feet only;
`all_contacts` restores Gym's: every body geom on the floor), stepped by the project's physics
layer (`physics.put_physics`: MJX-JAX or MuJoCo Warp). The goal lives in the state, so one compiled
`step` serves a batch of episodes of different goals: `jax.vmap(env.reset)(rngs, goals)`.
"""

from __future__ import annotations

import functools
import importlib.resources

import jax
import jax.numpy as jnp
import ml_collections
import mujoco
import numpy as np
from brax.envs.base import State
from mujoco import mjx

from bumps_jax.envs import base as task_env

TORSO = "torso"
# The torso's free joint is the model's first: qpos[0:3] its position, qpos[3:7] its quaternion (w, x, y, z).
ROOT = "root"
ROOT_Z_QPOS, ROOT_QUAT_QPOS = 2, slice(3, 7)
CONTEXT_SIZE = 2
# Brax's foot spheres: its only colliding geoms, inside the ends of the ankle capsules; Gym's model has none.
FOOT_SUFFIX = "_foot_geom"
# Contacts one geom makes with the floor at most (MuJoCo's sphere-plane and capsule-plane tests).
CONTACTS_PER_GEOM = {mujoco.mjtGeom.mjGEOM_SPHERE: 1, mujoco.mjtGeom.mjGEOM_CAPSULE: 2}
# The most floor contacts of one episode with `all_contacts` (the torso's sphere and 12 leg capsules:
# 1 + 12 x 2; `contacts_per_episode` counts them from the model) and without (Brax's 4 foot spheres).
MAX_CONTACTS = {True: 25, False: 4}
# Constraint rows of one contact: the pyramidal friction cone of condim 3.
ROWS_PER_CONTACT = 4
LIMITED_JOINTS = 8  # the hips and ankles: one limit row each at most
# PEARL's contact cost clips each number of cfrc_ext to this range.
CONTACT_FORCE_RANGE = (-1.0, 1.0)
IMPLS = task_env.IMPLS


def default_config() -> ml_collections.ConfigDict:
    """Every number of the task, in one place; docs/ant_goal.md gives their sources."""
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
    # most contacts one episode can make (25 with `all_contacts`).
    cfg.warp_contacts = MAX_CONTACTS[True] * 4096
    # Warp only: constraint rows per episode: 4 per contact (25) + 8 joint limits.
    cfg.warp_constraints_per_world = ROWS_PER_CONTACT * MAX_CONTACTS[True] + LIMITED_JOINTS
    cfg.episode_steps = 200  # control steps per episode (10 s): PEARL's max_path_length
    cfg.task_range = (-3.0, 3.0)  # m: each goal coordinate's range (the box around the goal disc)
    cfg.goal_radius = 3.0  # m: goals drawn by `reset` without one lie uniformly on this disc (PEARL, ProMP)
    # True: every body geom collides with the floor (torso, legs), as in Gym's model that ProMP
    # and PEARL load. False: Brax's model as it is, whose only colliding geoms are its foot spheres.
    cfg.all_contacts = True
    # True: the observation holds the torso's x and y (qpos[0:2]), as PEARL's and ProMP's (29
    # numbers). False: Gym's ant's 27, without them.
    cfg.torso_xy = True
    # Reset noise: joint positions + U[-s, s], joint velocities + s * N(0, 1) (Gym's 0.1).
    cfg.reset_noise = 0.1
    cfg.reward = ml_collections.ConfigDict()
    cfg.reward.distance = 1.0  # weight of -|torso (x, y) - goal|_1 (m)
    cfg.reward.ctrl = 0.1  # weight of -sum(action ** 2)
    cfg.reward.contact = 0.5e-3  # weight of -sum(clip(cfrc_ext, -1, 1) ** 2); 0: cfrc_ext is not computed
    cfg.reward.survive = 0.0  # reward per step for being alive: PEARL's and ProMP's 0 (Gym's ant: 1)
    return cfg


def make_config(config=None, overrides: dict | None = None) -> ml_collections.ConfigDict:
    """A locked copy of `config` (default: `default_config()`) with dotted `overrides`.

    Unknown keys raise at once, naming the key.
    """
    return task_env.locked_config(default_config() if config is None else config, overrides)


def validate_config(cfg: ml_collections.ConfigDict) -> None:
    """ValueError naming the first bad value of an ant env config."""
    task_env.validate_episode(cfg, ("episode_steps",))
    lo, hi = cfg.task_range
    if not 0 < cfg.goal_radius <= min(-lo, hi):
        raise ValueError(f"env.goal_radius must be in (0, {min(-lo, hi)}] (inside the task range), "
                         f"got {cfg.goal_radius!r}")  # fmt: skip
    task_env.validate_nonnegative("env.reset_noise", cfg.reset_noise)
    task_env.validate_weights(cfg.reward)


def load_model(all_contacts: bool = True) -> mujoco.MjModel:
    """Brax's ant (C MuJoCo model); with `all_contacts` every body geom collides with the floor,
    as in Gym's model (and Brax's foot spheres, which Gym's model lacks and which lie inside the
    ankle capsules' ends, do not). The contacts are set before compiling: the compiler derives
    per-body collision masks from the geoms' (`body_contype`), which C MuJoCo's broad phase reads."""
    xml = (importlib.resources.files("brax") / "envs/assets/ant.xml").read_text()
    spec = mujoco.MjSpec.from_string(xml)
    if all_contacts:
        for body in spec.bodies[1:]:  # every body but the world (the floor)
            for geom in body.geoms:
                geom.contype = 0 if geom.name.endswith(FOOT_SUFFIX) else 1
    return spec.compile()


def colliding_geoms(model: mujoco.MjModel) -> np.ndarray:
    """Ids of the body geoms that can touch the floor (the floor's conaffinity meets their contype)."""
    return np.flatnonzero((model.geom_bodyid > 0) & (model.geom_contype > 0))


def max_contacts(model: mujoco.MjModel) -> int:
    """The most floor contacts of one episode: 1 per colliding sphere, 2 per colliding capsule."""
    return sum(CONTACTS_PER_GEOM[mujoco.mjtGeom(int(model.geom_type[g]))] for g in colliding_geoms(model))


@functools.lru_cache(maxsize=4)
def contacts_per_episode(all_contacts: bool = True) -> int:
    """The most floor contacts one episode makes (25 with `all_contacts`, 4 without)."""
    return max_contacts(load_model(all_contacts))


@functools.lru_cache(maxsize=4)
def _model_options(all_contacts: bool) -> tuple[float, int]:
    """The model's own (physics step (s), solver iterations)."""
    model = load_model(all_contacts)
    return float(model.opt.timestep), int(model.opt.iterations)


def noise_free(cfg: ml_collections.ConfigDict) -> dict:
    """Overrides of an env config that switch its reset noise off."""
    return {"reset_noise": 0.0}


def resolved(env_cfg) -> dict:
    """An ant env config as plain data with its physics step and solver iterations resolved
    (None: the model's own), as records carry it."""
    return task_env.with_model_options(env_cfg, *_model_options(bool(env_cfg.get("all_contacts", True))))


def n_steps_of(cfg: ml_collections.ConfigDict) -> int:
    """Control steps of one episode under env config `cfg`."""
    return int(cfg.episode_steps)


def disc_goals(n: int, radius: float = 3.0, seed: int = 0) -> tuple[tuple[float, float], ...]:
    """`n` goals (x, y) drawn as PEARL's `sample_tasks` draws them, from numpy's default_rng(seed):
    n angles U[0, 2 pi), then n radii `radius` sqrt(U[0, 1]) (uniform on the disc), rounded to
    3 decimals, as a config holds contexts (a tuple of tuples)."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(size=n) * 2 * np.pi
    r = radius * np.sqrt(rng.uniform(size=n))
    return tuple((round(float(x), 3), round(float(y), 3)) for x, y in zip(r * np.cos(a), r * np.sin(a), strict=True))


def sample_goal(rng: jax.Array, radius: float) -> jax.Array:
    """A goal (2,) m drawn uniformly on the disc of `radius` m, as PEARL's `sample_tasks`: angle
    U[0, 2 pi), radius `radius` sqrt(U[0, 1])."""
    rng_a, rng_r = jax.random.split(rng)
    a = jax.random.uniform(rng_a, minval=0.0, maxval=2 * jnp.pi)
    r = radius * jnp.sqrt(jax.random.uniform(rng_r))
    return jnp.stack([r * jnp.cos(a), r * jnp.sin(a)])


def contact_cost(cfrc_ext) -> jax.Array:
    """sum(clip(cfrc_ext, -1, 1) ** 2) over every body's external wrench (nbody, 6), ()."""
    return jnp.sum(jnp.square(jnp.clip(cfrc_ext, *CONTACT_FORCE_RANGE)))


def up_z(quat) -> np.ndarray:
    """The world z of the torso's up axis from its quaternion (..., 4) (w, x, y, z; need not be of
    unit norm): 1 upright, 0 on its side, -1 on its back."""
    q = np.asarray(quat, np.float64)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return (w * w - x * x - y * y + z * z) / np.sum(q * q, axis=-1)


class AntGoalEnv(task_env.ContextualEnv):
    """The ant walks its torso to a goal (x, y) m on a disc of radius 3 m.

    reset(rng, goal (2,)) -> State; step(state, action) -> State. `action` (8,): motor commands
    in [-1, 1] (clipped; each motor's gear of 150 turns it into a torque), the order of the
    model's actuators (hip_4, ankle_4, hip_1, ankle_1, hip_2, ankle_2, hip_3, ankle_3).
    """

    default_config = staticmethod(default_config)
    resolved = staticmethod(resolved)
    noise_free = staticmethod(noise_free)
    n_steps_of = staticmethod(n_steps_of)
    validate_config = staticmethod(validate_config)

    UNIT = "m"
    ACHIEVED = "final_position"  # (..., 2): where the torso is at the episode's end
    CONTEXT_SIZE = CONTEXT_SIZE
    ACTION_BOUND = 1.0  # every motor's ctrlrange

    def __init__(self, config=None, config_overrides: dict | None = None):
        self.config = make_config(config, config_overrides)
        validate_config(self.config)
        cfg = self.config
        mj_model = load_model(cfg.all_contacts)
        self.contacts_per_episode = max_contacts(mj_model)
        self._init_physics(mj_model)
        # cfrc_ext only when the contact cost weighs it: MJX-JAX computes it after a control
        # step's physics steps (`step`), Warp in every physics step's forward pass under this option.
        self.contact_forces = cfg.reward.contact > 0
        if self.contact_forces and self._warp_data is not None:
            self.mjx_model = self.mjx_model.tree_replace({"opt._impl.run_rne_postconstraint": True})
        self.n_steps = int(cfg.episode_steps)
        self.torso_body = mujoco.mj_name2id(self.mj_model, mujoco.mjtObj.mjOBJ_BODY, TORSO)
        root = mujoco.mj_name2id(self.mj_model, mujoco.mjtObj.mjOBJ_JOINT, ROOT)
        if self.mj_model.jnt_qposadr[root] != 0 or self.mj_model.jnt_type[root] != mujoco.mjtJoint.mjJNT_FREE:
            raise ValueError(f"the model's {ROOT!r} joint is not a free joint at its first coordinate")
        self._ctrl_lo = jnp.asarray(self.mj_model.actuator_ctrlrange[:, 0], jnp.float32)
        self._ctrl_hi = jnp.asarray(self.mj_model.actuator_ctrlrange[:, 1], jnp.float32)

    # -- brax's Env interface ------------------------------------------------------------
    @property
    def observation_size(self) -> int:
        return self.mj_model.nq - (0 if self.config.torso_xy else 2) + self.mj_model.nv

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
            target = sample_goal(rng_goal, cfg.goal_radius)
        elif not isinstance(target, jax.core.Tracer):
            self.check_targets(target)
        target = jnp.asarray(target, jnp.float32)
        goal = jnp.clip(target, lo, hi)

        data, overflow = self.gym_start(rng_q, rng_v)
        zero = jnp.zeros((), jnp.float32)
        info = {
            "target": goal,
            "step": jnp.zeros((), jnp.int32),
            "return": zero,  # sum of the rewards so far
            "overflow": overflow,
            "solver_limit_steps": jnp.zeros((), jnp.int32),
            # Brax's flag of an episode cut by its time limit: every episode ends so.
            "truncation": zero,
        }
        metrics = self._metrics(data, info, (zero, zero, zero, zero), self._distance_l1(data, goal))
        metrics["target_clipped"] = jnp.any(goal != target).astype(jnp.float32)
        return State(pipeline_state=data, obs=self._observe(data), reward=zero, done=zero, metrics=metrics, info=info)

    def step(self, state: State, action: jax.Array) -> State:
        """One control step of `n_substeps` physics steps. action: (8,) in [-1, 1] (clipped)."""
        if action.shape != (self.action_size,):
            raise ValueError(f"action must have shape ({self.action_size},), got {action.shape}")
        info = dict(state.info)
        action = jnp.clip(action, self._ctrl_lo, self._ctrl_hi)

        data, overflow, limit_steps = self.physics_steps(
            state.pipeline_state.replace(ctrl=action), info["overflow"], info["solver_limit_steps"]
        )
        if self.contact_forces and self._warp_data is None:
            # cfrc_ext of the last physics step's contacts (Warp's step computes it itself).
            data = mjx.rne_postconstraint(self.mjx_model, data)

        w = self.config.reward
        distance_l1 = self._distance_l1(data, info["target"])
        contact = contact_cost(data._impl.cfrc_ext) if self.contact_forces else jnp.zeros((), jnp.float32)
        terms = (
            -w.distance * distance_l1,
            -w.ctrl * jnp.sum(jnp.square(action)),
            -w.contact * contact,
            jnp.full((), w.survive, jnp.float32),
        )
        reward = sum(terms)
        step = info["step"] + 1
        done = (step >= self.n_steps).astype(jnp.float32)
        info.update(step=step, overflow=overflow, solver_limit_steps=limit_steps, truncation=done)
        info["return"] = info["return"] + reward
        metrics = self._metrics(data, info, terms, distance_l1)
        metrics["target_clipped"] = state.metrics["target_clipped"]
        return State(pipeline_state=data, obs=self._observe(data), reward=reward, done=done, metrics=metrics, info=info)

    # -- pieces ------------------------------------------------------------------------------
    def _metrics(self, data, info, terms, distance_l1) -> dict:
        """The step's reward terms and the episode's score so far (final at `done`)."""
        xy = data.xpos[self.torso_body, :2]
        distance = jnp.linalg.norm(xy - info["target"])
        reward_distance, reward_ctrl, reward_contact, reward_survive = terms
        return {
            "return": info["return"],
            # The pipeline's score: the torso's Euclidean distance to the goal now (m), final at
            # the episode's end; and whether the episode counts (no physics overflow).
            "final_error": distance,
            "valid": (~info["overflow"] & jnp.isfinite(distance)).astype(jnp.float32),
            "final_position": xy,  # (2,) m: scores the episode against any goal
            "distance_l1": distance_l1,  # |p - goal|_1 (m) now, what the step's reward pays
            # The reward's distance term as a function of the state (0 at the goal): the potential
            # that PPO's `potential_shaping` turns into progress toward the goal.
            "potential": -self.config.reward.distance * distance_l1,
            # This step's reward terms, weighted: reward = their sum.
            "reward_distance": reward_distance,
            "reward_ctrl": reward_ctrl,
            "reward_contact": reward_contact,
            "reward_survive": reward_survive,
            "torso_height": data.qpos[ROOT_Z_QPOS],  # m
            # 1 when a Warp contact or constraint buffer overflowed: the physics dropped contacts.
            "overflow": info["overflow"].astype(jnp.float32),
            # Physics steps whose solver stopped at its iteration limit (Warp only; MJX-JAX: 0).
            "solver_limit_steps": info["solver_limit_steps"].astype(jnp.float32),
        }

    def _distance_l1(self, data, goal) -> jax.Array:
        """|torso (x, y) - goal|_1 (m)."""
        return jnp.sum(jnp.abs(data.xpos[self.torso_body, :2] - goal))

    def _observe(self, data) -> jax.Array:
        """qpos (15; without the torso's x and y, 13, unless `torso_xy`) and qvel (14)."""
        qpos = data.qpos if self.config.torso_xy else data.qpos[2:]
        return jnp.concatenate([qpos, data.qvel])

    def posture(self, qpos: np.ndarray) -> dict:
        """The torso's posture over episodes' steps, qpos (..., T, nq) -> {name: (...)}: its mean
        height (m), the mean world z of its up axis (1 upright, -1 on its back) and the fraction of
        steps it spends on its back (up axis pointing down)."""
        qpos = np.asarray(qpos, np.float64)
        up = up_z(qpos[..., ROOT_QUAT_QPOS])
        return {
            "height_m": qpos[..., ROOT_Z_QPOS].mean(axis=-1),
            "up_z": up.mean(axis=-1),
            "flipped_fraction": (up < 0).mean(axis=-1),
        }

    @property
    def context_observation_size(self) -> int:
        """What a contextual policy observes (`with_context`): the observation and the goal."""
        return self.observation_size + CONTEXT_SIZE

    def error_against(self, metrics: dict, targets) -> np.ndarray:
        """Final distances (m) to other goals (`task_env.goal_errors`)."""
        return task_env.goal_errors(metrics, targets)

    def with_context(self, obs: jax.Array, context) -> jax.Array:
        """What a contextual (meta-)policy observes: obs (..., O) with the normalised goal
        (`normalise_context`, (..., 2) or one goal (2,) for every obs) appended: (..., O + 2)."""
        c = self.normalise_context(jnp.asarray(context, obs.dtype))
        c = jnp.broadcast_to(c, (*obs.shape[:-1], CONTEXT_SIZE))
        return jnp.concatenate([obs, c], axis=-1)
