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
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax import experts, kick_env, prior, results


def noise_settings() -> dict[str, dict]:
    """Name -> noise overrides: all sources, none, and each source alone."""
    sources = dict(kick_env.default_config().noise)
    settings = {"all": {}, "none": {f"noise.{k}": 0.0 for k in sources}}
    for name in sources:
        settings[f"only_{name}"] = {f"noise.{k}": 0.0 for k in sources if k != name}
    return settings


def spread(params: np.ndarray, target: float, overrides: dict, repetitions: int, seed: int) -> dict:
    env = kick_env.KickEnv(config_overrides=overrides)
    rollout = prior.make_rollout(env)
    keys = jax.random.split(jax.random.key(seed), repetitions)[None]
    out = rollout(jnp.asarray(params, jnp.float32)[None], keys, target)
    distance = np.asarray(out["distance"][0])
    error = np.asarray(out["final_error"][0])
    return {
        "distance_mean_m": float(distance.mean()),
        "distance_std_m": float(distance.std()),
        "error_mean_m": float(error.mean()),
        "valid_fraction": float(np.mean(out["valid"][0])),
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
    args = parser.parse_args(argv)
    if args.repetitions < 2:
        parser.error(f"--repetitions must be at least 2, got {args.repetitions}")
    try:
        kicks = experts.read_starting_kicks(args.kicks, args.targets)
    except ValueError as err:
        parser.error(f"--targets: {err}")

    start = time.perf_counter()
    rows = {}
    for target, params in kicks.items():
        rows[str(target)] = {}
        for name, overrides in noise_settings().items():
            rows[str(target)][name] = row = spread(params, target, overrides, args.repetitions, args.seed)
            print(
                f"{target:5.1f} m  {name:20s} distance {row['distance_mean_m']:6.2f} +- {row['distance_std_m']:.2f} m"
                f"  error {row['error_mean_m']:.2f} m  valid {row['valid_fraction']:.2f}",
                flush=True,
            )
    payload = {
        "kicks": args.kicks,
        "repetitions": args.repetitions,
        "noise": dict(kick_env.default_config().noise),
        "targets": rows,
        **results.provenance("noise_sources", time.perf_counter() - start, physics_dt_s=kick_env.KickEnv().physics_dt),
    }
    device = "cpu" if jax.default_backend() == "cpu" else "gpu"
    print(results.write_json(Path(args.out_dir) / f"noise_sources_{device}.json", payload))


if __name__ == "__main__":
    main()
