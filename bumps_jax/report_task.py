"""The report of another contextual task's runs (not the kick): no paper columns, no prior, no
held-out stage; and `publish --task <task>`, which copies such a run into results/<task>/.
"""

from __future__ import annotations

from pathlib import Path

from bumps_jax import tables
from bumps_jax.report import EXTRAS, STAGES, load, pipeline_lines, preamble_lines, stages_table


def run_task(run_dir: str | Path) -> str:
    """The task a run's records name (`task`; the kick's records name none)."""
    for rel in (STAGES["experts"], STAGES["meta"], STAGES["filter"]):
        record = load(Path(run_dir), rel)
        if record:
            return record.get("task", "kick")
    return "kick"


def build_task(run_dir: str | Path, task: str) -> str:
    """The report's markdown of a run of `task` (not the kick): its stages' wall times, the
    experts, Table 1 and Table 2 in the task's unit."""
    run_dir = Path(run_dir)
    found = {name: load(run_dir, STAGES[name]) for name in ("experts", "meta", "filter")}
    lines = [f"# BUMPS on {task}: run `{run_dir.name}`", ""]
    first = next((v for v in found.values() if v), None)
    if first is None:
        return "\n".join([*lines, "No stage has written results in this directory yet.", ""])
    unit = first.get("unit", "m")
    lines += preamble_lines([first["preset"]], first)
    stage_lines, total = stages_table(found)
    lines += stage_lines
    lines += pipeline_lines(load(run_dir, EXTRAS["pipeline"]), total)
    if found["experts"]:
        lines += ["## Experts (each on its own training target)", "", tables.task_experts_markdown(found["experts"])]
    if found["meta"]:
        lines += [tables.task_table1_markdown(found["meta"]["rows"], unit)]
    if found["filter"]:
        lines += [tables.task_table2_markdown(found["filter"]["rows"], unit)]
    figures = sorted(p.relative_to(run_dir).as_posix() for p in run_dir.glob("*/*.png"))
    if figures:
        lines += ["## Figures", ""] + [f"![{f}]({f})" for f in figures] + [""]
    return "\n".join(lines)
