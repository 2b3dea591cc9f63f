"""The report of another contextual task's runs (not the kick): no paper columns, no prior, no
held-out stage; and `publish --task <task>`, which copies such a run into results/<task>/.
"""

from __future__ import annotations

from pathlib import Path

from bumps_jax.report import budgets, error_map, tables
from bumps_jax.report.summary import EXTRAS, STAGES, load, pipeline_lines, preamble_lines, stages_table
from bumps_jax.tasks import registry as tasks


def first_record(run_dir: str | Path) -> dict | None:
    """The first stage record a run holds (experts, meta, filter, or a baseline's run alone), None
    where none has written its record yet."""
    for rel in (STAGES["experts"], STAGES["meta"], STAGES["filter"], EXTRAS["baseline"]):
        record = load(Path(run_dir), rel)
        if record:
            return record
    return None


def run_task(run_dir: str | Path) -> str:
    """The task a run's records name (`task`; records from before they named one are the default
    task's, the only one there was), the default task where no stage has written its record yet."""
    from bumps_jax.tasks import registry as tasks  # noqa: PLC0415

    record = first_record(run_dir) or {}
    return record.get("task", tasks.DEFAULT)


def records(run_dir: Path) -> dict:
    """The run's stage records (name -> record, or None where the stage has not written it)."""
    found = {name: load(run_dir, STAGES[name]) for name in ("experts", "meta", "filter")}
    found["baseline"] = load(run_dir, EXTRAS["baseline"])
    return found


def write_figures(run_dir: str | Path) -> None:
    """The figures drawn from several stages' records: the error map of a 2-D context."""
    error_map.write(run_dir, records(Path(run_dir)))


def build_task(run_dir: str | Path, task: str) -> str:
    """The report's markdown of a run of `task` (not the kick): its stages' wall times, the
    experts, Table 1, Table 2 and the multi-task PPO baseline in the task's unit."""
    run_dir = Path(run_dir)
    stages = tasks.get(task).stages
    found = {name: record for name, record in records(run_dir).items() if name in stages}  # the task's own
    lines = [f"# BUMPS on {task}: run `{run_dir.name}`", ""]
    first = next((v for v in found.values() if v), None)
    if first is None:
        return "\n".join([*lines, "No stage has written results in this directory yet.", ""])
    unit = first.get("unit", "m")
    lines += preamble_lines([first["preset"]], first)
    stage_lines, own_s = stages_table(found)
    lines += stage_lines
    lines += pipeline_lines(load(run_dir, EXTRAS["pipeline"]), own_s)
    experts, meta, filtered, baseline = (found.get(name) for name in ("experts", "meta", "filter", "baseline"))
    if experts:
        lines += ["## Experts (each on its own training target)", "", tables.task_experts_markdown(experts)]
    if meta:
        lines += [tables.task_table1_markdown(meta["rows"], unit)]
    if filtered:
        lines += [tables.task_table2_markdown(filtered["rows"], unit)]
    if baseline:
        lines += task_baseline_lines(baseline, experts, filtered, unit)
    figures = sorted(p.relative_to(run_dir).as_posix() for p in [*run_dir.glob("*.png"), *run_dir.glob("*/*.png")])
    if figures:
        lines += ["## Figures", ""] + [f"![{f}]({f})" for f in figures] + [""]
    return "\n".join(lines)


def task_baseline_lines(baseline: dict, experts: dict | None, filtered: dict | None, unit: str) -> list[str]:
    """The multi-task PPO baseline beside BUMPS: its test error, its env steps against the experts'."""
    lo, hi = baseline["sample_task_range"]
    start = baseline["start"]
    lines = [
        "## Multi-task PPO baseline (one policy for every target, the same PPO)",
        "",
        f"One policy over (state, target) trained by PPO from a fresh init on targets drawn from U[{lo:g}, {hi:g}] "
        f"{unit}, {budgets.seeds_phrase(baseline['seeds'])} x {baseline['env_steps_per_seed']:,} env steps: test error "
        f"{baseline['error_mean_m']:.2f} {unit} over {len(baseline['eval_tasks'])} test targets, accuracy "
        f"{baseline['accuracy_mean']:.2f} (at the start: {start['error_mean_all_m']:.2f} {unit}).",
    ]
    if experts:
        n = len(experts["tasks_m"])
        total = n * experts.get("env_steps_total", experts["env_steps"])
        parts = ", ".join(f"{k} {v:,}" for k, v in experts.get("env_steps_breakdown", {}).items() if v is not None)
        lines.append(f"BUMPS's experts used {total:,} env steps in all ({n} experts, each: {parts}).")
    if filtered:
        name, best = min(filtered["rows"].items(), key=lambda kv: kv[1]["error_mean_m"])
        lines.append(f"Best BUMPS variant ({name}): {best['error_mean_m']:.2f} {unit} on its test targets.")
    return [*lines, ""]
