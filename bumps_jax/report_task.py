"""The report of another contextual task's runs (not the kick): no paper columns, no prior, no
held-out stage; and `publish --task <task>`, which copies such a run into results/<task>/.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from bumps_jax import tables
from bumps_jax.report import EXTRAS, STAGES, load, pipeline_lines, preamble_lines, stages_table

# What `publish --task <task>` copies from a finished run: run file -> path under results/<task>/.
TASK_PUBLISHED = {
    "experts/experts.json": "experts.json",
    "meta/table1.json": "table1.json",
    "filter/table2.json": "table2.json",
    "pipeline.json": "pipeline.json",
    "report.md": "report.md",
    "filter/error_vs_target.png": "error_vs_target.png",
    "filter/context_map.png": "context_map.png",
}


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


def publish_task(run_dir: str | Path, task: str, root: str | Path = ".") -> list[Path]:
    """Copy a finished run of `task` (not the kick) into results/<task>/ (`TASK_PUBLISHED`)."""
    run_dir, root = Path(run_dir), Path(root)
    if run_task(run_dir) != task:
        raise ValueError(f"{run_dir} holds no {task} run (its records name {run_task(run_dir)!r})")
    written = []
    for rel, name in TASK_PUBLISHED.items():
        if (run_dir / rel).exists():
            dest = root / "results" / task / name
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(run_dir / rel, dest)
            written.append(dest)
    if not any(p.suffix == ".json" for p in written):
        raise ValueError(f"{run_dir} holds no stage results to publish")
    return written
