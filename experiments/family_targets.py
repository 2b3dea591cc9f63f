"""Does a run meet the targets of the smooth-family work (docs/decisions.md, "Experts")? A reader of
a run's records, written before the arm it judges has run: the rule a development arm is adopted
by, applied the same way every time.

The targets, for a run at the paper's budget: the experts and every filtered variant err at most
0.35 m; each unfiltered meta-policy errs at most the paper's (Table 1: 4x256 0.72 m, 11x128 0.68 m)
with accuracy at least 0.95 and no task above 2 m; the finest context grid (`high_sample_rate_4x256`)
no worse than the same net's coarse one (`filtered_4x256`). It prints each target with what the
records measured, and the evaluation they come from (a development arm's targets and seed, or the
meta-test tasks). Exit status: 0 every target met, 1 one missed, 2 a record missing or unreadable.
It writes nothing: the numbers are the records'.

    python -m experiments.family_targets --run-dir runs/dev_<arm>
    python -m experiments.family_targets --arm <arm> [--device h100]   (experiments/results/dev_starting_kicks/)
    python -m experiments.family_targets --published                      (results/)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import NamedTuple

from bumps_jax import config, runio
from bumps_jax.report import tables

ROOT = Path(__file__).resolve().parents[1]
DEV_RECORDS = ROOT / "experiments" / "results" / "dev_starting_kicks"
ERROR_LIMIT_M = 0.35  # the experts and every filtered variant
ACCURACY_MIN = 0.95  # each unfiltered meta-policy
WORST_TASK_M = 2.0  # no task of an unfiltered meta-policy errs more
NETS = ("meta_4x256", "meta_11x128")
FINE, COARSE = "high_sample_rate_4x256", "filtered_4x256"  # the same net's fine and coarse context grids


class Target(NamedTuple):
    name: str
    measured: float | None  # None: the record lacks it
    limit: float
    at_most: bool = True  # measured <= limit (else >=)

    @property
    def met(self) -> bool | None:
        if self.measured is None:
            return None
        return self.measured <= self.limit if self.at_most else self.measured >= self.limit


def targets(experts: dict | None, table1: dict | None, table2: dict | None) -> list[Target]:
    """Every target against the records (an experts.json, a table1.json, a table2.json; None: not made)."""
    out = [Target("experts: error (m)", None if experts is None else experts.get("error_mean_m"), ERROR_LIMIT_M)]
    rows1 = {} if table1 is None else table1["rows"]
    for net in NETS:
        row = rows1.get(net, {})
        paper_error = tables.PAPER_TABLE1[net][2]
        worst = max((t["error_mean_m"] for t in row.get("per_task", [])), default=None)
        out += [
            Target(f"{net} unfiltered: error (m)", row.get("error_mean_m"), paper_error),
            Target(f"{net} unfiltered: accuracy", row.get("accuracy_mean"), ACCURACY_MIN, at_most=False),
            Target(f"{net} unfiltered: worst task (m)", worst, WORST_TASK_M),
        ]
    rows2 = {} if table2 is None else table2["rows"]
    for variant in tables.PAPER_TABLE2:
        out.append(Target(f"{variant}: error (m)", rows2.get(variant, {}).get("error_mean_m"), ERROR_LIMIT_M))
    fine, coarse = (rows2.get(v, {}).get("error_mean_m") for v in (FINE, COARSE))
    out.append(Target(f"{FINE} minus {COARSE} (m)", None if None in (fine, coarse) else fine - coarse, 0.0))
    return out


def evaluation(table1: dict | None) -> str:
    """Which evaluation the unfiltered rows come from: the meta-test tasks and seed, or others."""
    if table1 is None:
        return "no table1 record"
    e, meta_test = table1.get("eval", {}), config.make_config("paper").meta.eval
    tasks = [r["target_m"] for r in table1["rows"].get(NETS[0], {}).get("per_task", [])]
    on_meta_test = e.get("seed") == meta_test.seed and tasks == [float(t) for t in meta_test.tasks]
    kind = "the meta-test tasks and seed" if on_meta_test else "development targets and seed"
    return f"{kind} (seed {e.get('seed')}, {e.get('n_tasks')} tasks x {e.get('repetitions')} kicks)"


def record_paths(args) -> dict[str, Path]:
    """The three records to read, from the command line's choice."""
    if args.run_dir is not None:
        d = Path(args.run_dir)
        return {"experts": d / "experts" / "experts.json", "table1": d / "meta" / "table1.json",
                "table2": d / "filter" / "table2.json"}  # fmt: skip
    if args.arm is not None:
        return {name: DEV_RECORDS / f"{args.arm}_{name}_{args.device}.json" for name in ("experts", "table1", "table2")}
    return {name: ROOT / "results" / f"{name}.json" for name in ("experts", "table1", "table2")}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--run-dir", type=Path, help="a run directory (its experts/, meta/, filter/ records)")
    which.add_argument("--arm", help="a development arm's records in experiments/results/dev_starting_kicks/")
    which.add_argument("--published", action="store_true", help="the published run's records in results/")
    parser.add_argument("--device", default="h100", help="with --arm: the device part of the names (default h100)")
    args = parser.parse_args(argv)
    records, missing = {}, []
    for name, path in record_paths(args).items():
        if path.exists():
            try:
                records[name] = runio.read_json(path)
            except ValueError as err:
                print(f"error: {err}", file=sys.stderr)
                return 2
        else:
            records[name], missing = None, [*missing, runio.shown(path)]
    if all(r is None for r in records.values()):
        print(f"error: none of the records exists: {', '.join(missing)}", file=sys.stderr)
        return 2
    found = targets(records["experts"], records["table1"], records["table2"])
    print(f"evaluation: {evaluation(records['table1'])}")
    for t in found:
        shown = "not measured" if t.measured is None else f"{t.measured:.3f}"
        verdict = {True: "met", False: "MISSED", None: "-"}[t.met]
        print(f"  {t.name:50s} {shown:>12s}  {'<=' if t.at_most else '>='} {t.limit:<5g} {verdict}")
    if missing:
        print(f"not made: {', '.join(missing)}")
    if any(t.met is False for t in found):
        print("verdict: a target is missed")
        return 1
    if any(t.met is None for t in found):
        print("verdict: incomplete (a target not measured)")
        return 2
    print("verdict: every target met")
    return 0


if __name__ == "__main__":
    sys.exit(main())
