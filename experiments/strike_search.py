"""Can a re-optimised kick meet the ball through its centre, and is it then less sensitive?

Every kick the prior and the experts start from touches the ball 2.5-3.5 cm above its centre
(`impact_geometry.py`), and small changes of the ball's placement move where it stops by metres.
This searches the same 14-parameter kick family from several starting kicks, for several
targets, with CMA-ES (all searches vmapped into one program per generation), twice over:

- `control`: the prior's own fitness (resting error, sideways error, invalid kicks);
- `centred`: the same plus `--height-weight` per metre of how far above or below the ball's
  centre the foot is when it first reaches the ball.

Each search's final mean is then replayed over `--eval-reps` noisy episodes (fresh keys, the
same for every search), as are the experts' starting kicks at the same targets. The question
is answered by the spread of the resting distance (its std) among kicks of similar length.
The strike height is measured at the last control step before the ball moves: the point of
the kicking foot's box nearest the ball's centre, its height above that centre.

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
import ml_collections
import numpy as np

from bumps_jax import experts, kick_env, prior, results

# Starting kicks besides the committed prior's anchors: a straighter kicking leg that winds
# back less (the foot stays lower through the swing), varied in the knee and hip of the swing.
_STRAIGHT_VALUES = (13.0, 0.0, 8.0, 0.3, 0.15, -10.0, -20.0, 0.0, 0.15, 40.0, 30.0, 0.0, 0.12, 0.75)
_STRAIGHT = dict(zip(prior.PARAM_NAMES, _STRAIGHT_VALUES, strict=True))


def start_kicks() -> dict[str, np.ndarray]:
    starts = {"default": prior.DEFAULT_PARAMS}
    record = prior.load_prior()
    for name, params in zip(prior.ANCHORS, record["anchors"], strict=True):
        starts[f"prior_{name}"] = params
    for back_knee in (-20.0, -50.0):
        for swing_knee in (10.0, 40.0):
            for swing_hip in (35.0, 60.0):
                p = dict(_STRAIGHT, back_knee=back_knee, swing_knee=swing_knee, swing_hip=swing_hip)
                starts[f"straight_bk{back_knee:.0f}_sk{swing_knee:.0f}_sh{swing_hip:.0f}"] = np.array(
                    [p[n] for n in prior.PARAM_NAMES]
                )
    return {k: np.asarray(prior.clip_params(jnp.asarray(v, jnp.float32))) for k, v in starts.items()}


def strike_height(env: kick_env.KickEnv):
    """fn(data) -> (height of the foot point nearest the ball's centre above it, m; ball speed)."""
    ids = env.ids
    half = jnp.asarray(env.mj_model.geom_size[ids.l_foot_geom])

    def measure(data):
        centre = data.qpos[ids.ball_qpos : ids.ball_qpos + 3]
        rot = data.geom_xmat[ids.l_foot_geom].reshape(3, 3)
        origin = data.geom_xpos[ids.l_foot_geom]
        nearest = origin + rot @ jnp.clip(rot.T @ (centre - origin), -half, half)
        speed = jnp.linalg.norm(data.qvel[ids.ball_qvel : ids.ball_qvel + 3])
        return nearest[2] - centre[2], speed

    return measure


def episode_fn(env: kick_env.KickEnv):
    """(params (14,), key, target) -> outcome dict: the env's final metrics, `distance`,
    `lateral` (as `prior.make_rollout`) and `height` (m; 0.1 if the ball never moved)."""
    measure = strike_height(env)

    def episode(params, key, target):
        actions = prior.keyframes_to_actions(params, env.n_steps, env.dt)
        state = env.reset(key, target)

        def body(s, a):
            before, _ = measure(s.pipeline_state)
            s = env.step(s, a)
            _, speed = measure(s.pipeline_state)
            return s, (before, speed)

        state, (height, speed) = jax.lax.scan(body, state, actions)
        moved = speed > 0.1
        out = dict(state.metrics)
        target_xy = state.info["target_xy"]
        out["distance"] = out["rest_x"] - (target_xy[0] - state.info["target"])
        out["lateral"] = out["rest_y"] - target_xy[1]
        out["height"] = jnp.where(moved.any(), height[jnp.argmax(moved)], 0.1)
        return out

    return episode


def make_search(env, population: int, repetitions: int, sigma: float, weights):
    """(init, generation) of one CMA-ES search; vmap both over searches."""
    from evosax.algorithms import CMA_ES

    episodes = jax.vmap(jax.vmap(episode_fn(env), in_axes=(None, 0, None)), in_axes=(0, 0, None))
    scale = jnp.asarray(prior.PARAM_SCALE, jnp.float32)
    es = CMA_ES(population_size=population, solution=jnp.zeros(prior.N_PARAMS))
    es_params = es.default_params.replace(std_init=jnp.asarray(sigma))

    def init(key):
        return es.init(key, jnp.zeros(prior.N_PARAMS), es_params)

    def generation(state, key, x0, target, height_weight):
        ask_key, eval_key, tell_key = jax.random.split(key, 3)
        z, state = es.ask(ask_key, state, es_params)
        keys = jnp.broadcast_to(jax.random.split(eval_key, repetitions), (population, repetitions))
        out = episodes(prior.clip_params(x0 + scale * z), keys, target)
        cost = prior.fitness(out, target, weights) + height_weight * jnp.abs(out["height"])
        cost = jnp.mean(cost, axis=1)
        state, _ = es.tell(tell_key, z, cost, state, es_params)
        return state, jnp.min(cost)

    return init, generation, scale


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


def main(argv=None) -> None:
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
    try:
        env = kick_env.KickEnv(
            config_overrides={"task_range": prior.default_config().task_range, "physics_dt": args.physics_dt}
        )
    except ValueError as err:
        parser.error(f"--physics-dt: {err}")
    try:
        kick_env.check_targets(args.targets, env.config.task_range)
        on_tasks = [t for t in args.targets if t in kick_env.meta_train_tasks()]
        reference = experts.read_starting_kicks(args.kicks, on_tasks)
    except ValueError as err:
        parser.error(str(err))

    starts = start_kicks()
    if args.starts:
        unknown = [s for s in args.starts if s not in starts]
        if unknown:
            parser.error(f"--starts: unknown {unknown}; choose from {sorted(starts)}")
        starts = {s: starts[s] for s in args.starts}
    kinds = {k: w for k, w in {"control": 0.0, "centred": args.height_weight}.items() if k in args.kinds}
    rows = [(t, s, k) for t in args.targets for s in starts for k in kinds]
    x0 = jnp.asarray(np.stack([starts[s] for _, s, _ in rows]), jnp.float32)
    targets = jnp.asarray([t for t, _, _ in rows], jnp.float32)
    weights_h = jnp.asarray([kinds[k] for _, _, k in rows], jnp.float32)
    fitness_weights = ml_collections.ConfigDict(prior.default_config().fitness)
    init, generation, scale = make_search(env, args.population, args.repetitions, args.sigma, fitness_weights)
    step = jax.jit(jax.vmap(generation))

    t0 = time.perf_counter()
    key = jax.random.key(args.seed)
    key, init_key = jax.random.split(key)
    state = jax.vmap(init)(jax.random.split(init_key, len(rows)))
    state = jax.tree.map(lambda x: x.astype(x.dtype), state)  # weak types would compile twice
    for gen in range(args.generations):
        key, gen_key = jax.random.split(key)
        state, best = step(state, jax.random.split(gen_key, len(rows)), x0, targets, weights_h)
        best = np.asarray(best)
        if gen % 5 == 0 or gen == args.generations - 1:
            per_kind = {k: float(np.mean(best[[r[2] == k for r in rows]])) for k in kinds}
            print(f"gen {gen + 1:3d}/{args.generations}  mean best cost {per_kind}  ({time.perf_counter() - t0:.0f} s)",
                  flush=True)  # fmt: skip
    search_s = time.perf_counter() - t0

    found = np.asarray(prior.clip_params(x0 + scale * state.mean))
    ref_targets = list(reference)
    params = np.concatenate([found, np.stack([reference[t] for t in ref_targets])]) if ref_targets else found
    all_targets = np.concatenate([np.asarray(targets), np.asarray(ref_targets, np.float32)])
    # The same noisy episodes for every kick: differences are the kicks', not the noise's.
    keys = jnp.broadcast_to(jax.random.split(jax.random.fold_in(key, 1), args.eval_reps), (len(params), args.eval_reps))
    replay = jax.jit(jax.vmap(jax.vmap(episode_fn(env), in_axes=(None, 0, None)), in_axes=(0, 0, 0)))
    out = replay(jnp.asarray(params), keys, jnp.asarray(all_targets))
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
    for name, r in best.items():
        print(f"{name:14s} distance {r['distance_mean_m']:6.2f} +- {r['distance_std_m']:.2f} m  error "
              f"{r['error_mean_m']:.2f} m  valid {r['valid_fraction']:.2f}  strike {r['height_mean_cm']:+.1f} cm"
              f"  ({r['start']})")  # fmt: skip
    for r in references:
        print(f"{r['target_m']:5.1f}/starting distance {r['distance_mean_m']:6.2f} +- {r['distance_std_m']:.2f} m"
              f"  error {r['error_mean_m']:.2f} m  strike {r['height_mean_cm']:+.1f} cm")  # fmt: skip
    payload = {
        "settings": {k: v for k, v in vars(args).items() if k not in ("out_dir", "name")},
        "noise": dict(env.config.noise),
        "search_wall_s": search_s,
        "best": best,
        "references": references,
        "searches": searches,
        **results.provenance("strike_search", time.perf_counter() - t0, physics_dt_s=env.physics_dt),
    }
    device = "cpu" if jax.default_backend() == "cpu" else "gpu"
    out_dir = Path(args.out_dir)
    print(results.write_json(out_dir / f"{args.name}_{device}.json", payload))
    kicks = sorted(best.items(), key=lambda kv: kv[1]["target_m"])
    # One file per kind, so that each reads as a starting-kicks record (unique targets).
    for k in kinds:
        chosen = [r for name, r in kicks if name.endswith("/" + k)]
        if chosen:
            record = {"tasks_m": [r["target_m"] for r in chosen], "params": [r["params"] for r in chosen]}
            print(results.write_json(out_dir / f"{args.name}_kicks_{k}_{device}.json", record))


if __name__ == "__main__":
    main()
