"""How the trained experts' error depends on how much noise the task has.

The experts' error is mostly the spread that the task's noise gives each open-loop kick
(`noise_sources.py`, `strike_search.py`). This replays a finished run's experts, each on its
own task, with every noise source scaled by the same factor (0 = none, 1 = the task as trained
and scored), and reports per task and overall: the error, the resting distance's mean and
spread, the sideways offset and the valid fraction. Nothing is retrained: it shows what the
experts would score if the task were noisier or quieter, not what experts trained at that
noise would. The run's config is given as for the pipeline (--preset, --set) and checked
against the one its experts were trained under.

Writes <out-dir>/noise_scale_<device>.json.

    python experiments/noise_scale.py --run-dir runs/paper --preset paper --scales 0 0.25 0.5 1
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from bumps_jax import cli, config, runio
from bumps_jax.algo import evaluate
from bumps_jax.pipeline import runner as pipeline
from bumps_jax.pipeline.stages import experts
from bumps_jax.tasks.kick import env as kick_env


def scaled_noise(env_cfg, scale: float) -> dict:
    """Config overrides (env.noise.*) with every noise source of `env_cfg` multiplied by `scale`."""
    return {f"env.noise.{k}": float(v) * scale for k, v in env_cfg.noise.items()}


def summarise(metrics: dict, tasks) -> list[dict]:
    """Per task, from the env's final metrics of shape (n_tasks, n_reps): error, resting distance
    (m along the kick line from the ball's nominal start: mean and std), sideways offset, valid fraction."""
    rows = []
    for i, target in enumerate(tasks):
        distance = np.asarray(metrics["distance"][i])
        rows.append({
            "target_m": float(target),
            "error_mean_m": float(np.mean(metrics["final_error"][i])),
            "distance_mean_m": float(distance.mean()),
            "distance_std_m": float(distance.std()),
            "lateral_mean_m": float(np.mean(metrics["lateral"][i])),
            "valid_fraction": float(np.mean(metrics["valid"][i])),
        })  # fmt: skip
    return rows


def parse_args(argv=None):
    """(args, pipeline config, its overrides), every argument checked (parser errors) before any work."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-dir", default="runs/paper", help="a run whose experts stage finished")
    parser.add_argument("--preset", default="paper", help="the preset the run was made with")
    parser.add_argument("--set", action="append", nargs="+", default=[], metavar="KEY=VALUE",
                        help="the overrides the run was made with")  # fmt: skip
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
    if not (Path(args.run_dir) / "experts" / "final_params").is_dir():
        parser.error(f"--run-dir {args.run_dir} has no experts/final_params: train the experts first")
    try:
        overrides = cli.parse_overrides(args.set)
        cfg = config.make_config(args.preset, overrides)
        pipeline.plan("experts", cfg, Path(args.run_dir))  # the run's experts were made under this config
    except ValueError as err:
        parser.error(str(err))
    return args, cfg, overrides


def main(argv=None) -> None:
    args, cfg, overrides = parse_args(argv)
    start = time.perf_counter()
    family = experts.load_family(cfg, Path(args.run_dir))
    rows = {}
    for scale in args.scales:
        env = kick_env.KickEnv(config.make_config(args.preset, {**overrides, **scaled_noise(cfg.env, scale)}).env)
        metrics = evaluate.evaluate_experts(
            env, family.apply_fn, family.params, family.tasks, args.repetitions, args.seed
        )
        tasks_rows = summarise(metrics, family.tasks)
        row = rows[str(scale)] = {
            "error_mean_m": float(np.mean([r["error_mean_m"] for r in tasks_rows])),
            "accuracy_mean": float(np.mean([r["valid_fraction"] for r in tasks_rows])),
            "tasks": tasks_rows,
        }
        print(f"noise x{scale:<5}  error {row['error_mean_m']:.3f} m  accuracy {row['accuracy_mean']:.3f}"
              f"  ({time.perf_counter() - start:.0f} s)", flush=True)  # fmt: skip
    payload = {"run_dir": args.run_dir, "repetitions": args.repetitions, "noise": dict(cfg.env.noise), "scales": rows}
    print(runio.write_experiment(args.out_dir, "noise_scale", payload, cfg, time.perf_counter() - start))


if __name__ == "__main__":
    main()
