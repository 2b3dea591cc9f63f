"""Does the device count move the results? The same training seeds run twice, each arm a folder of
finished runs with its seeds.json (`reproduce --seeds`): one run per seed on one GPU, and one per
seed spread over several processes. Nothing is rerun.

Writes one record: per headline row, each arm's per-seed values, mean and std, the per-seed
difference (the same seed in both arms) and a two-sided exact permutation p-value of the
difference of the arms' means (every split of the pooled values into two arms of their sizes).
With three seeds an arm, the smallest p-value there is, is 0.1: the test can flag a large shift,
never prove equality; the per-seed differences say how far runs of one seed land apart.

    python experiments/device_count.py runs/dc_one runs/dc_four --out experiments/results/device_count.json
"""

from __future__ import annotations

import argparse
import datetime
import itertools
import time
from pathlib import Path

import numpy as np

from bumps_jax import records, runio

PROVENANCE = ("device", "versions", "preset", "env", "task", "unit")


def permutation_p(a, b) -> float:
    """Two-sided exact permutation p-value of mean(a) - mean(b): the share of the splits of the
    pooled values into groups of len(a) and len(b) whose |difference of means| is at least the
    observed one (the observed split counted)."""
    pooled, n = np.concatenate([a, b]), len(a)
    observed = abs(np.mean(a) - np.mean(b))
    diffs = []
    for idx in itertools.combinations(range(len(pooled)), n):
        mask = np.zeros(len(pooled), bool)
        mask[list(idx)] = True
        diffs.append(abs(pooled[mask].mean() - pooled[~mask].mean()))
    return float(np.mean(np.asarray(diffs) >= observed - 1e-12))


def summary_provenance(first: dict, devices, start: float) -> dict:
    """The results-contract keys of a record made from other records: the devices they ran on, the
    first one's versions, env and preset, and this command's date, command line and wall time
    since `start` (`time.perf_counter()`)."""
    return {
        "device": ", ".join(sorted({d for d in devices if d})),
        "versions": first.get("versions"),
        "env": first.get("env"),
        "preset": first.get("preset"),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": runio.command_line(),
        "wall_s": round(time.perf_counter() - start, 3),
    }


def arm(run_dir: Path) -> dict:
    """One arm: its seeds.json, the seeds of each run, and the processes each run's experts ran on.
    `run_dir`: a run folder (`run/<seed run>/experts/experts.json`) or a published task's results
    (`seeds/<seed run>/experts.json`, `publish --seed-runs`)."""
    seeds = runio.read_json(run_dir / "seeds.json", "an arm's headlines over seeds (reproduce --seeds)")
    processes = []
    for r in seeds["runs"]:
        published = run_dir / "seeds" / r["run"] / "experts.json"
        path = published if published.is_file() else run_dir / r["run"] / "experts" / "experts.json"
        experts = runio.read_json(path, "a run's experts record")
        processes.append(experts.get("n_processes", 1))
    return {"dir": run_dir.name, "seeds": [r["seeds"] for r in seeds["runs"]], "processes": processes, "record": seeds,
            "device": seeds.get("device")}  # fmt: skip


def compare(one: dict, other: dict) -> dict:
    """Per row both arms have: each arm's values, mean and std, the per-seed differences (other -
    one) and the permutation p-value. ValueError where the arms ran other seeds or envs."""
    if one["seeds"] != other["seeds"]:
        raise ValueError(f"the arms ran other training seeds: {one['seeds']} and {other['seeds']}")
    records.check_same_env(other["record"].get("env"), one["record"].get("env"), f"{other['dir']}/seeds.json")
    rows = {}
    for name in one["record"]["rows"]:
        if name not in other["record"]["rows"]:
            continue
        a = np.asarray(one["record"]["rows"][name]["per_seed"], np.float64)
        b = np.asarray(other["record"]["rows"][name]["per_seed"], np.float64)
        rows[name] = {
            "one": {"per_seed": a.tolist(), "mean": float(a.mean()), "std": float(a.std())},
            "other": {"per_seed": b.tolist(), "mean": float(b.mean()), "std": float(b.std())},
            "difference_per_seed": (b - a).tolist(),
            "difference_of_means": float(b.mean() - a.mean()),
            "permutation_p": permutation_p(a, b),
        }
    return rows


def procs(a: dict) -> str:
    """An arm's processes a run in words: "1 process", "4 processes", "4, 2, 2 processes"."""
    counts = sorted(set(a["processes"]))
    shown = str(counts[0]) if len(counts) == 1 else ", ".join(map(str, a["processes"]))
    return f"{shown} process" + ("" if shown == "1" else "es")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("one", type=Path, help="the arm of one process per run (a folder with seeds.json)")
    parser.add_argument("other", type=Path, help="the arm of several processes per run, the same seeds")
    parser.add_argument("--out", type=Path, required=True, help="the record to write (.json)")
    args = parser.parse_args()
    try:
        one, other = arm(args.one), arm(args.other)
        rows = compare(one, other)
    except ValueError as e:
        raise SystemExit(f"error: {e}") from None
    first = one["record"]
    record = {
        "arms": {
            name: {"dir": a["dir"], "processes_per_run": a["processes"], "device": a["device"]}
            for name, a in (("one", one), ("other", other))
        },
        "seeds": one["seeds"],
        "rows": rows,
        **{k: first[k] for k in PROVENANCE if k in first},
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": runio.command_line(),
        "wall_s": float(first.get("wall_s", 0.0)) + float(other["record"].get("wall_s", 0.0)),
    }
    runio.write_json(args.out, record)
    unit = first.get("unit", "")
    for name, r in rows.items():
        print(f"{name}: {r['one']['mean']:.3f} ({procs(one)} a run) vs {r['other']['mean']:.3f} "
              f"({procs(other)}) {unit}; per seed {np.round(r['difference_per_seed'], 3).tolist()}, "
              f"p = {r['permutation_p']:.2f}")  # fmt: skip
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
