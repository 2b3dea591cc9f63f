"""Cloning variants side by side: finished meta stages that cloned the same experts in different
ways (`meta.dataset`; DAgger's rounds, `meta.dagger`, until they were removed), each scored
unfiltered on the same contexts.

Reads each run's meta/table1.json (and the experts' record it names) and writes one record: per
variant, its cloning in words, the env steps it spent, the pairs it trained on, its training
time, and every net's error overall and per context, beside the experts' own. Nothing is rerun.

    python experiments/cloning_variants.py runs/dev101_plain runs/dev101_dart runs/dev101_dagger \
        --out experiments/results/cheetah_cloning_variants_dev101_gpu.json
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bumps_jax import runio

PROVENANCE = ("device", "n_devices", "versions", "preset", "env", "task", "unit")


def variant(run_dir: Path) -> dict:
    """One run's cloning and its nets' errors, from its table1.json."""
    t1 = runio.read_json(run_dir / "meta" / "table1.json", "a finished meta stage")
    nets = {n: r for n, r in t1["rows"].items() if n.startswith("meta_")}
    return {
        "run": run_dir.name,
        "cloning": t1.get("cloning", {}),
        "config": {k: t1["config"][k] for k in ("dataset", "dagger", "train") if k in t1["config"]},
        "dataset_pairs": t1["dataset_pairs"],
        "train_wall_s": max(t["train_wall_s"] for t in t1["timings"].values()),
        "error_mean_all_m": {n: r["error_mean_all_m"] for n, r in nets.items()},
        "per_task_error_m": {n: [p["error_mean_m"] for p in r["per_task"]] for n, r in nets.items()},
        "experts_error_mean_all_m": t1["rows"]["experts"]["error_mean_all_m"],
        "eval": t1["eval"],
        "contexts": t1["per_task"]["tasks"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run directories with a finished meta stage")
    parser.add_argument("--out", type=Path, required=True, help="the record to write (.json)")
    args = parser.parse_args()
    variants = [variant(d) for d in args.runs]
    contexts = {tuple(v["contexts"]) for v in variants}
    if len(contexts) != 1:
        raise SystemExit("the runs were scored on different contexts: not comparable")
    first = runio.read_json(args.runs[0] / "meta" / "table1.json")
    record = {
        "variants": variants,
        "contexts": variants[0]["contexts"],
        "best_mean_of_nets": min(variants, key=lambda v: sum(v["error_mean_all_m"].values()))["run"],
        **{k: first[k] for k in PROVENANCE if k in first},
        "date": first["date"],
        "command": runio.command_line(),
        "wall_s": sum(v["train_wall_s"] for v in variants),
    }
    runio.write_json(args.out, record)
    for v in variants:
        errors = ", ".join(f"{n} {e:.3f}" for n, e in v["error_mean_all_m"].items())
        print(f"{v['run']}: {v['cloning'].get('variant')}: {errors} ({v['dataset_pairs']} pairs)")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
