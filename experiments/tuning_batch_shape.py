"""Does the batch shape alone change how well the kick's starting-kick tuning does?

The kick's published seeds, made on four and two GPUs, came out worse than the same seeds on
one GPU, the gap opening in the CMA-ES tuning of the experts' starting kicks
(`experiments/results/device_count_kick.json`). Split over N processes, each device computes
exactly its share of the searches (`experiments/results/tuning_split_cpu.json`); what changes is
the batch each program call holds. This runs the tuning (`cmaes.tune_for_tasks`, at the preset's
settings) for several tuning seeds in one process, twice each: every generation as one call of
the whole batch, and as N calls of its N parts (what N processes compute). Same device, same code,
same starts: any difference is the batch shape's.

Writes one record, again after each seed (a stopped run keeps the seeds it finished): per seed
and arm the tuned kicks' fresh costs (each run's mean over the targets, the chosen kicks' mean),
the per-seed difference (parts - whole) and a two-sided sign-flip permutation p-value of its
mean (2^seeds sign patterns).

    python -m experiments.tuning_batch_shape --preset paper --impl warp --seeds 0 1 2 3 --parts 4 \\
        --out experiments/results/tuning_batch_shape_gpu.json
"""

from __future__ import annotations

import argparse
import datetime
import itertools
import sys
import time
from pathlib import Path

import numpy as np

from experiments import tuning_split  # the tuning with its generations in parts: `run_tuning`


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="tiny", help="the config preset whose tuning settings run")
    parser.add_argument("--impl", default=None, choices=("jax", "warp"), help="env.impl (default: the preset's)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="experts.tune.seed values")
    parser.add_argument("--parts", type=int, default=4, help="N: the calls each generation is split into")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides (JSON values)")
    parser.add_argument("--prior", type=Path, help="a prior stage's record (kick_prior.json) whose anchors and "
                        "sweep give the starts (default: the shipped prior)")  # fmt: skip
    parser.add_argument("--arms", nargs="+", default=["whole", "parts"], choices=("whole", "parts"),
                        help="which tunings run: the whole batch, its parts, or both (compared)")  # fmt: skip
    parser.add_argument("--side-by-side", action="store_true",
                        help="one process a GPU, the seeds dealt out over them")  # fmt: skip
    parser.add_argument("--out", type=Path, required=True, help="the record to write (.json)")
    parser.add_argument("--rows", type=Path, help=argparse.SUPPRESS)  # a side-by-side process: its seeds' rows
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    if args.parts < 2:
        parser.error(f"--parts must be at least 2, got {args.parts}")
    if len(set(args.seeds)) != len(args.seeds) or any(s < 0 for s in args.seeds):
        parser.error(f"--seeds must be distinct integers >= 0, got {args.seeds}")
    if len(set(args.arms)) != len(args.arms):
        parser.error(f"--arms must be distinct, got {args.arms}")
    return args


def read_prior(path: Path | None) -> dict | None:
    """The starts' prior from a prior stage's record (its anchors, in the order the kick names
    them, and its sweep); None: the shipped prior. ValueError naming what is missing."""
    if path is None:
        return None
    from bumps_jax import runio  # noqa: PLC0415
    from bumps_jax.tasks.kick import keyframes as kick_model  # noqa: PLC0415

    record = runio.read_json(path, "a kick prior record")
    anchors = record.get("anchors")
    if isinstance(anchors, dict):
        if set(anchors) != set(kick_model.ANCHORS):
            raise ValueError(f"--prior {path}: anchors {sorted(anchors)}, expected {list(kick_model.ANCHORS)}")
        anchors = [anchors[a] for a in kick_model.ANCHORS]
    if not anchors or not record.get("sweep"):
        raise ValueError(f"--prior {path}: not a kick prior record (it needs anchors and sweep)")
    return {"anchors": anchors, "sweep": record["sweep"]}


def make_config(args, seed: int):
    from bumps_jax import cli, config  # noqa: PLC0415

    overrides = {"task": "kick", **cli.parse_overrides([args.set]), "experts.tune.seed": seed}
    if args.impl is not None:
        overrides["env.impl"] = args.impl
    return config.make_config(args.preset, overrides)


def summary(arm: dict) -> dict:
    """An arm's fresh costs: each run's mean over the targets (as the experts' record's
    `starting_kicks_tuning_runs.fresh_costs`), and the tuned kicks' mean."""
    return {"runs_mean": [float(c) for c in arm["restart_costs"]], "tuned_mean": float(np.mean(arm["tuned_cost"])),
            "start_mean": float(np.mean(arm["start_cost"])), "runs_kept": arm["runs_kept"],
            "seconds": arm["seconds"]}  # fmt: skip


def sign_flip_p(diffs) -> float:
    """Two-sided exact p-value of mean(diffs) != 0 under sign flips (every sign pattern)."""
    d = np.asarray(diffs, np.float64)
    observed = abs(d.mean())
    flips = [abs(np.mean(d * np.asarray(s))) for s in itertools.product((1.0, -1.0), repeat=len(d))]
    return float(np.mean(np.asarray(flips) >= observed - 1e-12))


def compare(per_seed: dict) -> dict:
    """The arms over seeds: per-seed parts - whole of the runs' mean fresh cost and of the chosen
    kicks' mean, their means and sign-flip p-values."""
    out = {}
    for key, of in (("runs_mean", lambda s: float(np.mean(s["runs_mean"]))), ("tuned_mean", lambda s: s["tuned_mean"])):
        whole = [of(r["whole"]) for r in per_seed.values()]
        parts = [of(r["parts"]) for r in per_seed.values()]
        diffs = [p - w for p, w in zip(parts, whole, strict=True)]
        out[key] = {"whole": whole, "parts": parts, "difference_per_seed": diffs,
                    "difference_mean": float(np.mean(diffs)), "parts_higher": int(np.sum(np.asarray(diffs) > 0)),
                    "sign_flip_p": sign_flip_p(diffs)}  # fmt: skip
    return out


def tune_seeds(args, cfgs: dict, start: float, on_seed, prior: dict | None = None) -> dict:
    """Each seed's tuning, whole and in parts, one after another in this process: seed -> arms.
    `on_seed(per_seed)` runs after each seed (its rows so far written, so a stopped run keeps them)."""
    per_seed = {}
    for i, (seed, cfg) in enumerate(cfgs.items()):
        row = {}
        for name, parts in (("whole", 1), ("parts", args.parts)):
            if name not in args.arms:
                continue
            print(f"[tuning_batch_shape] seed {seed} ({i + 1}/{len(cfgs)}), {name}", flush=True)
            arm = tuning_split.run_tuning(cfg, parts=parts, check_whole=False, prior=prior,
                                          say=lambda m, name=name: print(f"[{name}] {m}", flush=True))  # fmt: skip
            row[name] = summary(arm)
        per_seed[str(seed)] = row
        on_seed(per_seed)
        done = time.perf_counter() - start
        costs = ", ".join(f"{name} {arm['tuned_mean']:.3f}" for name, arm in row.items())
        print(f"[tuning_batch_shape] seed {seed}: tuned kicks' mean fresh cost {costs} (starts "
              f"{next(iter(row.values()))['start_mean']:.3f}); ETA {done / (i + 1) * (len(cfgs) - i - 1):.0f} s",
              flush=True)  # fmt: skip
    return per_seed


def side_by_side(args) -> dict:
    """The seeds dealt out over one process per GPU (`launch.visible_gpus`), side by side; their rows."""
    import json  # noqa: PLC0415
    import os  # noqa: PLC0415
    import subprocess  # noqa: PLC0415
    import tempfile  # noqa: PLC0415

    from bumps_jax import launch  # noqa: PLC0415

    gpus = launch.visible_gpus() or [None]
    jobs = [(gpu, args.seeds[j :: len(gpus)]) for j, gpu in enumerate(gpus) if args.seeds[j :: len(gpus)]]
    with tempfile.TemporaryDirectory(prefix="tuning-batch-shape-") as tmp:
        procs = []
        for j, (gpu, seeds) in enumerate(jobs):
            own = [a for a in args.argv if a != "--side-by-side"]
            own += ["--seeds", *map(str, seeds), "--rows", str(Path(tmp) / f"rows.{j}.json")]
            env = dict(os.environ) if gpu is None else {**os.environ, "CUDA_VISIBLE_DEVICES": gpu}
            procs.append(subprocess.Popen([sys.executable, "-m", __spec__.name, *own], env=env))
        codes = [p.wait() for p in procs]
        if any(codes):
            raise SystemExit(f"error: a side-by-side process ended with {codes}")
        rows = {}
        for j in range(len(jobs)):
            rows.update(json.loads((Path(tmp) / f"rows.{j}.json").read_text()))
    return {str(s): rows[str(s)] for s in args.seeds}


def write_record(args, cfgs: dict, per_seed: dict, seconds: float) -> dict:
    """The record of the seeds tuned so far (`complete` once every requested seed is in)."""
    from bumps_jax import config, runio  # noqa: PLC0415

    cfg = cfgs[args.seeds[0]]
    tune = cfg.experts.tune
    record = {
        "task": cfg.task,
        "parts": args.parts,
        "settings": {
            "targets": list(cfg.experts.tasks),
            "generations": tune.generations,
            "population": tune.population_size,
            "repetitions": tune.repetitions,
            "eval_repetitions": tune.eval_repetitions,
            "restarts": tune.restarts,
            "leash": tune.neighbour_leash,
            "sigma": tune.sigma_init,
            "overrides": args.set,
        },  # fmt: skip
        "prior": str(args.prior) if args.prior else "the shipped prior",
        "arms": list(args.arms),
        "seeds_requested": list(args.seeds),
        "complete": len(per_seed) == len(args.seeds),
        "seeds": per_seed,
        **(compare(per_seed) if len(args.arms) == 2 else {}),
    }
    record.update(runio.provenance(cfg.preset, seconds, config.resolved_env(cfg)),
                  date=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"))  # fmt: skip
    runio.write_json(args.out, runio.json_safe(record))
    return record


def main(argv=None) -> None:
    args = parse_args(argv)
    from bumps_jax import runio  # noqa: PLC0415

    try:
        cfgs = {seed: make_config(args, seed) for seed in args.seeds}
        prior = read_prior(args.prior)
        runio.check_writable(args.out.parent, "the record's folder")
    except ValueError as err:
        raise SystemExit(f"error: {err}") from None
    start = time.perf_counter()
    if args.rows is not None:  # one of the side-by-side processes: its rows for the first to join
        tune_seeds(args, cfgs, start, on_seed=lambda rows: runio.write_json(args.rows, rows), prior=prior)
        return
    if args.side_by_side:
        per_seed = side_by_side(args)
    else:
        save = lambda rows: write_record(args, cfgs, rows, time.perf_counter() - start)  # noqa: E731
        per_seed = tune_seeds(args, cfgs, start, on_seed=save, prior=prior)
    record = write_record(args, cfgs, per_seed, time.perf_counter() - start)
    if "tuned_mean" not in record:  # one arm: nothing to compare
        print(f"wrote {args.out}")
        return
    t = record["tuned_mean"]
    print(
        f"chosen kicks' mean fresh cost, {args.parts} parts - whole, per seed: "
        f"{', '.join(f'{d:+.3f}' for d in t['difference_per_seed'])}; p = {t['sign_flip_p']:.2f}; wrote {args.out}"
    )


if __name__ == "__main__":
    main()
