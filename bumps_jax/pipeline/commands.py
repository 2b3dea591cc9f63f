"""The commands besides the stages that every task has: report, publish, evaluate; a task's own
(its folder's `commands.py`: the kick's render, video, showcase and kick) come from the registry.

Each takes the pipeline config, the run directory and the parsed arguments; each checks its
inputs (with their paths) before any long work.
"""

from __future__ import annotations

from pathlib import Path

from bumps_jax import config, runio


def run(command: str, cfg, run_dir: Path, args) -> None:
    """Run `command`: one of every task's, else one of the config's task's own."""
    from bumps_jax.tasks import registry as tasks  # noqa: PLC0415

    every = {"report": report, "publish": publish, "evaluate": evaluate}
    own = {name: spec.run for name, spec in tasks.own_commands(cfg.task).items()}
    if command not in {**every, **own}:
        raise ValueError(f"the {cfg.task} task has no {command} command; it has {', '.join(sorted({**every, **own}))}")
    {**every, **own}[command](cfg, Path(run_dir), args)


def report(cfg, run_dir: Path, args) -> None:
    from bumps_jax.report import publish as publish_mod  # noqa: PLC0415
    from bumps_jax.report import summary as report_mod  # noqa: PLC0415

    if not run_dir.is_dir():
        raise ValueError(f"no run directory {str(run_dir)!r}: run a stage first (e.g. python -m bumps_jax demo)")
    if not report_mod.has_results(run_dir):
        seeds = sorted(p.name for p in run_dir.glob("seed*") if report_mod.has_results(p))
        if seeds:  # `reproduce --seeds`: one run directory per seed under it
            raise ValueError(f"{run_dir} holds one run per seed ({', '.join(seeds)}): report one of them, "
                             f"e.g. --run-dir {run_dir / seeds[0]}")  # fmt: skip
        raise ValueError(f"{run_dir} holds no stage results yet: run a stage first")
    path = publish_mod.write_report(run_dir)
    print(path.read_text())
    print(f"wrote {path}")


def publish(cfg, run_dir: Path, args) -> None:
    """A finished paper run into the repository; another task's run into results/<task>/."""
    from bumps_jax.pipeline import runner as pipeline  # noqa: PLC0415
    from bumps_jax.report import publish as publish_mod  # noqa: PLC0415
    from bumps_jax.report import seeds  # noqa: PLC0415
    from bumps_jax.tasks import registry as tasks  # noqa: PLC0415

    seed_runs = [Path(d) for d in getattr(args, "seed_runs", [])]
    for d in [run_dir, *seed_runs]:
        check_paper_run(d, cfg)  # before anything is read further or written
    if getattr(args, "baseline_at_budget", False):  # the run's baseline alone, beside the preset's own
        if seed_runs or getattr(args, "records_only", False):
            raise ValueError("--baseline-at-budget publishes one baseline run: not with --seed-runs or --records-only")
        for path in publish_mod.publish_at_budget(run_dir, cfg.task):
            print(f"wrote {path}")
        return
    # A run with a stage unfinished would leave that stage's committed record from an older run
    # beside the new ones (and the report would set them side by side): refused, naming them.
    missing = pipeline.unfinished(run_dir, tasks.get(cfg.task).stages, cfg.task)
    if missing:
        records = ", ".join(f"{m}/{pipeline.stage_module(m, cfg.task).OUTPUT}" for m in missing)
        raise ValueError(
            f"not published: {runio.shown(run_dir)} has not finished {', '.join(missing)} (no {records}); "
            "run those stages into it before publishing"
        )
    for d in seed_runs:  # every seed's run checked before anything is written
        missing = pipeline.unfinished(d, ("experts", "meta", "filter"), cfg.task)
        if missing:
            raise ValueError(f"not published: {runio.shown(d)} (--seed-runs) has not finished {', '.join(missing)}")
    paper_rows = tasks.get(cfg.task).report.paper_rows
    records_only = getattr(args, "records_only", False)
    if records_only and not paper_rows:
        raise ValueError(f"--records-only: the {cfg.task} task's publish writes records only already")
    # The seeds' summary first: the README and results pages written next read it.
    written = seeds.publish_seeds([run_dir, *seed_runs], cfg.task, runio.command_line()) if seed_runs else []
    if not paper_rows:  # another task's records go to results/<task>/
        for path in written + publish_mod.publish_task(run_dir, cfg.task):
            print(f"wrote {path}")
        return
    made_with = publish_mod.run_config(run_dir, cfg)
    try:
        pipeline.check_current(made_with, run_dir, tasks.get(made_with.task).stages, inputs=not records_only)
    except pipeline.StaleRunError as err:
        raise ValueError(f"not published: {err}") from None
    if made_with.preset != cfg.preset:
        print(f"{run_dir} is a {made_with.preset} run: publishing it with the {made_with.preset} preset's config")
    written += publish_mod.publish(run_dir, cfg=made_with, assets=not records_only)
    for path in written:
        print(f"wrote {path}")
    if records_only:
        print(f"assets/ kept: the prior later runs start from and the shipped policies are not {run_dir}'s")


def check_paper_run(run_dir: Path, cfg) -> None:
    """ValueError naming a run `publish` must not copy: the committed results and the pages that
    describe them are the paper preset's, so a run of another preset (a tiny demo) would replace
    them with numbers of another budget."""
    from bumps_jax.report import publish as publish_mod  # noqa: PLC0415

    if not run_dir.is_dir():
        raise ValueError(f"not published: no run directory {runio.shown(run_dir)}")
    try:
        preset, _ = publish_mod.made_with(run_dir, cfg)
    except ValueError:  # neither record that names a preset: the copy itself says what is missing
        return
    if preset != config.PAPER:
        raise ValueError(
            f"not published: {runio.shown(run_dir)} is a {preset} run; the committed results are the "
            f"{config.PAPER} preset's (publish a run of `reproduce --preset {config.PAPER}`)"
        )


def evaluate(cfg, run_dir: Path, args) -> None:
    """A finished run on the held-out targets (its heldout stage: run_dir/heldout/heldout.json),
    or on the development targets (`--dev`: run_dir/dev/dev.json, outside the pipeline)."""
    from bumps_jax.pipeline import runner as pipeline  # noqa: PLC0415
    from bumps_jax.pipeline.stages import heldout  # noqa: PLC0415
    from bumps_jax.tasks import registry as tasks  # noqa: PLC0415

    if args.heldout == args.dev:
        raise ValueError("evaluate needs one of --heldout (reporting) or --dev (design choices)")
    tasks.check_stage(cfg.task, "heldout")  # --dev runs the held-out stage's evaluation on other targets
    if args.dev and "dev" not in cfg:
        raise ValueError(f"evaluate --dev: the {cfg.task} task's config has no dev section (development targets)")
    if args.heldout:
        pipeline.run_stage("heldout", cfg, run_dir, force=args.force)
        print(f"wrote {run_dir / 'heldout' / heldout.OUTPUT}")
        return
    heldout.run(cfg, run_dir, section="dev")  # its inputs checked, then run_dir/dev made writable
    print(f"wrote {run_dir / 'dev' / 'dev.json'}")
