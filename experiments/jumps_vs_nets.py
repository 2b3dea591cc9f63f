"""Do the meta-policies pay for jumps in the experts' starting kicks? A reader of the committed
development arms (experiments/results/dev_starting_kicks/): for each arm with both an experts and a
table1 record of one device, the largest parameter jump between neighbouring starting kicks
(`starting_kicks_smoothness.jump`, PARAM_SCALE units), the experts' error and each unfiltered
meta-policy's error above the experts' (what the net loses on the development targets between and
at the tasks), then Spearman's rank correlation of the jump with each excess over the arms.

The family scheme's arms are left out: their experts err over 1.3 m, so their nets' excess says
nothing about interpolation. It writes nothing: the numbers are the records'.

    python -m experiments.jumps_vs_nets [--device h100]
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from experiments.family_targets import DEV_RECORDS, NETS, ROOT


class Arm(NamedTuple):
    name: str
    paper_budget: bool
    jump: float  # largest jump between neighbouring starting kicks (PARAM_SCALE units)
    experts_m: float
    excess_m: dict  # net -> unfiltered error minus the experts' (m)


def arms(records: Path = DEV_RECORDS, device: str = "h100") -> list[Arm]:
    """Every arm in `records` with experts and table1 records of `device`, the family scheme's left out."""
    out = []
    for table1_path in sorted(records.glob(f"*_table1_{device}.json")):
        name = table1_path.name.removesuffix(f"_table1_{device}.json")
        experts_path = records / f"{name}_experts_{device}.json"
        if not experts_path.exists():
            continue
        experts, table1 = json.loads(experts_path.read_text()), json.loads(table1_path.read_text())
        if scheme(experts["command"]) == "family":
            continue
        rows = table1["rows"]
        excess = {net: rows[net]["error_mean_m"] - experts["error_mean_m"] for net in NETS}
        jump = experts["starting_kicks_smoothness"]["jump"]
        out.append(Arm(name, "paper_budget" in name, jump, experts["error_mean_m"], excess))
    return out


def scheme(command: str) -> str:
    """The tuning scheme a record's command set (its last `experts.tune.scheme=`, as `--set` reads
    them); the preset's "per_task" where it set none."""
    found = re.findall(r"experts\.tune\.scheme=(\w+)", command)
    return found[-1] if found else "per_task"


def spearman(x, y) -> float:
    """Spearman's rank correlation (ties ranked by order: the jumps are continuous)."""
    rx, ry = (np.argsort(np.argsort(np.asarray(v))) for v in (x, y))
    return float(np.corrcoef(rx, ry)[0, 1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="h100", help="the records' device suffix, e.g. h100")
    args = parser.parse_args(argv)
    found = arms(device=args.device)
    if len(found) < 3:
        where = DEV_RECORDS.relative_to(ROOT)
        parser.error(f"{len(found)} arm(s) with experts and table1 records of device {args.device!r} in {where}")
    print(f"{'arm':80s} budget  jump  experts  " + "  ".join(f"{n} excess" for n in NETS))
    for arm in sorted(found, key=lambda a: a.jump):
        budget = "paper" if arm.paper_budget else "short"
        excess = "  ".join(f"{arm.excess_m[n]:+15.3f}" for n in NETS)
        print(f"{arm.name[:80]:80s} {budget:6s} {arm.jump:5.2f}  {arm.experts_m:7.3f}  {excess}")
    jumps = [a.jump for a in found]
    for net in NETS:
        rho = spearman(jumps, [a.excess_m[net] for a in found])
        print(f"Spearman(jump, {net} excess) over {len(found)} arms: {rho:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
