"""Does the kick's physics give the same episodes when asked twice?

A seed fixes a run's path only if the same program on the same inputs gives the same numbers.
This replays one batch of noisy kicks (the shipped prior's blended family at targets spread over
the task range, `--reps` noise draws each; `scoring.replay`) `--calls` times in this process, the
program compiled once, and compares every call's episodes with the first's: bit for bit, the
largest difference of the ball's resting distance, and how many episodes lie more than 1 mm
apart. With `--against` it also compares the first call with another run's record of the same
batch (another process, GPU or version).

    python -m experiments.repeatability --preset paper --calls 3 --out experiments/results/repeatability_gpu.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from experiments import tuning_split  # `episode_differences`

TOLERANCE_M = 1e-3  # an episode "differs" when its resting distance moves more than this


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="tiny", help="the config preset whose env runs")
    parser.add_argument("--impl", default=None, choices=("jax", "warp"), help="env.impl (default: the preset's)")
    parser.add_argument("--targets", type=int, default=23, help="targets spread over the task range")
    parser.add_argument("--reps", type=int, default=32, help="noise draws per target")
    parser.add_argument("--calls", type=int, default=3, help="how often the same batch is replayed")
    parser.add_argument("--against", type=Path, help="another run's record of this batch, to compare with")
    parser.add_argument("--out", type=Path, required=True, help="the record to write (.json)")
    args = parser.parse_args(argv)
    for name in ("targets", "reps", "calls"):
        if getattr(args, name) < (2 if name == "calls" else 1):
            parser.error(f"--{name} must be at least {2 if name == 'calls' else 1}, got {getattr(args, name)}")
    return args


def differences(first: np.ndarray, other: np.ndarray) -> dict:
    """How `other`'s resting distances (N, R) lie from `first`'s (m): bit for bit or not, and
    `tuning_split.episode_differences` over the episodes."""
    return {"identical": bool(np.array_equal(first, other)),
            **tuning_split.episode_differences(first, other, TOLERANCE_M)}  # fmt: skip


def main(argv=None) -> None:
    args = parse_args(argv)
    from bumps_jax import config, runio  # noqa: PLC0415

    overrides = {"task": "kick"} | ({"env.impl": args.impl} if args.impl else {})
    try:
        cfg = config.make_config(args.preset, overrides)
        runio.check_writable(args.out.parent, "the record's folder")
        against = None if args.against is None else runio.read_json(args.against, "another run's repeatability record")
    except ValueError as err:
        raise SystemExit(f"error: {err}") from None
    lo, hi = (float(t) for t in cfg.prior.task_range)
    targets = np.linspace(lo, hi, args.targets + 2, dtype=np.float32)[1:-1]
    if against is not None and (against.get("targets_m") != targets.tolist() or against.get("reps") != args.reps):
        raise SystemExit(f"error: {args.against} holds another batch (its targets or --reps differ from these)")

    import jax  # noqa: PLC0415

    from bumps_jax.tasks.kick import keyframes as kick_model  # noqa: PLC0415
    from bumps_jax.tasks.kick import scoring, starting_kicks  # noqa: PLC0415

    start = time.perf_counter()
    env = starting_kicks.tune_env(cfg)
    record = kick_model.load_record(kick_model.ASSET)
    params = kick_model.family_kicks(record, targets)
    keys = jax.random.split(jax.random.key(0), len(targets) * args.reps).reshape(len(targets), args.reps)
    calls, seconds = [], []
    for i in range(args.calls):
        t0 = time.perf_counter()
        calls.append(scoring.replay(env, params, targets, keys)["distance"])
        seconds.append(time.perf_counter() - t0)
        print(f"[repeatability] call {i + 1}/{args.calls}: mean distance {calls[-1].mean():.4f} m, "
              f"{seconds[-1]:.1f} s{' (compile included)' if i == 0 else ''}", flush=True)  # fmt: skip
    out = {
        "task": "kick",
        "targets_m": targets.tolist(),
        "reps": args.reps,
        "calls": args.calls,
        "call_seconds": seconds,
        "distance_m": calls[0].tolist(),  # the first call's episodes, for another run's --against
        "repeat_vs_first": [differences(calls[0], c) for c in calls[1:]],
    }
    if against is not None:
        theirs = np.asarray(against.get("distance_m"), np.float64)
        out["against"] = {"record": runio.portable_argument(str(args.against)), "device": against.get("device"),
                          **differences(theirs, calls[0])}  # fmt: skip
    out.update(runio.provenance(cfg.preset, time.perf_counter() - start, config.resolved_env(cfg)))
    runio.write_json(args.out, runio.json_safe(out))
    print(json.dumps({"repeat_vs_first": out["repeat_vs_first"], "against": out.get("against")}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
