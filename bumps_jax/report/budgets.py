"""Env steps per arm: what each part of BUMPS and the baseline spent, from the committed records
of every task (docs/results.md), so that every comparison states both arms' budgets."""

from __future__ import annotations

import json
from pathlib import Path

import ml_collections

# Where each task's committed records are: the default task's under results/, another's under
# results/<task>/ (`publish` and `publish --task`).
RECORDS = ("experts.json", "table1.json", "table2.json", "baseline.json")
# A baseline arm trained at BUMPS' whole budget, beside the preset's own (`publish --baseline-at-budget`).
AT_BUDGET = "baseline_at_budget.json"


def task_records(root: Path, task: str) -> dict:
    """{name: record or None} of a task's committed records (`registry.folder`)."""
    from bumps_jax.tasks import registry  # noqa: PLC0415

    folder = Path(root) / "results" / registry.folder(task)
    return {n: json.loads((folder / n).read_text()) if (folder / n).exists() else None for n in (*RECORDS, AT_BUDGET)}


def seeds_phrase(n: int) -> str:
    """'1 seed', '3 seeds'."""
    return f"{n} seed" if n == 1 else f"{n} seeds"


def experts_total(experts: dict | None) -> int | None:
    """BUMPS' experts' env steps in all: every expert's whole budget (the record's
    `env_steps_total`) times the experts (None: a record without it)."""
    if not experts or "env_steps_total" not in experts:
        return None
    return len(experts["tasks_m"]) * int(experts["env_steps_total"])


def episode_steps(task: str, env: dict) -> int:
    """Control steps of one episode of `task` under a record's env config."""
    from bumps_jax.tasks import registry  # noqa: PLC0415

    return int(registry.get(task).env_class.n_steps_of(ml_collections.ConfigDict(env)))


def rows(task: str, rec: dict) -> list[tuple[str, str, int | None]]:
    """(arm, part, env steps) for one task: BUMPS' experts (each part of their budget, all experts
    together), cloning, each filtering variant's selection rollouts, and the baseline per seed."""
    experts, t1, t2, base = (rec[n] for n in RECORDS)
    out = []
    if experts and "tasks_m" in experts:
        n = len(experts["tasks_m"])
        for part, steps in experts.get("env_steps_breakdown", {"ppo": experts.get("env_steps")}).items():
            out.append(("BUMPS", f"experts: {part} ({n} experts)", None if steps is None else n * steps))
    if t1:
        cloning = t1.get("cloning", {})
        out.append(("BUMPS", f"cloning: {cloning.get('variant', 'the experts episodes')}",
                    cloning.get("env_steps_total", t1.get("dataset_pairs"))))  # fmt: skip
    if t2 and "env" in t2:
        steps = episode_steps(task, t2["env"])
        for name, r in t2.get("rows", {}).items():
            if "rollouts" in r:
                out.append(("BUMPS", f"filtering: {name}'s selection rollouts ({r['n_tasks']} test contexts)",
                            r["rollouts"] * steps))  # fmt: skip
    if base and "env_steps_per_seed" in base:
        seeds = seeds_phrase(base["seeds"])
        out.append(("baseline", f"multi-task PPO, per seed ({seeds})", base["env_steps_per_seed"]))
    at_budget = rec.get(AT_BUDGET)
    if at_budget:
        what = f"multi-task PPO at BUMPS' experts' budget, per seed ({seeds_phrase(at_budget['seeds'])})"
        out.append(("baseline", what, at_budget["env_steps_per_seed"]))
    return out


def section(root: str | Path = ".") -> list[str]:
    """docs/results.md's section: one table per task with committed records."""
    from bumps_jax.tasks import registry  # noqa: PLC0415

    lines = ["## Env steps per arm", "",
             "What each arm spent, from the committed records (evaluation episodes not counted). BUMPS' "
             "total is its experts, its cloning and one filtering variant's selection.", ""]  # fmt: skip
    for task in registry.TASKS:
        table = rows(task, task_records(Path(root), task))
        if not table:
            continue
        lines += [f"**{task}**", "", "| arm | part | env steps |", "|---|---|---|"]
        lines += [f"| {arm} | {part} | {'not recorded' if s is None else f'{s:,}'} |" for arm, part, s in table]
        known = [s for arm, part, s in table if arm == "BUMPS" and not part.startswith("filtering") and s]
        lines += ["", f"BUMPS before filtering: {sum(known):,} env steps.", ""]
    return lines
