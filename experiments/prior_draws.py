"""Do kick priors made on several processes tune worse than priors made on one?

On a GPU a kick run's prior is a draw (Warp does not repeat itself) and the prior sets how well
the experts' starting kicks tune (`docs/scaling.md`). This groups priors, each tuned again by
`experiments.tuning_batch_shape --arms whole --prior <its record>`, by the processes their prior
stage ran on, and compares the groups' tunings, each prior one sample: per prior its error at its
target, its processes, device and date, and its tuning's per-restart fresh costs and their mean;
per group the means and a two-sided exact permutation p-value (`device_count.permutation_p`); and
the same grouped by the GPU each prior was made on.

Each argument is a tuning record, or TUNING=PRIOR where the prior's record lies elsewhere than the
path the tuning record names (a prior made on another machine and kept in the repository).

    python -m experiments.prior_draws runs/pp/tuning_*.json --out experiments/results/prior_draws_gpu.json
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from bumps_jax import runio
from experiments.device_count import permutation_p, summary_provenance


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tunings", nargs="+", metavar="TUNING[=PRIOR]",
                        help="tuning_batch_shape records (--arms whole --prior P)")  # fmt: skip
    parser.add_argument("--out", type=Path, required=True, help="the record to write (.json)")
    return parser.parse_args(argv)


def read_tuning(argument: str) -> dict:
    """The tuning record `TUNING[=PRIOR]` names."""
    return runio.read_json(Path(argument.partition("=")[0]), "a tuning record (experiments.tuning_batch_shape)")


def prior_row(argument: str, tuning: dict | None = None) -> dict:
    """One prior's row from `TUNING[=PRIOR]` (its tuning record, read if not given); ValueError
    naming the record that does not fit."""
    tuning_path, _, prior_path = argument.partition("=")
    tuning = read_tuning(argument) if tuning is None else tuning
    seeds = tuning.get("seeds") or {}
    if not tuning.get("prior") or len(seeds) != 1 or "whole" not in next(iter(seeds.values())):
        raise ValueError(f"{tuning_path}: not one seed's whole-batch tuning from a prior (--arms whole --prior P)")
    whole = next(iter(seeds.values()))["whole"]
    prior_file = Path(prior_path or tuning["prior"])
    prior = runio.read_json(prior_file, "the tuned prior's record (kick_prior.json)")
    if "mean_error_m" not in prior:
        raise ValueError(f"{prior_file}: not a kick prior record (no mean_error_m)")
    return {
        "tuning_record": tuning_path,
        "prior_record": str(prior_file),
        "prior_processes": int(prior.get("n_processes", 1)),
        "prior_device": prior.get("device"),
        "prior_date": prior.get("date"),
        "prior_error_m": float(prior["mean_error_m"]),
        "tuning_device": tuning.get("device"),
        "tuning_fresh_costs": [float(c) for c in whole["runs_mean"]],
        "tuning_mean": float(np.mean(whole["runs_mean"])),
    }


def compare(rows: list[dict]) -> dict:
    """Priors of one process against priors of several: each group's tunings, means and p-value."""
    one = [r["tuning_mean"] for r in rows if r["prior_processes"] == 1]
    several = [r["tuning_mean"] for r in rows if r["prior_processes"] > 1]
    both = bool(one and several)
    return {
        "priors": {"one_process": len(one), "several_processes": len(several)},
        "tuning_mean": {"one_process": one, "several_processes": several,
                        "mean_one": float(np.mean(one)) if one else None,
                        "mean_several": float(np.mean(several)) if several else None,
                        "permutation_p": permutation_p(np.asarray(one), np.asarray(several)) if both else None},
    }  # fmt: skip


def by_device(rows: list[dict]) -> dict:
    """The same tunings grouped by the GPU their prior was made on (the other thing that may set
    the groups of `compare` apart): per device its tunings and mean, and with two devices the
    permutation p-value between them."""
    devices = sorted({r["prior_device"] or "unknown" for r in rows})
    groups = {d: [r["tuning_mean"] for r in rows if (r["prior_device"] or "unknown") == d] for d in devices}
    out = {d: {"tuning_mean": g, "mean": float(np.mean(g))} for d, g in groups.items()}
    p = permutation_p(*(np.asarray(g) for g in groups.values())) if len(groups) == 2 else None
    return {"by_prior_device": {"devices": out, "permutation_p": p}}


def main(argv=None) -> None:
    args = parse_args(argv)
    start = time.perf_counter()
    try:
        runio.check_writable(args.out.parent, "the record's folder")
        tunings = [read_tuning(a) for a in args.tunings]
        rows = [prior_row(a, t) for a, t in zip(args.tunings, tunings, strict=True)]
    except ValueError as err:
        raise SystemExit(f"error: {err}") from None
    first = tunings[0]
    for argument, other in zip(args.tunings[1:], tunings[1:], strict=True):
        for key in ("env", "settings", "preset"):
            if other.get(key) != first.get(key):
                raise SystemExit(f"error: {argument} tuned under another {key} than {args.tunings[0]}")
    record = {
        "task": "kick",
        "per_prior": rows,
        **compare(rows),
        **by_device(rows),
        **summary_provenance(first, [r["tuning_device"] for r in rows], start),
    }
    runio.write_json(args.out, runio.json_safe(record))
    t = record["tuning_mean"]
    p = "n/a" if t["permutation_p"] is None else f"{t['permutation_p']:.2f}"
    print(
        f"tunings of priors made on one process {np.round(t['one_process'], 3).tolist()}, on several "
        f"{np.round(t['several_processes'], 3).tolist()} (p = {p}); wrote {args.out}"
    )
    d = record["by_prior_device"]
    for device, group in d["devices"].items():
        print(f"  priors made on {device}: {np.round(group['tuning_mean'], 3).tolist()}")
    if d["permutation_p"] is not None:
        print(f"  between the two devices p = {d['permutation_p']:.2f}")


if __name__ == "__main__":
    main()
