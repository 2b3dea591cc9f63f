"""How much of a kick's spread each of the task's noise sources causes.

Replays the experts' starting kicks (one open-loop keyframe kick per task, from an experts
run's starting_kicks.json) over the same number of episodes with all noise, with none, and
with each source alone. The policies see only (phase, target), so no policy can react to
the noise: the spread that remains is what a single open-loop kick cannot remove.
Writes <out-dir>/noise_sources_<device>.json.

    python experiments/noise_sources.py --kicks docs/experts_starting_kicks.json --targets 12 18
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax import cli, config, runio
from bumps_jax.algo import rollout
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model
from bumps_jax.tasks.kick import starting_kicks


def noise_settings(env_cfg) -> dict[str, dict]:
    """Name -> config overrides (env.noise.*): all of env_cfg's noise sources, none, and each alone."""
    sources = dict(env_cfg.noise)
    settings = {"all": {}, "none": {f"env.noise.{k}": 0.0 for k in sources}}
    for name in sources:
        settings[f"only_{name}"] = {f"env.noise.{k}": 0.0 for k in sources if k != name}
    return settings


def spread(env: kick_env.KickEnv, kicks: dict, repetitions: int, seed: int) -> dict[float, dict]:
    """Each kick (target m -> params (14,)) on its own target, the same `repetitions` noisy
    episodes each: resting distance mean and std, final error, valid fraction."""
    targets = np.asarray(list(kicks), np.float32)
    tables = kick_model.action_tables(np.stack(list(kicks.values())), env.n_steps, env.config.ctrl_dt)
    keys = jnp.broadcast_to(jax.random.split(jax.random.key(seed), repetitions), (len(targets), repetitions))
    out = rollout.matched_fn(env, rollout.table_policy)(tables, jnp.asarray(targets), jnp.asarray(targets), keys)
    distance, error = np.asarray(out["distance"]), np.asarray(out["final_error"])
    return {
        float(t): {
            "distance_mean_m": float(distance[i].mean()),
            "distance_std_m": float(distance[i].std()),
            "error_mean_m": float(error[i].mean()),
            "valid_fraction": float(np.mean(out["valid"][i])),
        }
        for i, t in enumerate(targets)
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--kicks", default="docs/experts_starting_kicks.json", help="an experts run's starting_kicks.json"
    )
    parser.add_argument("--targets", type=float, nargs="+", default=[12.0, 18.0])
    parser.add_argument("--repetitions", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out-dir", default="experiments/results")
    parser.add_argument("--preset", default="paper", help="the config whose env (and noise) the kicks run in")
    parser.add_argument("--set", action="append", nargs="+", default=[], metavar="KEY=VALUE",
                        help="config overrides, e.g. env.physics_dt=0.005")  # fmt: skip
    args = parser.parse_args(argv)
    if args.repetitions < 2:
        parser.error(f"--repetitions must be at least 2, got {args.repetitions}")
    try:
        overrides = cli.parse_overrides(args.set)
        cfg = config.make_config(args.preset, overrides)
        kick_env.check_targets(args.targets, cfg.env.task_range)
        kicks = starting_kicks.read_starting_kicks(args.kicks, args.targets)
    except ValueError as err:
        parser.error(str(err))

    start = time.perf_counter()
    rows = {str(t): {} for t in kicks}
    for name, noise in noise_settings(cfg.env).items():
        env = kick_env.KickEnv(config.make_config(args.preset, {**overrides, **noise}).env)
        for target, row in spread(env, kicks, args.repetitions, args.seed).items():
            rows[str(target)][name] = row
            print(
                f"{target:5.1f} m  {name:20s} distance {row['distance_mean_m']:6.2f} +- {row['distance_std_m']:.2f} m"
                f"  error {row['error_mean_m']:.2f} m  valid {row['valid_fraction']:.2f}",
                flush=True,
            )
    payload = {"kicks": args.kicks, "repetitions": args.repetitions, "noise": dict(cfg.env.noise), "targets": rows}
    print(runio.write_experiment(args.out_dir, "noise_sources", payload, cfg, time.perf_counter() - start))


if __name__ == "__main__":
    main()
