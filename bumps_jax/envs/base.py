"""The shared base of the pipeline's contextual tasks (the kick, HalfCheetah-Vel).

A contextual task is a brax-style env whose `reset(rng, target)` takes the task's parameter (the
context: a distance in m, a velocity in m/s, or a vector of `CONTEXT_SIZE` numbers such as a goal
position) and whose final metrics score the episode against it:

    final_error   the episode's error against its target, in the context's unit (final at `done`)
    valid         1 for an episode the pipeline counts (no fall, no physics overflow, ...), else 0

and, for policy filtering, enough to score the same episode against any other target
(`error_against`): the physics of an episode does not depend on the target, only its score does.
A (meta-)policy sees `with_context(obs, context)`; an expert sees `expert_observation` of it.

`ContextualEnv` holds what both envs share: the physics step and backend setup, the Warp
contact pool's capacity in episodes, the target checks and the context's normalisation.
"""

from __future__ import annotations

import abc
import copy
import importlib.util
import json
import math

import jax
import jax.numpy as jnp
import ml_collections
import mujoco
import numpy as np
from brax.envs.base import Env
from mujoco import mjx

from bumps_jax.envs import physics

IMPLS = ("jax", "warp")


def locked_config(config: ml_collections.ConfigDict, overrides: dict | None = None) -> ml_collections.ConfigDict:
    """A locked deep copy of `config` with dotted `overrides`; an unknown key raises at once, naming it.
    (The copy: overriding a nested key must not write into the caller's config.)"""
    cfg = copy.deepcopy(ml_collections.ConfigDict(config))
    cfg.lock()
    for key, value in (overrides or {}).items():
        node = cfg
        *parents, leaf = key.split(".")
        for p in parents:
            if p not in node:
                raise ValueError(f"unknown config key {key!r}")
            node = node[p]
        if leaf not in node:
            raise ValueError(f"unknown config key {key!r}")
        node[leaf] = value
    return cfg


def physics_config(ctrl_dt: float, impl: str = "jax", warp_contacts: int = 4096,
                   warp_constraints_per_world: int = 4) -> ml_collections.ConfigDict:  # fmt: skip
    """The env config keys every task's physics reads, for a task's `default_config()` to add its
    own to; the defaults suit a task without collisions on MJX's JAX backend."""
    cfg = ml_collections.ConfigDict()
    cfg.ctrl_dt = ctrl_dt  # control step (s)
    # Physics step (s), a divisor of ctrl_dt; None: the model's own.
    cfg.physics_dt = ml_collections.FieldReference(None, field_type=float)
    cfg.impl = impl  # MJX backend that steps the physics: "jax" (MJX's JAX backend) or "warp" (MuJoCo Warp)
    # Constraint-solver iterations; None: the model's own.
    cfg.solver_iterations = ml_collections.FieldReference(None, field_type=int)
    cfg.warp_contacts = warp_contacts  # Warp only: contact slots of one physics call, over all its episodes
    cfg.warp_constraints_per_world = warp_constraints_per_world  # Warp only: constraint rows per episode
    return cfg


def with_model_options(env_cfg, timestep: float, iterations: int) -> dict:
    """An env config as plain data, as records carry it, with its physics step and solver iterations
    resolved: where they are None, the model's own `timestep` and `iterations`."""
    d = env_cfg.to_dict() if isinstance(env_cfg, ml_collections.ConfigDict) else dict(env_cfg)
    if d.get("physics_dt") is None:
        d["physics_dt"] = timestep
    if d.get("solver_iterations") is None:
        d["solver_iterations"] = iterations
    return json.loads(json.dumps(d, default=list))


def validate_physics(cfg: ml_collections.ConfigDict, int_keys=()) -> None:
    """ValueError naming the first bad physics value of an env config: the backend, the solver's
    iterations (None: the model's own), Warp's buffers, and the positive integers `int_keys`."""
    if cfg.impl not in IMPLS:
        raise ValueError(f"env.impl must be one of {IMPLS}, got {cfg.impl!r}")
    if cfg.impl == "warp" and importlib.util.find_spec("warp") is None:
        raise ValueError(
            "env.impl 'warp' needs the warp-lang package (pip install 'mujoco-mjx[warp]==3.17.0'), or set env.impl=jax"
        )
    for key in ("solver_iterations", "warp_contacts", "warp_constraints_per_world", *int_keys):
        value = cfg[key]
        if (value is not None or key != "solver_iterations") and (
            isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1
        ):
            raise ValueError(f"env.{key} must be a positive integer, got {value!r}")


def validate_physics_dt(cfg: ml_collections.ConfigDict) -> None:
    """ValueError if env.physics_dt is set outside (0, ctrl_dt], or does not divide ctrl_dt (checked
    with the config, before a stage writes anything, not when an env is built)."""
    if cfg.physics_dt is not None and not 0 < cfg.physics_dt <= cfg.ctrl_dt:
        raise ValueError(f"env.physics_dt must be in (0, ctrl_dt {cfg.ctrl_dt}], got {cfg.physics_dt!r}")
    if cfg.physics_dt is not None and cfg.ctrl_dt > 0:
        n = round(cfg.ctrl_dt / cfg.physics_dt)
        if not math.isclose(n * cfg.physics_dt, cfg.ctrl_dt, rel_tol=1e-6):
            steps = [cfg.ctrl_dt / k for k in range(1, 2000) if float(f"{cfg.ctrl_dt / k:.3g}") == cfg.ctrl_dt / k]
            near = sorted(steps, key=lambda dt: abs(dt - cfg.physics_dt))[:2]
            raise ValueError(
                f"env.physics_dt {cfg.physics_dt!r} does not divide env.ctrl_dt {cfg.ctrl_dt} into whole physics "
                f"steps; the nearest that do: {', '.join(f'{dt:g}' for dt in sorted(near))}"
            )


def validate_episode(cfg: ml_collections.ConfigDict, int_keys=()) -> None:
    """`validate_physics`, then a finite `task_range` with low < high, `ctrl_dt` > 0 and the physics
    step (`validate_physics_dt`): ValueError naming the first bad value."""
    validate_physics(cfg, int_keys)
    validate_task_range(cfg.task_range)
    if not cfg.ctrl_dt > 0:
        raise ValueError(f"env.ctrl_dt must be > 0, got {cfg.ctrl_dt!r}")
    validate_physics_dt(cfg)


def validate_task_range(task_range) -> None:
    """ValueError unless `env.task_range` is (low, high), finite, low < high."""
    ok = len(task_range) == 2 and all(isinstance(v, int | float) and math.isfinite(v) for v in task_range)
    if not (ok and task_range[0] < task_range[1]):
        raise ValueError(f"env.task_range must be finite with low < high, got {tuple(task_range)}")


def validate_nonnegative(name: str, value, what: str = "number") -> None:
    """ValueError naming `name` unless `value` is a finite number >= 0."""
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"{name} must be a finite {what} >= 0, got {value!r}")


def validate_weights(weights: ml_collections.ConfigDict, prefix: str = "env.reward.") -> None:
    """ValueError naming the first of a section's weights (`prefix` + its name) that is not a
    finite number >= 0."""
    for name, value in weights.items():
        validate_nonnegative(f"{prefix}{name}", value, "weight")


def goal_errors(metrics: dict, goals) -> np.ndarray:
    """Final distances (m) of finished episodes to other goals: `final_position` (S..., 2) against
    goals (..., 2) broadcasting with it, e.g. (C, R, 2) against (T, 1, 1, 2) -> (T, C, R); an
    invalid episode scores inf. A goal-reaching env's `error_against`."""
    pos = np.asarray(metrics["final_position"], np.float64)
    err = np.linalg.norm(pos - np.asarray(goals, np.float64), axis=-1)
    return np.where(np.asarray(metrics["valid"]) > 0, err, np.inf)


def check_targets(targets, task_range, unit: str = "m", size: int = 1) -> np.ndarray:
    """Targets as a float array, or ValueError naming the first one outside `task_range` (in `unit`).

    size 1: scalar contexts, any shape. size K > 1: vector contexts (..., K), each coordinate in
    [low, high] of `task_range` (a box); a last axis of another length raises."""
    arr = np.asarray(targets, dtype=np.float64)
    if size > 1 and (arr.ndim == 0 or arr.shape[-1] != size):
        raise ValueError(f"targets must be vectors of {size} numbers ({unit}), got shape {arr.shape}")
    lo, hi = task_range
    bad = ~np.isfinite(arr) | (arr < lo - 1e-9) | (arr > hi + 1e-9)
    if bad.any():
        if size > 1:
            row = arr.reshape(-1, size)[bad.reshape(-1, size).any(axis=1)][0]
            raise ValueError(f"target {format_context(row)} {unit} is outside the task range [{lo}, {hi}] {unit}")
        raise ValueError(f"target {float(arr[bad].flat[0])!r} {unit} is outside the task range [{lo}, {hi}] {unit}")
    return arr


# -- contexts of any shape: a scalar (size 1, the kick's and the cheetah's) or a vector (size K) --


def context_shape(size: int) -> tuple[int, ...]:
    """The shape of one context: () for size 1, (K,) for size K > 1."""
    return () if size == 1 else (int(size),)


def as_contexts(values, size: int = 1) -> np.ndarray:
    """Contexts as a float64 array of N contexts: (N,) for size 1, (N, K) for size K > 1."""
    return np.asarray(values, np.float64).reshape(-1, *context_shape(size))


def context_json(context):
    """One context as records carry it: a float (size 1) or a list of floats (size K)."""
    arr = np.asarray(context, np.float64)
    return float(arr) if arr.ndim == 0 else [float(v) for v in arr]


def format_context(context, spec: str = ".3g") -> str:
    """One context as text: `1.2` (size 1) or `(0.5, -0.3)` (size K), each number by `spec`."""
    arr = np.asarray(context, np.float64)
    if arr.ndim == 0:
        return format(float(arr), spec)
    return "(" + ", ".join(format(float(v), spec) for v in arr) + ")"


class ContextualEnv(Env):
    """What every contextual task of the pipeline shares. A subclass sets `config` (with ctrl_dt,
    physics_dt, solver_iterations, impl, warp_contacts, warp_constraints_per_world, task_range),
    `contacts_per_episode`, then calls `_init_physics(mj_model)`; it defines reset, step,
    observation_size, action_size, with_context and error_against, and its config's static
    functions `default_config()`, `resolved(env_config)`, `noise_free(env_config)` and
    `n_steps_of(env_config)` (an episode's control steps)."""

    UNIT = "m"  # the context's unit
    CONTEXT_SIZE = 1  # numbers in one context: 1, a scalar (); K > 1, a vector (K,) (a goal position)
    ACHIEVED: str | None = None  # the final metric holding what an episode achieved, in UNIT (plots): required
    # The actions' bound: the env clips each action to [-ACTION_BOUND, ACTION_BOUND]; None: no
    # clipping (the kick's joint targets).
    ACTION_BOUND: float | None = None
    contacts_per_episode: int  # the most contacts one episode makes: Warp's pool holds this per episode

    def _init_physics(self, mj_model: mujoco.MjModel) -> None:
        """The model's physics step and solver iterations from the config, the control step's
        physics steps, Warp's capacity in episodes, and the MJX model and blank data."""
        cfg = self.config
        if cfg.physics_dt is not None:
            mj_model.opt.timestep = cfg.physics_dt
        if cfg.solver_iterations is not None:
            mj_model.opt.iterations = cfg.solver_iterations
        self.mj_model = mj_model
        physics_dt = self.physics_dt = float(mj_model.opt.timestep)
        self.n_substeps = int(round(cfg.ctrl_dt / physics_dt))
        if not math.isclose(self.n_substeps * physics_dt, cfg.ctrl_dt, rel_tol=1e-6):
            raise ValueError(f"ctrl_dt {cfg.ctrl_dt} is not a multiple of the physics step {physics_dt}")
        # Episodes one physics call holds: Warp's contact pool; None: no limit (MJX-JAX).
        self.max_episodes = cfg.warp_contacts // self.contacts_per_episode if cfg.impl == "warp" else None
        self.mjx_model, self._warp_data = physics.put_physics(mj_model, cfg)

    def start_data(self, qpos: jax.Array, qvel: jax.Array) -> tuple:
        """A new episode's physics data at (qpos, qvel) with no control, after a forward pass:
        (data, whether a Warp buffer overflowed ())."""
        blank = physics.blank_data(self.mjx_model, self._warp_data)
        data = blank.replace(qpos=qpos, qvel=qvel, ctrl=jnp.zeros(self.mj_model.nu))
        data, overflow, _ = physics.read_flags(mjx.forward(self.mjx_model, data))
        return data, overflow

    def physics_steps(self, data, overflow: jax.Array, limit_steps: jax.Array) -> tuple:
        """One control step's physics: `n_substeps` MJX steps of `data` (its ctrl set), with
        Warp's flags carried: (data, whether a buffer overflowed in this or an earlier step,
        `limit_steps` plus the steps whose solver stopped at its iteration limit)."""

        def substep(carry, _):
            data, overflow, limit_steps = carry
            data, overflowed, hit_limit = physics.read_flags(mjx.step(self.mjx_model, data))
            return (data, overflow | overflowed, limit_steps + hit_limit.astype(jnp.int32)), None

        (data, overflow, limit_steps), _ = jax.lax.scan(substep, (data, overflow, limit_steps), None, self.n_substeps)
        return data, overflow, limit_steps

    def gym_start(self, rng_q: jax.Array, rng_v: jax.Array) -> tuple:
        """`start_data` as Gym's MuJoCo envs start an episode: the model's qpos0 + U[-s, s], joint
        velocities s * N(0, 1), s the config's `reset_noise`."""
        s, nq, nv = self.config.reset_noise, self.mj_model.nq, self.mj_model.nv
        qpos = jnp.asarray(self.mj_model.qpos0, jnp.float32) + jax.random.uniform(rng_q, (nq,), minval=-s, maxval=s)
        return self.start_data(qpos, s * jax.random.normal(rng_v, (nv,)))

    # -- brax's Env interface ------------------------------------------------------------
    @property
    def backend(self) -> str:
        return "mjx"

    @property
    def dt(self) -> float:
        return self.config.ctrl_dt

    @property
    def action_size(self) -> int:
        """One action per actuator of the model (a task whose actions are not its actuators' says its own)."""
        return self.mj_model.nu

    # -- the context -----------------------------------------------------------------------
    def check_targets(self, targets) -> np.ndarray:
        """Targets as a float array, or ValueError naming the first one outside the task range
        (vectors (..., CONTEXT_SIZE) for a vector context)."""
        return check_targets(targets, self.config.task_range, self.UNIT, self.CONTEXT_SIZE)

    def normalise_context(self, context):
        """A target or context as the policy sees it: 0 at the task range's low end, 1 at its high
        (each coordinate of a vector context)."""
        lo, hi = self.config.task_range
        return (context - lo) / (hi - lo)

    @property
    def context_observation_size(self) -> int:
        """Size of what a contextual policy observes (`with_context`); the env's own by default."""
        return self.observation_size

    def expert_observation(self, obs: jax.Array) -> jax.Array:
        """What a single-task expert observes of a contextual observation (..., context size):
        the env's own observation, its first `observation_size` numbers (..., observation_size)."""
        return obs[..., : self.observation_size]

    def posture(self, qpos: np.ndarray) -> dict:
        """Statistics of a body's posture over episodes, qpos (..., T, nq) -> {name: (...)}: what
        tells whether experts move alike (the cheetah: torso pitch and height). None by default."""
        return {}

    @abc.abstractmethod
    def with_context(self, obs: jax.Array, context) -> jax.Array:
        """What a contextual (meta-)policy observes: obs with the normalised `context` in it,
        (..., context_observation_size)."""

    @abc.abstractmethod
    def error_against(self, metrics: dict, targets) -> np.ndarray:
        """Final errors of finished episodes against other targets: metrics (host arrays of shape
        S, as the env reports them) with targets broadcasting against S, e.g. (T, 1, 1) against
        (C, R) -> (T, C, R); a vector context's targets carry its last axis: (T, 1, 1, K)."""


# What a task's env class holds besides `ContextualEnv`'s methods: its config's functions.
CONFIG_FUNCTIONS = ("default_config", "validate_config", "resolved", "noise_free", "n_steps_of")


def interface_gaps(env_class: type) -> list[str]:
    """What `env_class` lacks of a task's env (docs/your_task.md §1): its abstract methods left
    undefined, its config's static functions, a named `ACHIEVED` metric; [] when nothing."""
    gaps = sorted(getattr(env_class, "__abstractmethods__", ()))
    gaps += [f"{name}()" for name in CONFIG_FUNCTIONS if not callable(getattr(env_class, name, None))]
    if not isinstance(getattr(env_class, "ACHIEVED", None), str):
        gaps.append("ACHIEVED (the final metric holding what an episode achieved)")
    return gaps


def check_episode(env: ContextualEnv) -> None:
    """ValueError naming the first way one episode step of `env`, traced and not run
    (`jax.eval_shape`), breaks what the pipeline reads of it: the observation's and the
    contextual observation's sizes, a scalar reward and done, a step keeping the state's shapes,
    and the final metrics `final_error`, `valid` and `ACHIEVED`."""
    name = type(env).__name__
    lo, hi = env.config.task_range
    context = jnp.full(context_shape(env.CONTEXT_SIZE), (lo + hi) / 2, jnp.float32)
    first = jax.eval_shape(env.reset, jax.random.key(0), context)
    after = jax.eval_shape(env.step, first, jnp.zeros(env.action_size, jnp.float32))
    seen = jax.eval_shape(env.with_context, first.obs, context)
    for what, shape, size in (("reset's observation", first.obs.shape, env.observation_size),
                              ("with_context's observation", seen.shape, env.context_observation_size)):  # fmt: skip
        if shape != (size,):
            raise ValueError(f"{name}: {what} has shape {shape}, its size says ({size},)")
    if first.reward.shape != () or first.done.shape != ():
        raise ValueError(f"{name}: reset's reward and done must be scalars, got shapes {first.reward.shape} and "
                         f"{first.done.shape}")  # fmt: skip
    before_leaves = dict(jax.tree_util.tree_flatten_with_path(first)[0])
    for path, leaf in jax.tree_util.tree_flatten_with_path(after)[0]:
        was = before_leaves.get(path)
        if was is None or (was.shape, was.dtype) != (leaf.shape, leaf.dtype):
            where = jax.tree_util.keystr(path)
            had = "nothing" if was is None else f"{was.dtype}{list(was.shape)}"
            raise ValueError(f"{name}: step returns state{where} as {leaf.dtype}{list(leaf.shape)}, reset as {had}")
    for metric in ("final_error", "valid", env.ACHIEVED):
        if metric not in after.metrics:
            raise ValueError(f"{name}: step's metrics hold no {metric!r} (they hold {sorted(after.metrics)})")
    for metric in ("final_error", "valid"):
        if after.metrics[metric].shape != ():
            raise ValueError(f"{name}: metric {metric!r} must be a scalar, got shape {after.metrics[metric].shape}")


class ContextObserved:
    """`env` whose every observation carries its episode's target (`env.with_context`): what one
    policy over every target trains on when the env's own observation holds none. The rest is `env`'s."""

    def __init__(self, env):
        self.env = env

    def __getattr__(self, name):
        return getattr(self.env, name)

    @property
    def observation_size(self) -> int:
        return self.env.context_observation_size

    def reset(self, rng, target=None):
        state = self.env.reset(rng, target)
        return state.replace(obs=self.env.with_context(state.obs, state.info["target"]))

    def step(self, state, action):
        nxt = self.env.step(state, action)
        return nxt.replace(obs=self.env.with_context(nxt.obs, nxt.info["target"]))
