"""The keyframe kick: fourteen numbers -> joint targets at every control step, and its saved record.

The kick is a handful of key poses, each held as a joint-target vector and reached by linear
interpolation at 50 Hz (the environment then rate-limits the targets as SimSpark's servos do):

    stance -> lean (weight over the right foot) -> lift -> wind back -> swing -> lift
           -> lean -> stance (held to the end of the kick phase)

`PARAM_NAMES` lists the fourteen numbers: the lean, how the support leg carries the body
forward, the wind-back and swing poses of the kicking leg, the segment durations, and a
`strength` in (0, 1] that sets how fast the swing runs as a fraction of the servos' speed
limit. A family of kicks spans the reachable distances: three anchors (short, main, long) and
the blend between them (`blend_params`), calibrated from distance to strength by a sweep.

A kick prior is saved as a small versioned JSON record (`save_record` / `load_record`) that
names the env config it was tuned under; loading it under another one is refused.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax import records as env_records
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import scene

FORMAT_VERSION = 1
# The committed kick prior: where a run's prior search starts, and the experts' prior when a
# run made none of its own.
ASSET = Path(__file__).resolve().parents[3] / "assets" / "kick_prior.json"

# Angles in degrees (offsets from the stance unless noted), times in seconds.
PARAM_NAMES = (
    "lean",  # hip roll on both legs (feet kept flat): shifts the torso over the right foot
    "support_hip",  # right hip pitch offset while on one foot
    "support_ankle",  # right ankle pitch offset: positive carries the body forward
    "t_shift",  # time to lean over (s)
    "t_lift",  # lean -> lifted kicking foot (s)
    "back_hip",  # kicking leg at the end of the wind-back
    "back_knee",
    "back_ankle",
    "t_back",  # lift -> wound back (s)
    "swing_hip",  # kicking leg at the end of the swing
    "swing_knee",
    "swing_ankle",
    "t_swing",  # shortest swing duration (s); a low strength stretches it
    "strength",  # swing speed as a fraction of the servo speed limit, (0, 1]
)
N_PARAMS = len(PARAM_NAMES)

# The hand-found starting point (C MuJoCo grid search): hits the ball to ~8-11 m standing.
DEFAULT_PARAMS = np.array([13.0, 0.0, 8.0, 0.3, 0.15, 0.0, -90.0, 10.0, 0.15, 50.0, 40.0, 0.0, 0.12, 1.0])
# CMA-ES searches z with params = start + SCALE * z: one unit of z is a comparable change
# (a few degrees, a few control steps) in every coordinate.
PARAM_SCALE = np.array([1.0, 3.0, 3.0, 0.04, 0.04, 5.0, 8.0, 5.0, 0.04, 5.0, 8.0, 5.0, 0.03, 0.1])
# Hard bounds: durations positive, and every key pose inside the joint ranges (the stance
# knee is -40 deg, so the wind-back knee offset stops at -90 = the -130 deg limit).
PARAM_LOW = np.array([5.0, -20.0, -15.0, 0.1, 0.04, -30.0, -90.0, -30.0, 0.04, 10.0, -20.0, -40.0, 0.04, 0.1])
PARAM_HIGH = np.array([25.0, 25.0, 20.0, 0.6, 0.4, 30.0, 0.0, 50.0, 0.4, 80.0, 40.0, 40.0, 0.3, 1.0])

# The lifted kicking leg between wind-back and recovery (fixed: the search tunes the rest).
_LIFT = {"llj3": 10.0, "llj4": -40.0, "llj5": 20.0}
# Recovery after the swing: back to the lift, then the lean, then the stance (s after it).
_RECOVER = (0.2, 0.45, 0.7)

_J = {name: i for i, name in enumerate(scene.JOINTS)}


def _pose(lean=0.0, support=(0.0, 0.0), kick=(0.0, 0.0, 0.0)) -> jax.Array:
    """Joint targets (22,) rad: the stance plus offsets in degrees."""
    offset = jnp.zeros(scene.N_JOINTS)
    # Equal hip roll on both legs tilts the body over the right foot; the ankle rolls undo
    # it at the soles so both feet stay flat.
    offset = offset.at[jnp.array([_J["llj2"], _J["rlj2"]])].set(lean)
    offset = offset.at[jnp.array([_J["llj6"], _J["rlj6"]])].set(-lean)
    offset = offset.at[jnp.array([_J["rlj3"], _J["rlj5"]])].set(jnp.stack(support))
    offset = offset.at[jnp.array([_J["llj3"], _J["llj4"], _J["llj5"]])].set(jnp.stack(kick))
    return jnp.asarray(scene.STANCE) + jnp.deg2rad(offset)


def keyframes(params) -> tuple[jax.Array, jax.Array]:
    """The kick's key poses. params: (14,). Returns times (K,) s, increasing, and poses (K, 22) rad."""
    p = dict(zip(PARAM_NAMES, jnp.asarray(params, jnp.float32), strict=True))
    support = (p["support_hip"], p["support_ankle"])
    lift = tuple(jnp.float32(_LIFT[n]) for n in ("llj3", "llj4", "llj5"))
    back = (p["back_hip"], p["back_knee"], p["back_ankle"])
    swing = (p["swing_hip"], p["swing_knee"], p["swing_ankle"])
    stance = _pose()
    lean = _pose(p["lean"], support)
    lifted = _pose(p["lean"], support, lift)
    wound = _pose(p["lean"], support, back)
    swung = _pose(p["lean"], support, swing)
    # The swing's hip target moves at `strength` x the speed limit, or slower if t_swing asks.
    # (The hip, not the knee: the hip drives the foot; the knee target runs ahead of the
    # rate-limited servo and only sets how straight the leg is at the ball.)
    amplitude = jnp.deg2rad(jnp.abs(p["swing_hip"] - p["back_hip"]))
    strength = jnp.clip(p["strength"], 0.05, 1.0)
    t_swing = jnp.maximum(p["t_swing"], amplitude / (strength * scene.MAX_JOINT_SPEED))
    # Segment durations, floored at 10 ms so the times stay strictly increasing.
    durations = jnp.maximum(
        jnp.stack([p["t_shift"], p["t_lift"], p["t_back"], t_swing, *map(jnp.float32, _steps(_RECOVER))]),
        0.01,
    )
    times = jnp.concatenate([jnp.zeros(1), jnp.cumsum(durations)])
    poses = jnp.stack([stance, lean, lifted, wound, swung, lifted, lean, stance])
    return times, poses


def _steps(marks):
    """Absolute marks after the swing -> the durations between them."""
    return (marks[0], marks[1] - marks[0], marks[2] - marks[1])


def keyframes_to_actions(params, n_steps: int, ctrl_dt: float = 0.02) -> jax.Array:
    """Joint targets (n_steps, 22) rad at each control step, interpolated from the key poses.

    Step k's action is the interpolated pose at time (k + 1) * ctrl_dt (the pose the servos
    should be heading for by the end of that step); after the last key pose it is held.
    Pure and jittable; vmap over params (P, 14) for a population.
    """
    times, poses = keyframes(params)
    t = (jnp.arange(n_steps, dtype=jnp.float32) + 1.0) * ctrl_dt
    interp = jax.vmap(lambda column: jnp.interp(t, times, column), in_axes=1, out_axes=1)
    return interp(poses)


def clip_params(params) -> jax.Array:
    """Params (..., 14) clipped into [PARAM_LOW, PARAM_HIGH]."""
    return jnp.clip(params, PARAM_LOW, PARAM_HIGH)


# The family of kicks that spans the reachable range: the short kick, the 12 m prior and the
# long kick, each optimised on its own, at strength 0, 0.5 and 1; strengths in between
# interpolate their parameters linearly. (The `strength` parameter of one kick alone only
# caps the swing's speed: the optimised 12 m kick swings slower than every cap above 0.5.)
ANCHORS = ("short", "main", "long")


def blend_params(anchors, strength) -> jax.Array:
    """Kick params (14,) at `strength` in [0, 1] along the anchors (3, 14): short, main, long."""
    anchors = jnp.asarray(anchors, jnp.float32)
    s = jnp.clip(jnp.asarray(strength, jnp.float32), 0.0, 1.0)
    lower = jnp.where(s < 0.5, anchors[0], anchors[1])
    upper = jnp.where(s < 0.5, anchors[1], anchors[2])
    w = jnp.where(s < 0.5, 2.0 * s, 2.0 * s - 1.0)
    return clip_params((1.0 - w) * lower + w * upper)


def calibration(record: dict) -> np.ndarray:
    """(n, 2) rows (strength, mean resting distance m) from a prior record's sweep, kept only
    where the distance rises (np.interp needs it increasing; the blend is not monotone
    everywhere: a dip is dropped, not smoothed)."""
    rows = sorted((r["strength"], r["distance_m"]) for r in record["sweep"])
    kept = [rows[0]]
    for s, d in rows[1:]:
        if d > kept[-1][1]:
            kept.append((s, d))
    return np.asarray(kept, np.float32)


def kick_for(anchors, table, target) -> jax.Array:
    """The blended kick params (14,) expected to rest near `target` m (jittable in target).

    anchors: (3, 14); table: `calibration(...)` rows (strength, distance).
    """
    table = jnp.asarray(table)
    strength = jnp.interp(jnp.asarray(target, jnp.float32), table[:, 1], table[:, 0])
    return blend_params(anchors, strength)


def family_kicks(record: dict, targets) -> np.ndarray:
    """The prior `record`'s blended family (its anchors at the strengths its sweep calibrates,
    `kick_for`) at `targets` (T,) m: (T, 14)."""
    anchors, table = jnp.asarray(record["anchors"], jnp.float32), jnp.asarray(calibration(record))
    return np.asarray(jax.vmap(lambda t: kick_for(anchors, table, t))(jnp.asarray(targets, jnp.float32)))


def largest_jump(params, targets) -> dict:
    """The roughness of a family of kicks: the largest change of one parameter between kicks of
    neighbouring targets, in `PARAM_SCALE` units.

    params: (T, 14) kicks for targets (T,) m (any order; T >= 2). Returns {"jump": float,
    "param": name, "between_m": [lower target, upper target]}.
    """
    params, targets = np.asarray(params, np.float64), np.asarray(targets, np.float64)
    if params.ndim != 2 or params.shape != (len(targets), N_PARAMS) or len(targets) < 2:
        raise ValueError(f"need params (T, {N_PARAMS}) and targets (T,) with T >= 2, got {params.shape} "
                         f"and {targets.shape}")  # fmt: skip
    order = np.argsort(targets, kind="stable")
    steps = np.abs(np.diff(params[order], axis=0)) / PARAM_SCALE  # (T - 1, 14)
    i, j = np.unravel_index(int(np.argmax(steps)), steps.shape)
    return {
        "jump": float(steps[i, j]),
        "param": PARAM_NAMES[j],
        "between_m": [float(targets[order][i]), float(targets[order][i + 1])],
    }


def fitness(metrics: dict, target, weights) -> jax.Array:
    """Cost to minimise, (...,) from the env's final metrics of (...,): distance error, sideways error, validity.

    An invalid kick still pays its distance error, so a near miss ranks above a wild one.
    """
    along = jnp.abs(metrics["distance"] - target)
    invalid = 1.0 - metrics["valid"]
    lateral = jnp.abs(metrics["lateral"])
    return weights.distance * along + weights.lateral * lateral + weights.invalid * invalid


def action_tables(params, n_steps: int, ctrl_dt: float) -> jax.Array:
    """Joint targets (P, n_steps, 22) of a batch of kicks (P, 14): `rollout.table_policy` plays them."""
    return jax.vmap(lambda p: keyframes_to_actions(p, n_steps, ctrl_dt))(jnp.asarray(params, jnp.float32))


# -- the saved record ---------------------------------------------------------------------------


def make_record(params, prior_cfg, env: dict, evaluation: dict, **extra) -> dict:
    """The JSON-able record of a kick prior: params, names, the prior and env configs, evaluation."""
    return {
        "format_version": FORMAT_VERSION,
        "param_names": list(PARAM_NAMES),
        "params": [float(x) for x in np.asarray(params)],
        "config": json.loads(prior_cfg.to_json()) if hasattr(prior_cfg, "to_json") else prior_cfg,
        "env": env,
        "evaluation": evaluation,
        **extra,
    }


def save_record(record: dict, path: str | Path) -> Path:
    from bumps_jax import runio  # noqa: PLC0415

    return runio.write_json(path, record)


def load_record(path: str | Path = ASSET, env_cfg=None) -> dict:
    """A saved prior; record['params'] is float32 (14,), record['anchors'] (3, 14) if present.

    ValueError naming the path if it is missing, not a prior of this format, or (with `env_cfg`)
    made under another env config.
    """
    from bumps_jax import runio  # noqa: PLC0415

    record = runio.read_json(path, "a kick prior record")
    if record.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{path}: format_version {record.get('format_version')!r}, expected {FORMAT_VERSION}")
    if tuple(record.get("param_names", ())) != PARAM_NAMES:
        raise ValueError(f"{path}: param_names {record.get('param_names')!r} do not match {PARAM_NAMES}")
    if env_cfg is not None:
        env_records.check_same_env(record.get("env"), env_cfg, f"kick prior {path}", kick_env.resolved)
    record["params"] = np.asarray(record["params"], np.float32)
    if "anchors" in record:
        record["anchors"] = np.asarray([record["anchors"][n] for n in ANCHORS], np.float32)
    return record
