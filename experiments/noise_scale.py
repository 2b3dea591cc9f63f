"""How the trained experts' error depends on how much noise the task has.

The experts' error is mostly the spread that the task's noise gives each open-loop kick
(`noise_sources.py`, `strike_search.py`). This replays a finished experts run's 23 experts,
each on its own task, with every noise source scaled by the same factor (0 = none, 1 = the
task as trained and scored), and reports per task and overall: the error, the resting
distance's mean and spread, the sideways offset and the valid fraction. Nothing is retrained:
it shows what the committed experts would score if the task were noisier or quieter, not what
experts trained at that noise would.

Writes <out-dir>/noise_scale_<device>.json.

    python experiments/noise_scale.py --run-dir runs/paper/experts --scales 0 0.25 0.5 1
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import numpy as np

from bumps_jax import evaluate, experts, filtering, kick_env, results


def scaled_noise(scale: float) -> dict:
    """Env overrides with every noise source of the default task multiplied by `scale`."""
    return {f"noise.{k}": float(v) * scale for k, v in kick_env.default_config().noise.items()}


def summarise(metrics: dict, tasks, ball_xy) -> list[dict]:
    """Per task, from final metrics of shape (n_tasks, n_reps): error, resting distance (m ahead
    of the ball's nominal start: mean and std), sideways offset and valid fraction."""
    rows = []
    for i, target in enumerate(tasks):
        distance = np.asarray(metrics["rest_x"][i]) - ball_xy[0]
        rows.append({
            "target_m": float(target),
            "error_mean_m": float(np.mean(metrics["final_error"][i])),
            "distance_mean_m": float(distance.mean()),
            "distance_std_m": float(distance.std()),
            "lateral_mean_m": float(np.mean(np.asarray(metrics["rest_y"][i]) - ball_xy[1])),
            "valid_fraction": float(np.mean(metrics["valid"][i])),
        })  # fmt: skip
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-dir", default="runs/paper/experts", help="a finished experts run")
    parser.add_argument("--scales", type=float, nargs="+", default=[0.0, 0.25, 0.5, 1.0])
    parser.add_argument("--repetitions", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out-dir", default="experiments/results")
    args = parser.parse_args(argv)
    if args.repetitions < 2:
        parser.error(f"--repetitions must be at least 2, got {args.repetitions}")
    bad = [s for s in args.scales if not np.isfinite(s) or s < 0]
    if bad:
        parser.error(f"--scales must be >= 0, got {bad[0]}")
    if not (Path(args.run_dir) / "final_params").is_dir():
        parser.error(f"--run-dir {args.run_dir} has no final_params: train the experts first")

    start = time.perf_counter()
    fam = experts.family(args.run_dir)
    tasks = np.asarray(fam.tasks, np.float32)
    rows = {}
    for scale in args.scales:
        env = kick_env.KickEnv(config_overrides=scaled_noise(scale))
        metrics = evaluate.evaluate_experts(env, fam.apply_fn, fam.params, tasks, args.repetitions, args.seed)
        tasks_rows = summarise(metrics, tasks, filtering.ball_start_xy(env))
        row = rows[str(scale)] = {
            "error_mean_m": float(np.mean([r["error_mean_m"] for r in tasks_rows])),
            "accuracy_mean": float(np.mean([r["valid_fraction"] for r in tasks_rows])),
            "tasks": tasks_rows,
        }
        print(f"noise x{scale:<5}  error {row['error_mean_m']:.3f} m  accuracy {row['accuracy_mean']:.3f}"
              f"  ({time.perf_counter() - start:.0f} s)", flush=True)  # fmt: skip
    payload = {
        "run_dir": args.run_dir,
        "repetitions": args.repetitions,
        "noise": dict(kick_env.default_config().noise),
        "scales": rows,
        **results.provenance("noise_scale", time.perf_counter() - start, physics_dt_s=env.physics_dt),
    }
    device = "cpu" if jax.default_backend() == "cpu" else "gpu"
    print(results.write_json(Path(args.out_dir) / f"noise_scale_{device}.json", payload))


if __name__ == "__main__":
    main()
