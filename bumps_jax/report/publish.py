"""What a finished run leaves behind: its report.md, and its records, figures and policies
copied into the repository (`publish` for the kick's paper run, `publish_task` for another task's).
"""

from __future__ import annotations

import shutil
from pathlib import Path

from bumps_jax import config, runio
from bumps_jax.report import budgets, curves, error_map
from bumps_jax.report import readme as readme_table
from bumps_jax.report import summary as report
from bumps_jax.report import task_report as report_task
from bumps_jax.tasks import registry as tasks

REPORT = "report.md"  # under the run directory
POLICIES = "assets/policies"  # the shipped policies (`policies.write`)
AT_BUDGET_CURVE = "baseline_at_budget_curve.png"  # the training curve of `publish_at_budget`'s baseline
# What `publish` copies from a finished paper run into the repository: run file -> committed path.
PUBLISHED = {
    "prior/kick_prior.json": "results/kick_prior.json",
    "prior/kick_sweep.png": "docs/kick_sweep.png",
    "prior/kick_prior_timing.json": "benchmarks/results/kick_prior.json",
    # The prior the run's experts started from: the committed asset that later runs start from.
    "prior/kick_prior_asset.json": report.PRIOR_ASSET,
    "experts/experts.json": "results/experts.json",
    "experts/experts.md": "docs/experts.md",
    "experts/progress.csv": "docs/experts_progress.csv",
    "experts/starting_kicks.json": "docs/experts_starting_kicks.json",
    "meta/table1.json": "results/table1.json",
    "meta/table1.md": "docs/table1.md",
    "filter/table2.json": "results/table2.json",
    "filter/table2.md": "docs/table2.md",
    "filter/error_vs_target.png": "docs/error_vs_target.png",
    "filter/context_map.png": "docs/context_map.png",
    "baseline/baseline.json": "results/baseline.json",
    "baseline/baseline_curve.png": "docs/baseline_curve.png",
    "pipeline.json": "results/pipeline.json",
    "heldout/heldout.json": "results/heldout.json",
    "filtered_kicks.gif": "docs/filtered_kicks.gif",
}

# What `publish --task <task>` copies from a finished run: run file -> path under results/<task>/.
TASK_PUBLISHED = {
    "experts/experts.json": "experts.json",
    "experts/progress.csv": "experts_progress.csv",  # every expert's training curve
    "meta/table1.json": "table1.json",
    "filter/table2.json": "table2.json",
    "pipeline.json": "pipeline.json",
    "report.md": "report.md",
    "filter/error_vs_target.png": "error_vs_target.png",
    "filter/context_map.png": "context_map.png",
    "baseline/baseline.json": "baseline.json",
    "baseline/baseline_curve.png": "baseline_curve.png",
    "error_map.png": "error_map.png",
}


def publish(run_dir: str | Path, root: str | Path = ".", cfg=None, assets: bool = True) -> list[Path]:
    """Copy a finished paper run's results, tables and figures into results/ and docs/, and its
    kick prior into assets/; with `cfg` (the run's config) and a finished filter stage, ship its
    policies into assets/policies/ (the task's `Report.ship_policies`: the kick's `policies.write`).
    assets=False: neither (the committed prior and policies stay another run's). Then rebuild
    docs/results.md and README's results table. Returns the paths written."""
    run_dir, root = Path(run_dir), Path(root)
    written = []
    for rel, dest in PUBLISHED.items():
        if dest.startswith("assets/") and not assets:
            continue
        if (run_dir / rel).exists():
            (root / dest).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(run_dir / rel, root / dest)
            written.append(root / dest)
    if not any(p.suffix == ".json" for p in written):
        raise ValueError(f"{run_dir} holds no stage results to publish")
    ship = None if cfg is None or not assets else tasks.get(cfg.task).report.ship_policies
    if ship is not None and (run_dir / "filter" / "table2.json").exists():
        written += ship(cfg, run_dir, root / POLICIES)
    written.append(report.write_committed(root))
    if (root / "README.md").exists():
        written.append(readme_table.write_readme(root))
    return written


def made_with(run_dir: str | Path, cfg) -> tuple[str, dict]:
    """(preset, overrides) `run_dir` was made with, as its pipeline.json records them (a run of
    single stages: its experts record's preset, with `cfg`'s overrides); ValueError where it
    holds neither record."""
    run_dir = Path(run_dir)
    if (run_dir / "pipeline.json").exists():
        record = runio.read_json(run_dir / "pipeline.json")
        return record.get("preset", cfg.preset), record.get("overrides", {})
    record = runio.read_json(run_dir / "experts" / "experts.json", "the experts' record: run train-experts first")
    return record.get("preset", cfg.preset), config.overrides_of(cfg)


def run_config(run_dir: str | Path, cfg):
    """The config `run_dir` was made with (`made_with`). The policies shipped from a run are shaped
    by its own config, not by the publishing command's default preset."""
    preset, overrides = made_with(run_dir, cfg)
    if preset == cfg.preset and overrides == config.overrides_of(cfg):
        return cfg
    return config.make_config(preset, {key: tuple(v) if isinstance(v, list) else v for key, v in overrides.items()})


def write_report(run_dir: str | Path) -> Path:
    """run_dir/report.md: the kick's report (`report.build`), or another task's (`report_task.build_task`) where the
    run's records name one."""
    path = Path(run_dir) / REPORT
    task = report_task.run_task(run_dir)
    paper_rows = tasks.get(task).report.paper_rows
    if not paper_rows:
        report_task.write_figures(run_dir)
    runio.write_text(path, report.build(run_dir) if paper_rows else report_task.build_task(run_dir, task))
    runio.sync("report")  # every process reads it back
    return path


def remove_report(run_dir: str | Path) -> list[Path]:
    """Remove run_dir/report.md and the figure drawn from several stages' records (`error_map`),
    where they exist, before a stage changes its records: a report never shows records that are
    gone or replaced. Returns the paths removed; `write_report` writes them anew."""
    found = [p for p in (Path(run_dir) / REPORT, Path(run_dir) / error_map.NAME) if p.exists()]
    for path in found:
        runio.remove(path)
    return found


def publish_task(run_dir: str | Path, task: str, root: str | Path = ".") -> list[Path]:
    """Copy a finished run of `task` (one without the paper's rows) into results/<task>/
    (`TASK_PUBLISHED`), then regenerate the task's blocks beside others' published results
    (`Report.published_blocks`)."""
    run_dir, root = Path(run_dir), Path(root)
    if not any((run_dir / rel).exists() for rel in TASK_PUBLISHED if rel.endswith(".json")):
        raise ValueError(f"{run_dir} holds no stage results to publish")
    tasks.check_record_task(report_task.run_task(run_dir), task, str(run_dir))
    write_report(run_dir)  # from the records as they are now, not as the last stage left it
    written = []
    for rel, name in TASK_PUBLISHED.items():
        if (run_dir / rel).exists():
            dest = root / "results" / tasks.folder(task) / name
            dest.parent.mkdir(parents=True, exist_ok=True)
            if rel == "report.md":  # its figures under their published names
                text = (run_dir / rel).read_text()
                for fig in (f for f in TASK_PUBLISHED if f.endswith(".png")):
                    text = text.replace(f"]({fig})", f"]({TASK_PUBLISHED[fig]})")
                runio.write_text(dest, text)
            else:
                shutil.copyfile(run_dir / rel, dest)
            written.append(dest)
    if (root / report.COMMITTED["experts"]).exists():  # the results page's env steps per arm span every task
        written.append(report.write_committed(root))
    blocks = tasks.get(task).report.published_blocks  # the task's rows beside others' published results
    return written + ([] if blocks is None else blocks(root))


def publish_at_budget(run_dir: str | Path, task: str, root: str | Path = ".") -> list[Path]:
    """A finished baseline run whose env steps per seed are BUMPS' experts' whole (the task's
    committed experts record) to within one of its updates, into the task's results folder as
    `budgets.AT_BUDGET`, beside the preset's own baseline; then the results page and, for the
    task with the paper's rows, README. ValueError naming what does not fit, before any copy."""
    run_dir, root = Path(run_dir), Path(root)
    record = runio.read_json(run_dir / "baseline" / "baseline.json", "a finished baseline: run its stage first")
    tasks.check_record_task(record.get("task", tasks.DEFAULT), task, str(run_dir))
    experts = budgets.task_records(root, task)["experts.json"]
    total = budgets.experts_total(experts)
    if total is None:
        raise ValueError(f"--baseline-at-budget: no committed experts record of {task} with its env steps to match")
    ours, theirs = report.physics_step(record), report.physics_step(experts)
    if ours != theirs:
        raise ValueError(f"--baseline-at-budget: {runio.shown(run_dir)}'s baseline ran on {ours} physics, "
                         f"the committed experts on {theirs}")  # fmt: skip
    per_seed, per_update = int(record["env_steps_per_seed"]), int(record["curve"]["env_steps"][0])
    if abs(per_seed - total) > per_update:
        nearest = max(1, round(total / per_update)) * per_update
        raise ValueError(
            f"--baseline-at-budget: {runio.shown(run_dir)}'s baseline ran {per_seed:,} env steps per seed, not BUMPS' "
            f"experts' {total:,} within one update ({per_update:,}): train it with "
            f"baseline.ppo.total_env_steps={nearest}"
        )
    folder = root / "results" / tasks.folder(task)
    paper_rows = tasks.get(task).report.paper_rows
    dest = folder / budgets.AT_BUDGET
    dest.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(run_dir / "baseline" / "baseline.json", dest)
    # Its training curve, drawn from the record (the kick's figures sit in docs/, on the results page).
    written = [dest, curves.baseline(record, (root / "docs" if paper_rows else folder) / AT_BUDGET_CURVE)]
    if (root / report.COMMITTED["experts"]).exists():  # the results page's env steps per arm span every task
        written.append(report.write_committed(root))
    if paper_rows and (root / "README.md").exists():
        written.append(readme_table.write_readme(root))
    return written
