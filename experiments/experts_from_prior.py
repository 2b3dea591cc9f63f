"""The same kick prior's experts on another device count: a run's experts stage started from the
prior another run made, beside that run's experts.

A prior stage's record (`kick_prior.json`, e.g. the published seed 0's, made on four processes)
holds its anchors and sweep: all the experts' starting kicks read. Written as the prior asset of
a run folder that has no prior stage of its own, `reproduce --stages experts` starts from it, on
however many processes this command is given. The record: this run's experts (the starting
kicks' tuning, each restart's fresh cost, and the experts' error) beside those of `--against`,
the experts record of the run that made the prior.

    python -m experiments.experts_from_prior --prior results/kick_prior.json \\
        --against results/experts.json --run-dir runs/same_prior --out experiments/results/X.json
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from experiments.device_count import summary_provenance
from experiments.kick_runs import run_row


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--prior", type=Path, required=True, help="a prior stage's record (kick_prior.json)")
    parser.add_argument("--against", type=Path, required=True,
                        help="the experts record (experts.json) of the run that made --prior")  # fmt: skip
    parser.add_argument("--run-dir", type=Path, required=True, help="the run folder for this run's experts (resumes)")
    parser.add_argument("--seed", type=int, default=0, help="the seed run (reproduce --seeds) whose experts run")
    parser.add_argument("--preset", default="paper", help="paper (reproduce), or tiny (demo: a check on a CPU)")
    parser.add_argument("--processes", type=int, default=None, help="reproduce --processes (default: one process)")
    parser.add_argument("--out", type=Path, required=True, help="the record to write (.json)")
    args = parser.parse_args(argv)
    if args.seed < 0:
        parser.error(f"--seed must be >= 0, got {args.seed}")
    if args.processes is not None and args.processes < 1:
        parser.error(f"--processes must be >= 1, got {args.processes}")
    return args


def asset(stage_record: dict, source: Path, prior_cfg) -> dict:
    """The prior asset a prior stage writes beside its record (`kick_model.make_record`), made from
    the record: its main anchor, anchors, sweep, env and episodes; `made_from` names the record.
    Its config is `prior_cfg` (the preset's prior section), refused where it differs from what the
    record says the stage ran (its target, extremes and search sizes)."""
    from bumps_jax import records  # noqa: PLC0415
    from bumps_jax.tasks.kick import keyframes as kick_model  # noqa: PLC0415

    anchors = stage_record.get("anchors")
    if not isinstance(anchors, dict) or set(anchors) != set(kick_model.ANCHORS) or not stage_record.get("sweep"):
        raise ValueError(f"--prior {source}: not a kick prior stage's record (it needs anchors "
                         f"{list(kick_model.ANCHORS)} and a sweep)")  # fmt: skip
    extremes = stage_record.get("extremes", {})
    ran = {"target": stage_record.get("target_m"), "eval_repetitions": stage_record.get("n_reps"),
           "generations": stage_record.get("generations"), "population_size": stage_record.get("population_size"),
           "repetitions": stage_record.get("repetitions_per_candidate"),
           **{f"extremes.{n}": extremes.get(n, {}).get("target_m") for n in prior_cfg.extremes}}  # fmt: skip
    preset = prior_cfg.to_dict()
    for key, value in ran.items():
        mine = records.lookup(preset, key)
        if value != mine:
            raise ValueError(f"--prior {source}: made with prior.{key} {value!r}, this preset has {mine!r}")
    evaluation = {"target": stage_record["target_m"], "repetitions": stage_record["n_reps"],
                  **{k: stage_record[f"{k}_m"] for k in ("mean_error", "std_error")},
                  **{k: stage_record[k] for k in ("valid_fraction", "struck_fraction", "fallen_fraction")}}  # fmt: skip
    return kick_model.make_record(anchors["main"], prior_cfg, env=stage_record["env"], evaluation=evaluation,
                                  generations_run=stage_record["generations"], anchors=anchors,
                                  sweep=stage_record["sweep"], episodes=stage_record["episodes"],
                                  made_from=str(source))  # fmt: skip


def place(args, cfg) -> Path:
    """Write the prior asset into the seed run's prior/ (the same one again on a resumed run);
    ValueError where the folder holds another prior or a prior stage of its own."""
    from bumps_jax import runio  # noqa: PLC0415
    from bumps_jax.tasks.kick import prior as prior_stage  # noqa: PLC0415

    record = asset(runio.read_json(args.prior, "a kick prior stage's record"), args.prior, cfg.prior)
    runio.check_writable(args.run_dir, "--run-dir")
    prior_dir = args.run_dir / f"seed{args.seed}" / "prior"
    if (prior_dir / prior_stage.OUTPUT).exists():
        raise ValueError(f"--run-dir {args.run_dir}: seed {args.seed} has a prior stage of its own ({prior_dir})")
    path = prior_dir / prior_stage.ASSET
    if path.exists() and runio.read_json(path, "a kick prior asset") != runio.json_safe(record):
        raise ValueError(f"{path} holds another prior than --prior {args.prior}: use a new --run-dir")
    runio.write_json(path, runio.json_safe(record))
    return path


def main(argv=None) -> None:
    args = parse_args(argv)
    start = time.perf_counter()
    from bumps_jax import cli, config, records, runio  # noqa: PLC0415
    from bumps_jax.tasks.kick import env as kick_env  # noqa: PLC0415

    try:
        runio.check_writable(args.out.parent, "the record's folder", create=False)
        against = run_row(args.against, tuned=False)
        cfg = config.make_config(args.preset, {"task": "kick"})
        records.check_same_env(
            runio.read_json(args.against).get("env"), cfg.env, f"--against {args.against}", kick_env.resolved
        )
        asset_path = place(args, cfg)
    except ValueError as err:
        raise SystemExit(f"error: {err}") from None
    print(f"experts of seed {args.seed} from the prior in {args.prior} (as {asset_path})")
    command = ["reproduce" if args.preset == "paper" else "demo", "--task", "kick", "--preset", args.preset,
               "--stages", "experts", "--seeds", str(args.seed), "--run-dir", str(args.run_dir)]  # fmt: skip
    cli.main(command + ([] if args.processes is None else ["--processes", str(args.processes)]))
    made = args.run_dir / f"seed{args.seed}" / "experts" / "experts.json"
    this = run_row(made, tuned=False)
    rows = {"this_run": this, "against": against}
    record = {
        "task": "kick",
        "prior": str(args.prior),
        "runs": rows,
        "tuning_mean_difference": None
        if None in (this["tuning_mean"], against["tuning_mean"])
        else this["tuning_mean"] - against["tuning_mean"],
        "experts_error_difference_m": this["experts_error_m"] - against["experts_error_m"],
        **summary_provenance(
            runio.read_json(made, "this run's experts record"), [r["device"] for r in rows.values()], start
        ),
    }
    runio.write_json(args.out, runio.json_safe(record))
    for name, r in rows.items():
        tuning = "not run" if r["tuning_mean"] is None else f"{r['tuning_mean']:.3f}"
        print(f"{name}: {r['processes']} process(es) on {r['device']}: tuning {tuning}, "
              f"experts {r['experts_error_m']:.3f} m")  # fmt: skip
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
