"""Can a re-optimised kick meet the ball through its centre, and is it then less sensitive?

Every kick the prior and the experts start from touches the ball 2.5-3.5 cm above its centre
(`impact_geometry.py`), and small changes of the ball's placement move where it stops by metres.
This searches the same 14-parameter kick family from several starting kicks, for several
targets, with CMA-ES (`bumps_jax.tasks.kick.cmaes`: all searches in one program per generation), twice over:

- `control`: the prior's own fitness (resting error, sideways error, invalid kicks);
- `centred`: the same plus `--height-weight` per metre of how far above or below the ball's
  centre the foot is when it first reaches the ball.

Each search's final mean is then replayed over `--eval-reps` noisy episodes (fresh keys, the
same for every search), as are the experts' starting kicks at the same targets. The question
is answered by the spread of the resting distance (its std) among kicks of similar length.
The strike height is measured in the last state before the ball has moved `MOVED` m: the point
of the kicking foot's box nearest the ball's centre, its height above that centre.

Writes <out-dir>/<name>_<device>.json and, for the best kick of each target and kind,
<out-dir>/<name>_kicks_<kind>_<device>.json in the starting-kicks format, which
`impact_geometry.py` and `noise_sources.py` replay (--name: strike_search by default).

    python experiments/strike_search.py --targets 8 12 16 --generations 60
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from bumps_jax import config, runio

# Starting kicks besides the committed prior's anchors: a straighter kicking leg that winds
from bumps_jax.algo import rollout, sharding
from bumps_jax.tasks.kick import cmaes, starting_kicks

# Starting kicks besides the committed prior's anchors: a straighter kicking leg that winds
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model

# Starting kicks besides the committed prior's anchors: a straighter kicking leg that winds
# back less (the foot stays lower through the swing), varied in the knee and hip of the swing.
_STRAIGHT_VALUES = (13.0, 0.0, 8.0, 0.3, 0.15, -10.0, -20.0, 0.0, 0.15, 40.0, 30.0, 0.0, 0.12, 0.75)
_STRAIGHT = dict(zip(kick_model.PARAM_NAMES, _STRAIGHT_VALUES, strict=True))
# The ball counts as struck once its centre has moved this far (m) across the floor from its start.
MOVED = 0.002
# Strike height recorded for a kick that never moves the ball (m).
NO_STRIKE = 0.1


def start_kicks() -> dict[str, np.ndarray]:
    """Name -> kick params (14,), inside the bounds: the default kick, the committed prior's
    anchors and the straight-leg variants."""
    starts = {"default": kick_model.DEFAULT_PARAMS}
    record = kick_model.load_record()
    for name, params in zip(kick_model.ANCHORS, record["anchors"], strict=True):
        starts[f"prior_{name}"] = params
    for back_knee in (-20.0, -50.0):
        for swing_knee in (10.0, 40.0):
            for swing_hip in (35.0, 60.0):
                p = dict(_STRAIGHT, back_knee=back_knee, swing_knee=swing_knee, swing_hip=swing_hip)
                starts[f"straight_bk{back_knee:.0f}_sk{swing_knee:.0f}_sh{swing_hip:.0f}"] = np.array(
                    [p[n] for n in kick_model.PARAM_NAMES]
                )
    return {k: np.asarray(kick_model.clip_params(jnp.asarray(v, jnp.float32))) for k, v in starts.items()}


def strike_height(env: kick_env.KickEnv):
    """fn(data) -> height (m) of the kicking foot's point nearest the ball's centre above that
    centre; data: MJX or C MuJoCo data with its kinematics computed."""
    ids = env.ids
    half = jnp.asarray(env.mj_model.geom_size[ids.l_foot_geom])

    def measure(data):
        centre = jnp.asarray(data.qpos[ids.ball_qpos : ids.ball_qpos + 3])
        rot = jnp.asarray(data.geom_xmat[ids.l_foot_geom]).reshape(3, 3)
        origin = jnp.asarray(data.geom_xpos[ids.l_foot_geom])
        nearest = origin + rot @ jnp.clip(rot.T @ (centre - origin), -half, half)
        return nearest[2] - centre[2]

    return measure


def outcome_fn(env: kick_env.KickEnv):
    """(params (14,), target, key) -> the env's final metrics plus `height` (m; NO_STRIKE if the
    ball never moved), from the qpos after every control step (`rollout.episode_fn`)."""
    episode = rollout.episode_fn(env, rollout.table_policy, record="qpos")
    measure = strike_height(env)
    ball = slice(env.ids.ball_qpos, env.ids.ball_qpos + 2)

    def outcome(params, target, key):
        metrics, qpos = episode(kick_model.keyframes_to_actions(params, env.n_steps, env.dt), target, target, key)
        start = env.reset(key, target).pipeline_state.qpos
        before = jnp.concatenate([start[None], qpos[:-1]])  # the state before each step
        moved = jnp.linalg.norm(qpos[:, ball] - start[ball], axis=-1) > MOVED
        data = mjx.make_data(env.mjx_model).replace(qpos=before[jnp.argmax(moved)])
        height = measure(mjx.kinematics(env.mjx_model, data))
        return {**metrics, "height": jnp.where(moved.any(), height, NO_STRIKE)}

    return outcome


def height_cost(env: kick_env.KickEnv, fitness):
    """A `cmaes.make_search` cost: the prior's fitness plus `extra` (the search's height weight)
    per metre of strike height."""
    outcomes = jax.vmap(jax.vmap(outcome_fn(env), in_axes=(None, None, 0)), in_axes=(0, None, 0))

    def cost_fn(params, keys, target, weight):
        out = outcomes(params, target, keys)
        cost = kick_model.fitness(out, target, fitness) + weight * jnp.abs(out["height"])
        return jnp.mean(cost, axis=1), out

    return cost_fn


def summarise(out: dict, i: int) -> dict:
    distance, error = np.asarray(out["distance"][i]), np.asarray(out["final_error"][i])
    height = np.asarray(out["height"][i])
    return {
        "distance_mean_m": float(distance.mean()),
        "distance_std_m": float(distance.std()),
        "error_mean_m": float(error.mean()),
        "lateral_mean_m": float(np.mean(out["lateral"][i])),
        "valid_fraction": float(np.mean(out["valid"][i])),
        "height_mean_cm": float(100 * height.mean()),
        "height_std_cm": float(100 * height.std()),
    }


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--targets", type=float, nargs="+", default=[8.0, 12.0, 16.0])
    parser.add_argument("--generations", type=int, default=60)
    parser.add_argument("--population", type=int, default=24)
    parser.add_argument("--repetitions", type=int, default=8, help="noisy episodes per candidate")
    parser.add_argument("--sigma", type=float, default=2.0, help="CMA-ES step, in units of the prior's scale")
    parser.add_argument("--height-weight", type=float, default=30.0, help="cost per metre of strike height")
    parser.add_argument("--eval-reps", type=int, default=100)
    parser.add_argument("--starts", nargs="+", default=None, help="names of the starting kicks to use (default: all)")
    parser.add_argument("--kinds", nargs="+", default=["control", "centred"], choices=["control", "centred"])
    parser.add_argument("--kicks", default="docs/experts_starting_kicks.json", help="reference kicks to replay")
    parser.add_argument("--physics-dt", type=float, default=None, help="physics step (s); default: the scene's")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out-dir", default="experiments/results")
    parser.add_argument("--name", default="strike_search", help="stem of the files written")
    args = parser.parse_args(argv)
    for name in ("generations", "population", "repetitions", "eval_reps"):
        if getattr(args, name) < (2 if name in ("population", "eval_reps") else 1):
            parser.error(f"--{name.replace('_', '-')} is too small: {getattr(args, name)}")
    if not args.sigma > 0:
        parser.error(f"--sigma must be > 0, got {args.sigma}")
    return parser, args


def setup(argv=None):
    """(args, env, reference kicks, starting kicks), every argument checked (parser errors)."""
    parser, args = parse_args(argv)
    task_range = tuple(config.default_config().prior.task_range)
    try:
        env = kick_env.KickEnv(None, {"task_range": task_range, "physics_dt": args.physics_dt})
    except ValueError as err:
        parser.error(f"--physics-dt: {err}")
    try:
        kick_env.check_targets(args.targets, env.config.task_range)
        reference = starting_kicks.read_starting_kicks(
            args.kicks, [t for t in args.targets if t in kick_env.meta_train_tasks()]
        )
    except ValueError as err:
        parser.error(str(err))
    starts = start_kicks()
    if args.starts:
        unknown = [s for s in args.starts if s not in starts]
        if unknown:
            parser.error(f"--starts: unknown {unknown}; choose from {sorted(starts)}")
        starts = {s: starts[s] for s in args.starts}
    return args, env, reference, starts


def search(args, env, starts, kinds):
    """Every (target, start, kind) search at once: (rows, final means (N, 14), the driver's key)."""
    rows = [(t, s, k) for t in args.targets for s in starts for k in kinds]
    x0 = np.stack([starts[s] for _, s, _ in rows])
    fitness = config.default_config().prior.fitness
    searches = cmaes.make_search(height_cost(env, fitness), args.population, args.repetitions, args.sigma,
                                 sharding.device_mesh(impl=env.config.impl))  # fmt: skip
    result = cmaes.run_search(searches, x0, [t for t, _, _ in rows], np.ones_like(x0, bool), args.generations,
                              args.seed, extra=[kinds[k] for _, _, k in rows], label="strike search")  # fmt: skip
    return rows, result.mean, result.key


def main(argv=None) -> None:
    args, env, reference, starts = setup(argv)
    kinds = {k: w for k, w in {"control": 0.0, "centred": args.height_weight}.items() if k in args.kinds}
    t0 = time.perf_counter()
    rows, found, key = search(args, env, starts, kinds)
    search_s = time.perf_counter() - t0

    ref_targets = list(reference)
    params = np.concatenate([found, *([np.stack([reference[t] for t in ref_targets])] if ref_targets else [])])
    all_targets = np.asarray([t for t, _, _ in rows] + ref_targets, np.float32)
    # The same noisy episodes for every kick: differences are the kicks', not the noise's.
    keys = jnp.broadcast_to(jax.random.split(jax.random.fold_in(key, 1), args.eval_reps), (len(params), args.eval_reps))
    replay = jax.jit(jax.vmap(jax.vmap(outcome_fn(env), in_axes=(None, None, 0)), in_axes=(0, 0, 0)))
    out = replay(jnp.asarray(params), jnp.asarray(all_targets), keys)
    searches = [
        {"target_m": t, "start": s, "kind": k, **summarise(out, i), "params": found[i].tolist()}
        for i, (t, s, k) in enumerate(rows)
    ]
    references = [
        {"target_m": t, **summarise(out, len(rows) + j), "params": reference[t].tolist()}
        for j, t in enumerate(ref_targets)
    ]
    best = {}
    for t in args.targets:
        for k in kinds:
            mine = [r for r in searches if r["target_m"] == t and r["kind"] == k and r["valid_fraction"] >= 0.95]
            if mine:
                best[f"{t}/{k}"] = min(mine, key=lambda r: r["error_mean_m"])
    report(best, references)
    payload = {
        "settings": {k: v for k, v in vars(args).items() if k not in ("out_dir", "name")},
        "noise": dict(env.config.noise),
        "search_wall_s": search_s,
        "best": best,
        "references": references,
        "searches": searches,
        **runio.provenance("strike_search", time.perf_counter() - t0, kick_env.resolved(env.config)),
    }
    write(args, kinds, best, payload)


def report(best: dict, references: list) -> None:
    for name, r in best.items():
        print(f"{name:14s} distance {r['distance_mean_m']:6.2f} +- {r['distance_std_m']:.2f} m  error "
              f"{r['error_mean_m']:.2f} m  valid {r['valid_fraction']:.2f}  strike {r['height_mean_cm']:+.1f} cm"
              f"  ({r['start']})")  # fmt: skip
    for r in references:
        print(f"{r['target_m']:5.1f}/starting distance {r['distance_mean_m']:6.2f} +- {r['distance_std_m']:.2f} m"
              f"  error {r['error_mean_m']:.2f} m  strike {r['height_mean_cm']:+.1f} cm")  # fmt: skip


def write(args, kinds, best: dict, payload: dict) -> None:
    out_dir = Path(args.out_dir)
    path = runio.write_experiment(out_dir, args.name, payload)
    print(path)
    device = path.stem.rsplit("_", 1)[1]
    kicks = sorted(best.items(), key=lambda kv: kv[1]["target_m"])
    # One file per kind, so that each reads as a starting-kicks record (unique targets).
    for k in kinds:
        chosen = [r for name, r in kicks if name.endswith("/" + k)]
        if chosen:
            record = {"tasks_m": [r["target_m"] for r in chosen], "params": [r["params"] for r in chosen]}
            print(runio.write_json(out_dir / f"{args.name}_kicks_{k}_{device}.json", record))


if __name__ == "__main__":
    main()
