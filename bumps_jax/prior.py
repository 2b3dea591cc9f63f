"""A parametrised keyframe kick for the left leg, and its CMA-ES optimisation in MJX.

The kick is a handful of key poses, each held as a joint-target vector and reached by linear
interpolation at 50 Hz (the environment then rate-limits the targets as SimSpark's servos do):

    stance -> lean (weight over the right foot) -> lift -> wind back -> swing -> lift
           -> lean -> stance (held to the end of the kick phase)

Fourteen numbers describe it (`PARAM_NAMES`): the lean, how the support leg carries the body
forward, the wind-back and swing poses of the kicking leg, the segment durations, and a
`strength` in (0, 1] that sets how fast the swing runs as a fraction of the servos' speed
limit. Strength is the knob that sets the distance: a sweep over it turns one prior into
kicks from ~6 m upwards (`sweep`).

`optimise` tunes the prior for one target with evosax's CMA-ES; each generation's whole
population x repetitions runs as one jitted, vmapped MJX program. The result is a small
versioned JSON (`save_prior` / `load_prior`) that later stages replay without optimising.
"""

from __future__ import annotations

import csv
import functools
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from bumps_jax import kick_env, scene

FORMAT_VERSION = 1
PRIOR_JSON = Path(__file__).resolve().parent.parent / "assets" / "kick_prior.json"
# A kick-prior run's own copy of the record it would commit as PRIOR_JSON, beside its payload:
# the stages after it read this file, and `publish` commits it, so a run brought back from
# another machine carries the prior its experts started from.
RUN_PRIOR_JSON = "kick_prior_asset.json"

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


# -- configuration ----------------------------------------------------------------------------


def default_config() -> ml_collections.ConfigDict:
    """Every number of the prior's optimisation, in one place."""
    cfg = ml_collections.ConfigDict()
    cfg.target = 12.0  # metres: the prior is tuned for the middle of the task range
    # The env's target range while tuning: wider than the paper's tasks so that the short and
    # long extremes of the reachable range (about 6 and 21 m) can be optimised too.
    cfg.task_range = (5.0, 25.0)
    cfg.population_size = 16
    cfg.generations = 30
    cfg.repetitions = 4  # noisy episodes (env noise) per candidate per generation
    cfg.sigma_init = 1.0  # CMA-ES step in units of PARAM_SCALE
    cfg.seed = 0
    # Names of the parameters CMA-ES moves; the rest stay at the start point. Strength is held
    # (below 1) so that the optimised kick keeps headroom for longer kicks in the sweep.
    cfg.free_params = tuple(n for n in PARAM_NAMES if n != "strength")
    cfg.start_strength = 0.75
    cfg.eval_repetitions = 32  # noisy episodes for the final evaluation of the best kick
    cfg.fitness = ml_collections.ConfigDict()
    cfg.fitness.distance = 1.0  # per metre of resting error along the kick direction
    cfg.fitness.lateral = 2.0  # per metre of sideways error: the ball must go straight
    cfg.fitness.invalid = 20.0  # a fall, a miss or a blow-up
    return cfg


def make_config(config=None, overrides: dict | None = None) -> ml_collections.ConfigDict:
    """A locked copy of `config` (default: `default_config()`) with dotted `overrides`."""
    return kick_env.make_config(default_config() if config is None else config, overrides)


def validate_config(cfg: ml_collections.ConfigDict) -> None:
    """ValueError naming the first bad value; called before anything compiles."""
    for key in ("population_size", "generations", "repetitions", "eval_repetitions"):
        value = cfg[key]
        if not isinstance(value, int | np.integer) or value < 1:
            raise ValueError(f"{key} must be a positive integer, got {value!r}")
    if cfg.population_size < 2:
        raise ValueError(f"population_size must be >= 2 for CMA-ES, got {cfg.population_size}")
    if not np.isfinite(cfg.sigma_init) or cfg.sigma_init <= 0:
        raise ValueError(f"sigma_init must be > 0, got {cfg.sigma_init!r}")
    if not 0.0 < cfg.start_strength <= 1.0:
        raise ValueError(f"start_strength must be in (0, 1], got {cfg.start_strength!r}")
    unknown = [n for n in cfg.free_params if n not in PARAM_NAMES]
    if unknown or not cfg.free_params:
        raise ValueError(f"free_params must name parameters of {PARAM_NAMES}, got {tuple(cfg.free_params)!r}")
    for name, value in cfg.fitness.items():
        if not np.isfinite(value) or value < 0:
            raise ValueError(f"fitness.{name} must be >= 0, got {value!r}")
    # The kick is tuned in the default task (its noise included): the target must be one of it.
    kick_env.check_targets(cfg.target, cfg.task_range)


# -- rollouts and fitness ---------------------------------------------------------------------


def make_rollout(env: kick_env.KickEnv):
    """A jitted fn (params (P, 14), keys (P, R) PRNG keys, target) -> outcome dict of (P, R).

    One XLA program for the whole batch: vmap over candidates and repetitions of
    reset + a lax.scan of `env.step` over the kick phase. Besides the env's final metrics the
    outcome holds `distance` (m the ball rests ahead of its nominal start) and `lateral`
    (m it rests to the left of the kick line).
    """

    over_reps = jax.vmap(_episode_fn(env), in_axes=(None, 0, None))
    return jax.jit(jax.vmap(over_reps, in_axes=(0, 0, None)))


def _episode_fn(env: kick_env.KickEnv):
    """(params (14,), key, target) -> outcome dict of one noisy kick (see `make_rollout`)."""

    def episode(params, key, target):
        actions = keyframes_to_actions(params, env.n_steps, env.dt)
        state = env.reset(key, target)
        state, _ = jax.lax.scan(lambda s, a: (env.step(s, a), None), state, actions)
        out = dict(state.metrics)
        target_xy = state.info["target_xy"]
        out["distance"] = out["rest_x"] - (target_xy[0] - state.info["target"])
        out["lateral"] = out["rest_y"] - target_xy[1]
        return out

    return episode


def fitness(outcome: dict, target, weights) -> jax.Array:
    """Cost to minimise, (...,) from an outcome of (...,): distance error, sideways error, validity.

    An invalid kick still pays its distance error, so a near miss ranks above a wild one.
    """
    along = jnp.abs(outcome["distance"] - target)
    invalid = 1.0 - outcome["valid"]
    lateral = jnp.abs(outcome["lateral"])
    return weights.distance * along + weights.lateral * lateral + weights.invalid * invalid


# -- optimisation -----------------------------------------------------------------------------


def _env_for(cfg) -> kick_env.KickEnv:
    # The default task, noise included; only the range of admissible targets is wider.
    return _env_for_range(tuple(cfg.task_range))


@functools.lru_cache(maxsize=4)
def _env_for_range(task_range: tuple) -> kick_env.KickEnv:
    # One env per range, so programs built on it (`_tuning_programs`) are found again.
    return kick_env.KickEnv(config_overrides={"task_range": task_range})


def _free_mask(cfg) -> np.ndarray:
    return np.array([n in cfg.free_params for n in PARAM_NAMES])


def evaluate(params, config=None, repetitions=None, seed: int = 1, env=None, rollout=None) -> dict:
    """Replay one kick over `repetitions` noisy episodes (default: config.eval_repetitions).

    Returns plain floats: mean and std of the resting error, mean distance and sideways
    offset, valid / struck / fallen fractions, mean fitness.
    """
    cfg = make_config(config)
    validate_config(cfg)
    reps = cfg.eval_repetitions if repetitions is None else repetitions
    env = env or _env_for(cfg)
    rollout = rollout or make_rollout(env)
    keys = jax.random.split(jax.random.key(seed), reps)[None]
    out = rollout(clip_params(jnp.asarray(params, jnp.float32))[None], keys, cfg.target)
    cost = fitness(out, cfg.target, cfg.fitness)
    summary = {
        "repetitions": int(reps),
        "target": float(cfg.target),
        "mean_error": float(jnp.mean(out["final_error"])),
        "std_error": float(jnp.std(out["final_error"])),
        "mean_distance": float(jnp.mean(out["distance"])),
        "mean_lateral": float(jnp.mean(out["lateral"])),
        "mean_fitness": float(jnp.mean(cost)),
    }
    for key in ("valid", "struck", "fallen"):
        summary[f"{key}_fraction"] = float(jnp.mean(out[key]))
    return summary


def optimise(
    config=None, out_dir: str | Path = "runs/prior", start=None, verbose: bool = True, env=None, rollout=None
) -> dict:
    """CMA-ES on the kick for `config.target`; writes out_dir/{progress.csv, kick_prior.json}.

    start: params (14,) to start from (default: the committed prior if there is one, else
    DEFAULT_PARAMS), with strength set to config.start_strength. Returns the saved record.
    """
    from evosax.algorithms import CMA_ES  # heavy import, only needed here

    cfg = make_config(config)
    validate_config(cfg)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if start is None:
        start = load_prior()["params"] if PRIOR_JSON.exists() else DEFAULT_PARAMS
    x0 = np.array(start, dtype=np.float32)
    x0[PARAM_NAMES.index("strength")] = cfg.start_strength
    free = _free_mask(cfg)
    scale = jnp.asarray(PARAM_SCALE[free], jnp.float32)

    env = env or _env_for(cfg)
    rollout = rollout or make_rollout(env)  # pass one in to share its compiled program
    P, R = cfg.population_size, cfg.repetitions

    def to_params(z):  # (P, F) search coordinates -> (P, 14) clipped params
        return clip_params(jnp.tile(x0, (z.shape[0], 1)).at[:, free].add(scale * z))

    def generation_cost(z, key):
        # Common random numbers: every candidate meets the same R noisy episodes, so the
        # ranking compares kicks, not luck.
        keys = jnp.broadcast_to(jax.random.split(key, R), (P, R) + key.shape)
        out = rollout(to_params(z), keys, cfg.target)
        return jnp.mean(fitness(out, cfg.target, cfg.fitness), axis=1), out

    es = CMA_ES(population_size=P, solution=jnp.zeros(int(free.sum())))
    es_params = es.default_params.replace(std_init=jnp.asarray(cfg.sigma_init))
    key = jax.random.key(cfg.seed)
    key, init_key = jax.random.split(key)
    state = es.init(init_key, jnp.zeros(int(free.sum())), es_params)

    csv_path = out_dir / "progress.csv"
    fields = ["generation", "best_fitness", "mean_fitness", "best_so_far", "valid_fraction", "seconds"]
    with open(csv_path, "w", newline="") as f:
        csv.writer(f).writerow(fields)
    best_cost, best_z = np.inf, np.zeros(int(free.sum()), np.float32)
    for gen in range(cfg.generations):
        t0 = time.perf_counter()
        key, ask_key, eval_key, tell_key = jax.random.split(key, 4)
        z, state = es.ask(ask_key, state, es_params)
        cost, out = generation_cost(z, eval_key)
        cost = jax.block_until_ready(cost)
        state, _ = es.tell(tell_key, z, cost, state, es_params)
        i = int(jnp.argmin(cost))
        if float(cost[i]) < best_cost:
            best_cost, best_z = float(cost[i]), np.asarray(z[i])
        row = [
            gen,
            float(cost[i]),
            float(jnp.mean(cost)),
            best_cost,
            float(jnp.mean(out["valid"])),
            time.perf_counter() - t0,
        ]
        with open(csv_path, "a", newline="") as f:
            csv.writer(f).writerow(row)
        if verbose:
            print(
                f"gen {gen:3d}  best {row[1]:8.3f}  mean {row[2]:8.3f}  best so far {best_cost:8.3f}"
                f"  valid {row[4]:.2f}  {row[5]:6.1f} s",
                flush=True,
            )

    best = np.asarray(to_params(jnp.asarray(best_z)[None])[0])
    numbers = evaluate(best, cfg, env=env, rollout=rollout)
    record = prior_record(best, cfg, numbers, generations_run=cfg.generations)
    save_prior(record, out_dir / "kick_prior.json")
    return record


@functools.lru_cache(maxsize=8)
def _cost_programs(env, mesh, fitness_json: str):
    """The mean cost of kicks over noisy episodes: `cost_of` (params (P, 14), keys (P, R), target)
    -> (P,), and its jitted batch over tasks split over `mesh`, (params (T, C, 14), keys (C, R)
    shared by every task, targets (T,)) -> (T, C). Kept per settings: compiled once per process."""
    from bumps_jax import sharding  # noqa: PLC0415 (keeps `import prior` light for tests)

    weights = ml_collections.ConfigDict(json.loads(fitness_json))
    episodes = jax.vmap(jax.vmap(_episode_fn(env), in_axes=(None, 0, None)), in_axes=(0, 0, None))

    def cost_of(params, keys, target):
        return jnp.mean(fitness(episodes(params, keys, target), target, weights), axis=1)

    return cost_of, sharding.over_batch(jax.vmap(cost_of, in_axes=(0, None, 0)), mesh, (True, False, True))


@functools.lru_cache(maxsize=8)
def _tuning_programs(env, mesh, P: int, R: int, fitness_json: str, sigma_init: float):
    """`tune_for_tasks`' CMA-ES, the scale of its steps and its two jitted programs (one
    generation of every task; the final start-vs-tuned costs, `_cost_programs`). Kept per
    settings, so a repeated or resumed run of the same settings in one process does not trace
    and compile them again (about a minute on a CPU)."""
    from evosax.algorithms import CMA_ES  # heavy import, only needed here

    from bumps_jax import sharding  # noqa: PLC0415 (keeps `import prior` light for tests)

    cost_of, final = _cost_programs(env, mesh, fitness_json)
    scale = jnp.asarray(PARAM_SCALE, jnp.float32)
    es = CMA_ES(population_size=P, solution=jnp.zeros(N_PARAMS))
    es_params = es.default_params.replace(std_init=jnp.asarray(sigma_init))

    def generation(state, key, x0, target):
        ask_key, eval_key, tell_key = jax.random.split(key, 3)
        z, state = es.ask(ask_key, state, es_params)
        # Common random numbers within a task's generation, as in `optimise`.
        keys = jnp.broadcast_to(jax.random.split(eval_key, R), (P, R) + eval_key.shape)
        cost = cost_of(clip_params(x0 + scale * z), keys, target)
        state, _ = es.tell(tell_key, z, cost, state, es_params)
        return state, jnp.min(cost)

    step = sharding.over_batch(jax.vmap(generation), mesh, (True, True, True, True))
    return es, es_params, scale, step, final


def tune_for_tasks(
    targets,
    starts,
    config=None,
    generations: int = 40,
    sigma_init: float = 0.5,
    verbose: bool = True,
    env=None,
    mesh=None,
) -> dict:
    """CMA-ES on every task's own kick at once: one search per target, vmapped.

    targets: (T,) m; starts: (T, 14) params each search starts from (e.g. `kick_for` of the
    blended family). Every parameter is free; steps are in units of PARAM_SCALE. `config`
    supplies population_size, repetitions, eval_repetitions, fitness and seed. Each task keeps
    the better of its start and its final CMA-ES mean on `eval_repetitions` fresh noisy
    episodes shared by both, so a task's kick never gets worse than its start.

    Returns {"params": (T, 14), "start_cost": (T,), "tuned_cost": (T,), "improved": (T,) bool,
    "history": (generations, T) best cost per generation, "episodes": int}.
    """
    cfg = make_config(config)
    validate_config(cfg)
    targets = jnp.asarray(targets, jnp.float32)
    starts = clip_params(jnp.asarray(starts, jnp.float32))
    if targets.ndim != 1 or starts.shape != (targets.shape[0], N_PARAMS):
        raise ValueError(f"need targets (T,) and starts (T, {N_PARAMS}), got {targets.shape} and {starts.shape}")
    if not isinstance(generations, int | np.integer) or generations < 0:
        raise ValueError(f"generations must be an integer >= 0, got {generations!r}")
    kick_env.check_targets(np.asarray(targets).tolist(), cfg.task_range)
    from bumps_jax import sharding  # noqa: PLC0415 (keeps `import prior` light for tests)

    mesh = mesh or sharding.device_mesh()
    n_tasks = targets.shape[0]
    targets, starts = sharding.pad((targets, starts), sharding.padded_size(n_tasks, mesh))
    env = env or _env_for(cfg)
    P, R, T = cfg.population_size, cfg.repetitions, targets.shape[0]
    # `scale` comes with the programs so the final mean is read in the units the search stepped in.
    es, es_params, scale, step, final = _tuning_programs(env, mesh, P, R, cfg.fitness.to_json(), float(sigma_init))
    key = jax.random.key(cfg.seed)
    key, init_key = jax.random.split(key)
    state = jax.vmap(lambda k: es.init(k, jnp.zeros(N_PARAMS), es_params))(jax.random.split(init_key, T))
    # CMA-ES starts some fields weakly typed and returns them strongly typed: fix the types now
    # so that the generation program compiles once, not twice.
    state = jax.tree.map(lambda x: x.astype(x.dtype), state)
    history = []
    t0 = time.perf_counter()
    for gen in range(generations):
        key, gen_key = jax.random.split(key)
        state, best = step(*sharding.place((state, jax.random.split(gen_key, T), starts, targets), mesh))
        history.append(np.asarray(best)[:n_tasks])
        if verbose:
            print(f"tuning gen {gen + 1:3d}/{generations}  mean best cost over tasks {history[-1].mean():7.3f}"
                  f"  worst {history[-1].max():7.3f}  ({time.perf_counter() - t0:5.1f} s)", flush=True)  # fmt: skip

    tuned = clip_params(starts + scale * state.mean)
    E = cfg.eval_repetitions
    keys = jnp.broadcast_to(jax.random.split(jax.random.fold_in(key, 1), E), (2, E) + key.shape)
    costs = np.asarray(final(jnp.stack([starts, tuned], 1), keys, targets))[:n_tasks]  # (T, 2): start, tuned
    improved = costs[:, 1] < costs[:, 0]
    tuned, starts = np.asarray(tuned)[:n_tasks], np.asarray(starts)[:n_tasks]
    T = n_tasks
    return {
        "params": np.where(improved[:, None], tuned, starts),
        "start_cost": costs[:, 0],
        "tuned_cost": costs[:, 1],
        "improved": improved,
        "history": np.asarray(history).reshape(generations, T),
        "episodes": int(T * (generations * P * R + 2 * E)),
    }


def best_starts(targets, candidates, config=None, repetitions: int = 16, seed: int = 3, env=None, mesh=None):
    """Each target's best candidate kick: the lowest mean fitness over `repetitions` noisy kicks,
    the same episodes for every candidate of a target (common random numbers). Tasks are split
    over `mesh` (default: every device), in the program that scores `tune_for_tasks`' result.

    targets: (T,) m; candidates: (T, C, 14). Returns (params (T, 14), index (T,), costs (T, C)).
    """
    cfg = make_config(config)
    validate_config(cfg)
    targets = jnp.asarray(targets, jnp.float32)
    candidates = clip_params(jnp.asarray(candidates, jnp.float32))
    if targets.ndim != 1 or candidates.ndim != 3 or candidates.shape[::2] != (targets.shape[0], N_PARAMS):
        shapes = f"{targets.shape} and {candidates.shape}"
        raise ValueError(f"need targets (T,) and candidates (T, C, {N_PARAMS}), got {shapes}")
    if not isinstance(repetitions, int | np.integer) or repetitions < 1:
        raise ValueError(f"repetitions must be a positive integer, got {repetitions!r}")
    kick_env.check_targets(np.asarray(targets).tolist(), cfg.task_range)
    from bumps_jax import sharding  # noqa: PLC0415 (keeps `import prior` light for tests)

    mesh = mesh or sharding.device_mesh()
    _, costs_of = _cost_programs(env or _env_for(cfg), mesh, cfg.fitness.to_json())
    n_tasks, n_candidates = candidates.shape[:2]
    keys = jnp.broadcast_to(jax.random.split(jax.random.key(seed), repetitions), (n_candidates, repetitions))
    padded = sharding.pad((candidates, targets), sharding.padded_size(n_tasks, mesh))
    costs = np.asarray(costs_of(padded[0], keys, padded[1]))[:n_tasks]
    index = np.argmin(costs, axis=1)
    return np.asarray(candidates)[np.arange(n_tasks), index], index, costs


def sweep(anchors, strengths, config=None, repetitions: int = 8, seed: int = 2, env=None, rollout=None) -> list[dict]:
    """The blended kick at each strength: resting distance and valid fraction over noisy reps.

    anchors: (3, 14) short, main, long kicks. One rollout program for all strengths x reps.
    """
    cfg = make_config(config)
    validate_config(cfg)
    strengths = np.asarray(strengths, np.float32)
    if strengths.ndim != 1 or not np.all((strengths >= 0) & (strengths <= 1)):
        raise ValueError(f"strengths must be a 1-d list in [0, 1], got {strengths.tolist()!r}")
    batch = jax.vmap(blend_params, in_axes=(None, 0))(jnp.asarray(anchors), jnp.asarray(strengths))
    rollout = rollout or make_rollout(env or _env_for(cfg))
    keys = jax.random.split(jax.random.key(seed), repetitions)
    keys = jnp.broadcast_to(keys, (len(strengths), repetitions))
    out = rollout(batch, keys, cfg.target)
    rows = []
    for i, st in enumerate(strengths):
        rows.append({
            "strength": float(st),
            "distance_m": float(jnp.mean(out["distance"][i])),
            "distance_std_m": float(jnp.std(out["distance"][i])),
            "lateral_m": float(jnp.mean(out["lateral"][i])),
            "valid_fraction": float(jnp.mean(out["valid"][i])),
            "fallen_fraction": float(jnp.mean(out["fallen"][i])),
        })  # fmt: skip
    return rows


# -- the saved prior --------------------------------------------------------------------------


def prior_record(params, cfg, numbers: dict, **extra) -> dict:
    """The JSON-able record of a prior: params, names, config, evaluation, format version."""
    return {
        "format_version": FORMAT_VERSION,
        "param_names": list(PARAM_NAMES),
        "params": [float(x) for x in np.asarray(params)],
        "config": json.loads(cfg.to_json()),
        "evaluation": numbers,
        **extra,
    }


def record_from_payload(payload: dict) -> dict:
    """The prior record of a kick-prior run made before runs kept theirs (RUN_PRIOR_JSON), from
    the run's kick_prior.json: its 12 m kick, anchors and sweep, which is all the later stages
    read. The evaluation holds only the numbers the payload kept."""
    evaluation = {"repetitions": payload["n_reps"], "target": payload["target_m"],
                  "mean_error": payload["mean_error_m"], "std_error": payload["std_error_m"],
                  **{k: payload[k] for k in ("valid_fraction", "struck_fraction", "fallen_fraction")}}  # fmt: skip
    cfg = make_config(None, PRESETS[payload["preset"]])
    return prior_record(payload["anchors"]["main"], cfg, evaluation, generations_run=payload["generations"],
                        anchors=payload["anchors"], sweep=payload["sweep"])  # fmt: skip


def save_prior(record: dict, path: str | Path = PRIOR_JSON) -> None:
    Path(path).write_text(json.dumps(record, indent=2) + "\n")


def load_prior(path: str | Path = PRIOR_JSON) -> dict:
    """The saved prior as a dict; record['params'] is a float32 array (14,), in PARAM_NAMES order.

    ValueError if the file's format version or parameter names do not match this code.
    """
    record = json.loads(Path(path).read_text())
    if record.get("format_version") != FORMAT_VERSION:
        version = record.get("format_version")
        raise ValueError(f"{path}: format_version {version!r}, expected {FORMAT_VERSION}")
    if tuple(record.get("param_names", ())) != PARAM_NAMES:
        raise ValueError(f"{path}: param_names {record.get('param_names')!r} do not match {PARAM_NAMES}")
    record["params"] = np.asarray(record["params"], np.float32)
    if "anchors" in record:
        record["anchors"] = np.asarray([record["anchors"][n] for n in ANCHORS], np.float32)
    return record


PRESETS = {
    # CPU-sized: a few generations, to show the machinery end to end.
    "tiny": {"population_size": 8, "generations": 3, "repetitions": 2, "eval_repetitions": 8},
    "paper": {"population_size": 64, "generations": 80, "repetitions": 16, "eval_repetitions": 100},
}
SWEEP_STRENGTHS = tuple(i / 8 for i in range(9))
# The ends of the reachable range, each optimised on its own with every parameter free.
EXTREMES = {"short": 6.0, "long": 21.0}


def run_stage(preset: str, run_dir: str | Path, overrides: dict | None = None, publish: bool = False) -> dict:
    """`make kick-prior`: optimise the 12 m prior (from the committed one), evaluate it, optimise
    the short and long extremes from it, sweep the blended family over strength; write
    run_dir/{kick_prior.json, kick_sweep.png, RUN_PRIOR_JSON} and, if `publish`, the prior to
    assets/ (the same record as run_dir/RUN_PRIOR_JSON).
    """
    from bumps_jax import results  # noqa: PLC0415 (keeps `import prior` light for tests)

    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose from {sorted(PRESETS)}")
    t0 = time.perf_counter()
    run_dir = Path(run_dir)
    cfg = make_config(None, {**PRESETS[preset], **(overrides or {})})
    validate_config(cfg)
    env = _env_for(cfg)
    rollout = make_rollout(env)  # one jitted program, compiled once per batch shape
    # `optimise` already scores its best kick over eval_repetitions fresh noisy episodes.
    main = optimise(cfg, run_dir / "main", env=env, rollout=rollout)
    main_params, evaluation = main["params"], main["evaluation"]
    optimise_s = time.perf_counter() - t0
    anchors = {"main": np.asarray(main_params)}
    extremes = {}
    for name, target in EXTREMES.items():
        ext_cfg = make_config(cfg, {"target": target, "free_params": PARAM_NAMES})
        ext = optimise(ext_cfg, run_dir / name, start=main_params, env=env, rollout=rollout)
        anchors[name], ext_eval = np.asarray(ext["params"]), ext["evaluation"]
        extremes[name] = {"target_m": target, "mean_error_m": ext_eval["mean_error"],
                          "mean_distance_m": ext_eval["mean_distance"], "valid_fraction": ext_eval["valid_fraction"],
                          "fallen_fraction": ext_eval["fallen_fraction"]}  # fmt: skip
    stacked = np.stack([anchors[n] for n in ANCHORS])
    rows = sweep(stacked, SWEEP_STRENGTHS, cfg, repetitions=max(4, cfg.eval_repetitions // 4), env=env, rollout=rollout)
    payload = {
        **results.provenance(preset, time.perf_counter() - t0, physics_dt_s=env.physics_dt),
        "target_m": float(cfg.target),
        "n_reps": int(cfg.eval_repetitions),
        "mean_error_m": evaluation["mean_error"],
        "std_error_m": evaluation["std_error"],
        "valid_fraction": evaluation["valid_fraction"],
        "fallen_fraction": evaluation["fallen_fraction"],
        "struck_fraction": evaluation["struck_fraction"],
        "optimise_wall_s": optimise_s,
        "generations": int(cfg.generations),
        "population_size": int(cfg.population_size),
        "repetitions_per_candidate": int(cfg.repetitions),
        "sweep": rows,
        "extremes": extremes,
        "anchors": {n: [float(x) for x in anchors[n]] for n in ANCHORS},
    }
    record = prior_record(main_params, cfg, evaluation, generations_run=cfg.generations,
                          anchors=payload["anchors"], sweep=rows)  # fmt: skip
    results.write_json(run_dir / "kick_prior.json", payload)
    results.write_json(run_dir / "kick_prior_timing.json", timing_record(payload))
    save_prior(record, run_dir / RUN_PRIOR_JSON)
    plot_sweep(payload, run_dir / "kick_sweep.png")
    if publish:  # the committed copies: results/, benchmarks/results/, docs/ and the asset
        root = PRIOR_JSON.parent.parent
        results.write_json(root / "results" / "kick_prior.json", payload)
        results.write_json(root / "benchmarks" / "results" / "kick_prior.json", timing_record(payload))
        plot_sweep(payload, root / "docs" / "kick_sweep.png")
        save_prior(record, PRIOR_JSON)
    return payload


def timing_record(payload: dict) -> dict:
    """The benchmark view of a kick-prior run: its provenance and wall times, nothing else."""
    keys = ("device", "n_devices", "versions", "date", "command", "preset", "wall_s", "optimise_wall_s",
            "generations", "population_size", "repetitions_per_candidate")  # fmt: skip
    episodes = payload["generations"] * payload["population_size"] * payload["repetitions_per_candidate"]
    return {
        **{k: payload[k] for k in keys},
        "episodes_per_optimisation": episodes,
        "episodes_per_s": episodes / payload["optimise_wall_s"],
    }


def plot_sweep(payload: dict, path: str | Path) -> None:
    """Resting distance vs strength along the short -> 12 m -> long family, with the task range."""
    import matplotlib

    from bumps_jax import results  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = payload["sweep"]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.errorbar(
        [r["strength"] for r in rows],
        [r["distance_m"] for r in rows],
        yerr=[r["distance_std_m"] for r in rows],
        marker="o",
        capsize=3,
        label="mean +- std over noisy kicks",
    )
    for r in rows:
        ax.annotate(
            f"{r['valid_fraction']:.2f}",
            (r["strength"], r["distance_m"]),
            textcoords="offset points",
            xytext=(4, -12),
            fontsize=7,
        )
    ax.axhspan(7.0, 18.0, color="green", alpha=0.1, label="task range 7-18 m")
    ax.set_xlabel("strength (0 = short kick, 0.5 = 12 m prior, 1 = long kick)")
    ax.set_ylabel("resting distance (m)")
    ax.set_title(f"Reachable range, valid fraction annotated ({payload['device']})", fontsize=9)
    ax.legend(fontsize=8)
    results.save_figure(fig, path)
