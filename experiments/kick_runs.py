"""Where do the kick's runs on one GPU and on several part? Every finished run's experts record,
grouped by the processes its experts ran on; nothing is rerun.

Per run: the starting kicks' tuning (each restart's fresh cost: the mean over the targets of
its tuned kicks' cost on fresh episodes), the prior beside it (its error at its target) and the
experts' mean error. Per group, for the tuning and the experts (not every run's prior is kept):
the runs' values, and a two-sided exact permutation p-value of the groups' difference, each run
one sample (`device_count.permutation_p`); the experts also beside the line through every run's
tuning (`given_tuning`: a run's experts follow its tuning, which its prior sets). Beside that, how
far a run's restarts lie apart against how far the runs do: restarts share their run's prior and
starts, runs do not.

    python -m experiments.kick_runs results/seeds/seed*/experts.json ... --out experiments/results/kick_runs.json
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from bumps_jax import runio
from experiments.device_count import permutation_p, summary_provenance

PRIOR = "kick_prior.json"  # the prior's record: beside the experts' in a published run, in prior/ in a run folder


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("experts", type=Path, nargs="+", help="finished runs' experts records (experts.json)")
    parser.add_argument("--out", type=Path, required=True, help="the record to write (.json)")
    return parser.parse_args(argv)


def prior_of(experts_json: Path) -> dict | None:
    for path in (experts_json.parent / PRIOR, experts_json.parent.parent / "prior" / PRIOR):
        if path.is_file():
            return runio.read_json(path, "a run's prior record")
    return None


def run_row(experts_json: Path, tuned: bool = True) -> dict:
    """One run's row; ValueError where the record is not a finished kick experts record with its
    starting kicks' tuning runs (tuned=False: a run without them, as at the tiny size, is taken
    with its tuning fields None)."""
    record = runio.read_json(experts_json, "a run's experts record")
    tuning = record.get("starting_kicks_tuning_runs")
    if record.get("task", "kick") != "kick" or "error_mean_m" not in record or (tuned and not tuning):
        wanted = " with its starting kicks' tuning" if tuned else ""
        raise ValueError(f"{experts_json}: not a kick experts record{wanted}")
    prior = prior_of(experts_json)
    costs = [float(c) for c in tuning["fresh_costs"]] if tuning else None
    return {
        "experts_record": str(experts_json),
        "processes": int(record.get("n_processes", 1)),
        "device": record.get("device"),
        "date": record.get("date"),
        "tuning_fresh_costs": costs,
        "tuning_mean": None if costs is None else float(np.mean(costs)),
        "tuning_spread": None if costs is None else float(np.max(costs) - np.min(costs)),
        "prior_error_m": None if prior is None else float(prior["mean_error_m"]),
        "experts_error_m": float(record["error_mean_m"]),
    }


def groups(rows: list[dict]) -> dict:
    """One process against several: each group's per-run values and means, and the p-values."""
    one = [r for r in rows if r["processes"] == 1]
    several = [r for r in rows if r["processes"] > 1]
    out = {"runs": {"one_process": len(one), "several_processes": len(several)}}
    for key in ("tuning_mean", "experts_error_m"):
        a, b = [r[key] for r in one], [r[key] for r in several]
        out[key] = {"one_process": a, "several_processes": b,
                    "mean_one": float(np.mean(a)) if a else None, "mean_several": float(np.mean(b)) if b else None,
                    "permutation_p": permutation_p(np.asarray(a), np.asarray(b)) if a and b else None}  # fmt: skip
    out["experts_given_tuning"] = given_tuning(one, several)
    means = [r["tuning_mean"] for r in rows]
    out["tuning_within_vs_between"] = {
        "largest_spread_in_a_run": max(r["tuning_spread"] for r in rows),
        "runs_range": [float(np.min(means)), float(np.max(means))],
    }
    return out


def given_tuning(one: list[dict], several: list[dict]) -> dict | None:
    """How far the groups' experts part once their tunings are accounted for: one straight line
    of the experts' error on the tuning's mean fresh cost fitted over every run, each run's
    residual from it, each group's mean residual and the permutation p-value of their difference
    (the line fitted on the pooled runs, so the p-value is approximate). None with fewer than two
    runs in a group."""
    if len(one) < 2 or len(several) < 2:
        return None
    rows = one + several
    x, y = (np.array([r[k] for r in rows]) for k in ("tuning_mean", "experts_error_m"))
    slope, intercept = np.polyfit(x, y, 1)
    residual = y - (intercept + slope * x)
    a, b = residual[: len(one)], residual[len(one) :]
    return {"slope_m_per_cost": float(slope), "intercept_m": float(intercept),
            "correlation": float(np.corrcoef(x, y)[0, 1]),
            "residual_one_process": a.tolist(), "residual_several_processes": b.tolist(),
            "mean_residual_one": float(a.mean()), "mean_residual_several": float(b.mean()),
            "permutation_p": permutation_p(a, b)}  # fmt: skip


def main(argv=None) -> None:
    args = parse_args(argv)
    start = time.perf_counter()
    try:
        runio.check_writable(args.out.parent, "the record's folder")
        rows = [run_row(p) for p in args.experts]
    except ValueError as err:
        raise SystemExit(f"error: {err}") from None
    first = runio.read_json(args.experts[0], "a run's experts record")
    for path in args.experts[1:]:
        env = runio.read_json(path, "a run's experts record").get("env")
        if env != first.get("env"):
            differing = sorted(k for k in set(env or {}) | set(first.get("env") or {})
                               if (env or {}).get(k) != (first.get("env") or {}).get(k))  # fmt: skip
            raise SystemExit(f"error: {path} ran another env than {args.experts[0]} (keys {differing})")
    record = {
        "task": "kick",
        "per_run": rows,
        **groups(rows),
        **summary_provenance(first, [r["device"] for r in rows], start),
    }
    runio.write_json(args.out, runio.json_safe(record))
    t = record["tuning_mean"]
    print(
        f"tuned starting kicks' fresh cost, runs on one process {np.round(t['one_process'], 3).tolist()}, on several "
        f"{np.round(t['several_processes'], 3).tolist()} (p = {t['permutation_p']:.2f}); wrote {args.out}"
    )
    g = record["experts_given_tuning"]
    if g is not None:
        print(
            f"experts' error beside the line through the tunings: one process {g['mean_residual_one']:+.3f} m, "
            f"several {g['mean_residual_several']:+.3f} m (p = {g['permutation_p']:.2f})"
        )


if __name__ == "__main__":
    main()
