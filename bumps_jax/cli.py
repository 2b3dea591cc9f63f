"""Every command of the pipeline from one command line.

    python -m bumps_jax <command> [--preset tiny|paper] [--task kick|cheetah_vel|ant_goal|point_goal] [--run-dir D]
                                  [--set KEY=VALUE ...] [--force]

`--task` picks the contextual task (the config's `task`: the kick by default), whose tree the
`--set` keys name; another task's runs go to runs/<task>/<preset> unless --run-dir says otherwise.

`--set` takes dotted keys of the one config tree (`bumps_jax.config`): `env.physics_dt=0.005`,
`experts.ppo.learning_rate=1e-5`; a stage's own keys may drop their section
(`train-experts --set ppo.learning_rate=1e-5`). Values are JSON (numbers, lists, true/false,
null), else plain strings; each is checked against the type of its leaf. The only module that
parses arguments (the GL backend of the rendering commands is chosen in `bumps_jax/__init__`,
before mujoco is imported).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import sys
import traceback
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent  # bumps_jax/: where its own errors are raised

# command -> (stage or pipeline, the presets it knows, help)
STAGE_COMMANDS = {
    "kick-prior": ("prior", "optimise the keyframe kick prior (CMA-ES), evaluate and sweep it"),
    "train-experts": ("experts", "train one PPO expert per task, all in one vmapped program"),
    "meta-train": ("meta", "behaviour-clone the experts into the two contextual meta-policies"),
    "filter": ("filter", "policy filtering: pick each test task's best context; Table 2"),
    "baseline": ("baseline", "the multi-task PPO baseline (the paper's Figure 1)"),
}
PIPELINES = {
    "demo": (
        ("experts", "meta", "filter"),
        "tiny",
        "the experts, meta and filter stages at CPU size, with a report (the kick starts from the prior in assets/)",
    ),
    "reproduce": (
        ("prior", "experts", "meta", "filter", "heldout", "baseline"),
        "paper",
        "every stage at the paper's size (a GPU), resumable, with a report",
    ),
}
OTHER = {
    "report": "write report.md of a run: our tables beside the paper's, figures, timings",
    "publish": "copy a finished paper run's results, figures and prior into the repository",
    "evaluate": "evaluate a finished run (experts, meta and filter done) on the held-out (--heldout) or "
    "development (--dev) targets",
    "config": "print every config key (--set KEY=VALUE) with its value under --preset, --task and --set",
}

# The commands besides the stages that read a finished run and write into its directory: under
# its lock, as the stages are, and refused at once where the directory does not exist. (A task's
# own commands say so themselves: `protocol.Command.needs_run`.)
NEEDS_RUN = ("evaluate", "publish", "report")
NO_DEVICE_WORK = ("config", "report", "publish")  # commands that only read and write files


def task_commands() -> dict:
    """The tasks' own commands: name -> `protocol.Command` (`tasks.registry.commands`)."""
    from bumps_jax.tasks import registry as tasks  # noqa: PLC0415

    return {name: spec for name, (_, spec) in tasks.commands().items()}


def parse_overrides(groups, section: str | None = None, task: str | None = None) -> dict:
    """[['a.b=1', 'c=[1, 2]'], ['d=x']] -> {'a.b': 1, 'c': (1, 2), 'd': 'x'}. With a stage's
    `section`, a key that names no top-level section of `task`'s tree is read inside that section."""
    from bumps_jax import config  # noqa: PLC0415
    from bumps_jax.tasks import registry as tasks  # noqa: PLC0415

    tops = set(config.default_config(task or tasks.DEFAULT).keys())
    out = {}
    for item in [i for group in groups for i in group]:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--set expects KEY=VALUE, got {item!r}")
        if key in ("task", "preset"):  # they choose the tree; set, they would relabel another one
            raise ValueError(f"--set {item}: {key} is not a config value to set; use --{key} {value}")
        try:
            parsed = json.loads(value)
        except json.JSONDecodeError:
            parsed = value
        if section and key.split(".")[0] not in tops:
            key = f"{section}.{key}"
        out[key] = tuple(parsed) if isinstance(parsed, list) else parsed
    return out


def flat_keys(tree: dict, prefix: str = "") -> dict:
    """{dotted key: value} of every leaf of a nested dict."""
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(flat_keys(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def config_keys_text(sections, task: str | None = None) -> str:
    """The keys of `task`'s config `sections` with the tiny preset's values (and the paper's where
    they differ): what --set takes, for a command's --help and the `config` command."""
    from bumps_jax import config  # noqa: PLC0415
    from bumps_jax.tasks import registry as tasks  # noqa: PLC0415

    overrides = {"task": task or tasks.DEFAULT}
    tiny, paper = (flat_keys(config.make_config(p, overrides).to_dict()) for p in ("tiny", "paper"))
    lines = ["config keys (--set KEY=VALUE), with the tiny preset's value (and the paper preset's where it differs):"]
    for key, value in tiny.items():
        if key.split(".")[0] in sections:
            other = paper.get(key, value)
            lines.append(
                f"  {key} = {json.dumps(value)}" + ("" if other == value else f"   (paper: {json.dumps(other)})")
            )
    return "\n".join(lines)


def build_parser(with_keys: bool = False) -> argparse.ArgumentParser:
    """The command line's parser; `with_keys`: each stage's --help lists its config keys (it builds
    the config: only when help is asked for)."""
    parser = argparse.ArgumentParser(prog="python -m bumps_jax", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    own = task_commands()
    helps = {**{k: v[1] for k, v in STAGE_COMMANDS.items()}, **{k: v[2] for k, v in PIPELINES.items()}, **OTHER}
    helps.update({name: spec.help for name, spec in own.items()})
    for name, help_text in helps.items():
        spec = own.get(name)
        own_only = spec is not None and spec.own_options_only
        epilog = None
        if with_keys and name in STAGE_COMMANDS:
            epilog = config_keys_text((STAGE_COMMANDS[name][0],)) + "\n  env.*: python -m bumps_jax config"
        elif with_keys and not own_only:
            epilog = "config keys (--set KEY=VALUE) with their values: python -m bumps_jax config"
        p = sub.add_parser(
            name,
            help=help_text,
            description=help_text,
            epilog=epilog,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        if own_only:  # a command under its own config (the kick's shipped policies): no preset, run directory or --set
            p.set_defaults(preset="tiny", run_dir=None, task=None, set=[], force=False, distributed=False, processes=1)
        else:
            add_run_options(p, name)
        if spec is not None and spec.add_arguments is not None:
            spec.add_arguments(p)
    return parser


def add_run_options(p, name: str) -> None:
    """The options of a command that runs the pipeline's config in a run directory."""
    presets = (PIPELINES[name][1],) if name in PIPELINES else ("tiny", "paper")
    p.add_argument("--preset", default=presets[0], help=f"one of {presets} (default {presets[0]})")
    p.add_argument(
        "--run-dir",
        default=None,
        type=Path,
        help="default: runs/<preset> (runs/demo for demo); another task's: runs/<task>/<preset>",
    )
    p.add_argument("--task", default=None, help="the contextual task (config: task): kick (default), cheetah_vel, ...")
    p.add_argument("--set", action="append", nargs="+", default=[], metavar="KEY=VALUE",
                   help="config overrides (JSON values); may be repeated")  # fmt: skip
    p.add_argument("--force", action="store_true",
                   help="recompute a stage whose outputs were made under another config or inputs, or "
                        "before its task's code changed, and every stage after it")  # fmt: skip
    p.add_argument("--processes", type=int, default=1, metavar="N",
                   help="run as N processes on this host, one GPU each (JAX's multi-process runtime): every "
                        "batched program split over them")  # fmt: skip
    p.add_argument("--distributed", action="store_true",
                   help="this process is one of a multi-process job (started by srun, or by --processes)")  # fmt: skip
    if name in PIPELINES:
        every = ", ".join(PIPELINES[name][0])
        p.add_argument("--stages", nargs="+", default=None, metavar="STAGE",
                       help=f"only these of its stages, in its order (default: all of {every}); the run "
                            "directory's timings and report count them as one more call")  # fmt: skip
        p.add_argument("--seeds", nargs="+", type=int, default=None, metavar="SEED",
                       help="the pipeline once per training seed (every stage's training randomness), into "
                            "<run-dir>/seed<SEED>, the baseline (seeded itself) in the first only; then "
                            "<run-dir>/seeds.json: every headline's mean and spread over them")  # fmt: skip
    if name == "publish":
        p.add_argument("--seed-runs", nargs="+", type=Path, default=[], metavar="RUN_DIR",
                       help="finished runs of the same config with other training seeds (experts, meta, filter): "
                            "every headline published as mean and spread over them and --run-dir")  # fmt: skip
        p.add_argument("--baseline-at-budget", action="store_true",
                       help="the run's baseline only, trained at BUMPS' experts' whole budget (its env steps per "
                            "seed within one update of the committed experts'): published beside the preset's own "
                            "baseline as results/[<task>/]baseline_at_budget.json")  # fmt: skip
        p.add_argument("--records-only", action="store_true",
                       help="the run's records, tables and figures only; assets/ (the kick prior later runs "
                            "start from, the shipped policies) kept as they are")  # fmt: skip
    if name == "evaluate":
        p.add_argument("--heldout", action="store_true", help="the held-out targets and seed (config: heldout)")
        p.add_argument("--dev", action="store_true",
                       help="the development targets and seed (config: dev), for design choices")  # fmt: skip


def default_run_dir(command: str, preset: str, task: str | None = None) -> Path:
    """runs/<preset> (runs/demo for demo) for the default task, runs/<task>/<preset> for another."""
    from bumps_jax.tasks import registry as tasks  # noqa: PLC0415

    name = "demo" if command == "demo" else preset
    return Path("runs") / tasks.folder(task or tasks.DEFAULT) / name


def missing_run(run_dir, args) -> str:
    """The message for a command that reads a run where `run_dir` does not exist: the demo's run
    named where --run-dir was left at its default and the demo's folder holds one."""
    message = f"no run directory {str(run_dir)!r}: run its stages first"
    demo = default_run_dir("demo", args.preset, args.task)
    if args.run_dir is None and demo.is_dir():
        return f"{message}, or add --run-dir {demo} (the demo's run)"
    from bumps_jax.tasks import registry as tasks  # noqa: PLC0415

    task = f" --task {args.task}" if args.task not in (None, tasks.DEFAULT) else ""
    return f"{message} (e.g. python -m bumps_jax demo{task}, then --run-dir {demo})"


def pipeline_stages(command: str, chosen) -> tuple[str, ...]:
    """The stages a pipeline command runs: all of them, or those `chosen` (--stages) in its order;
    ValueError naming a stage it does not have."""
    stages = PIPELINES[command][0]
    if chosen is None:
        return stages
    unknown = [s for s in chosen if s not in stages]
    if unknown:
        raise ValueError(f"--stages: {command} has no stage {unknown[0]!r}; choose from {', '.join(stages)}")
    return tuple(s for s in stages if s in chosen)


def command_config(args, section: str | None = None):
    """The pipeline config a parsed command asks for: its preset, --task and --set (keys read
    inside the stage's `section` where they name no top-level one)."""
    from bumps_jax import config  # noqa: PLC0415

    if args.task is not None:
        from bumps_jax.tasks import registry as tasks  # noqa: PLC0415

        tasks.check_task(args.task)
    overrides = parse_overrides(args.set, section, args.task)
    if args.task is not None:
        overrides = {"task": args.task, **overrides}
    return config.make_config(args.preset, overrides)


def has_command(task: str, command: str) -> bool:
    """Whether `task` runs `command`: a stage command of a stage it has, a pipeline, a command of
    every task's, or one of its own."""
    from bumps_jax.tasks import registry as tasks  # noqa: PLC0415

    if command in STAGE_COMMANDS:
        return STAGE_COMMANDS[command][0] in tasks.get(task).stages
    return command in PIPELINES or command in NEEDS_RUN or command in tasks.own_commands(task)


def check_run(run_dir: Path, cfg, command: str | None = None) -> None:
    """ValueError unless the run's records (where it has some) name `cfg`'s task, and were made
    under its env config or name its preset: a command given another task's run directory, or a
    run of another preset without `--preset`, is refused before it reads the run (the report
    reads any preset's)."""
    from bumps_jax import config, records  # noqa: PLC0415
    from bumps_jax.report import task_report  # noqa: PLC0415
    from bumps_jax.tasks import registry as tasks  # noqa: PLC0415

    try:
        record = task_report.first_record(run_dir) if run_dir.is_dir() else None
    except ValueError:  # an unreadable record: the stage that reads it names it
        return
    if record is None:
        return
    found = record.get("task", tasks.DEFAULT)
    try:
        tasks.check_record_task(found, cfg.task, str(run_dir))
    except ValueError as err:
        if command is not None and not has_command(found, command):
            raise ValueError(f"{err}, and {found} has no {command} command: give another --run-dir") from None
        raise ValueError(f"{err}: add --task {found}, or give another --run-dir") from None
    preset = record.get("preset")
    if command == "report" or preset in (None, cfg.preset) or record.get("env") is None:
        return
    try:
        records.check_same_env(record["env"], config.resolved_env(cfg), f"{run_dir}'s records")
    except ValueError:
        raise ValueError(
            f"{run_dir} holds a run of preset {preset!r} (its records say so), whose env this command's preset "
            f"{cfg.preset!r} does not share: add --preset {preset}"
        ) from None


def checked_config(args, run_dir=None):
    """The command's config once its preset, its --set values and (where it writes a run) its run
    directory are checked: ValueError naming the first mistake, before any work or process starts."""
    known = (PIPELINES[args.command][1],) if args.command in PIPELINES else ("tiny", "paper")
    if args.preset not in known:
        raise ValueError(f"--preset {args.preset!r}: {args.command} takes {' or '.join(map(repr, known))}")
    cfg = command_config(args, STAGE_COMMANDS.get(args.command, (None,))[0])
    if args.command == "report" and any(args.set):
        raise ValueError("--set: report reads a run's records as they are; it takes no config values")
    # The report reads the task from the run: only a --task given for it is checked against it.
    if run_dir is not None and (args.command not in ("config", "report") or args.task is not None):
        check_run(Path(run_dir), cfg, args.command)
    return cfg


def dispatch(args) -> None:
    """Run one parsed command; ValueError for every user mistake."""
    from bumps_jax import runio  # noqa: PLC0415
    from bumps_jax.pipeline import runner as pipeline  # noqa: PLC0415

    section = STAGE_COMMANDS.get(args.command, (None,))[0]
    run_dir = args.run_dir or default_run_dir(args.command, args.preset, args.task)
    cfg = checked_config(args, run_dir)
    if args.command == "config":
        for key, value in flat_keys(cfg.to_dict()).items():
            print(f"{key} = {json.dumps(value)}")
        return
    # One command at a time writes stages into a run directory; with --distributed every host runs
    # the same command into the same directory, by design.
    lock = contextlib.nullcontext() if args.distributed else runio.run_lock(run_dir)
    spec = task_commands().get(args.command)
    needs_run = args.command in NEEDS_RUN or (spec is not None and spec.needs_run)
    if needs_run:
        if not Path(run_dir).is_dir():  # refused before the lock would create it
            raise ValueError(missing_run(run_dir, args))
    if section:
        if not Path(run_dir).is_dir():  # a stage's missing inputs refused before the lock creates the directory
            pipeline.plan(section, cfg, Path(run_dir))
        with lock:
            pipeline.run_stage(section, cfg, run_dir, force=args.force)
    elif args.command in PIPELINES:
        stages = pipeline_stages(args.command, args.stages)
        if args.stages is not None:  # a named stage the task lacks is a mistake, not one to skip
            from bumps_jax.tasks import registry as tasks  # noqa: PLC0415

            for name in stages:
                tasks.check_stage(cfg.task, name)
        if args.seeds is None:
            with lock:
                pipeline.run_pipeline(stages, cfg, run_dir, force=args.force)
        elif args.distributed:  # the launcher that started this process holds the run directory
            run_seeds(args.seeds, stages, cfg, Path(run_dir), args.force, lock=lambda _: contextlib.nullcontext())
        else:  # commands of other seeds may write into the same run directory, each its own seeds'
            with runio.run_lock(run_dir, shared=True):
                run_seeds(args.seeds, stages, cfg, Path(run_dir), args.force)
    else:
        from bumps_jax.pipeline import commands  # noqa: PLC0415

        writes = needs_run if spec is None or spec.writes_run is None else spec.writes_run(args)
        with lock if writes else contextlib.nullcontext():
            commands.run(args.command, cfg, run_dir, args)


def run_seeds(seeds, stages, cfg, run_dir: Path, force: bool = False, lock=None) -> None:
    """The pipeline once per training seed into run_dir/seed<S> (the baseline, seeded itself, in
    the first only), each holding `lock(seed_dir)` (default: `runio.run_lock`, so that commands
    of other seeds run side by side in one run directory), then run_dir/seeds.json over the runs
    that finished experts, meta and filter."""
    from bumps_jax import config, runio  # noqa: PLC0415
    from bumps_jax.pipeline import runner as pipeline  # noqa: PLC0415
    from bumps_jax.report import seeds as seeds_report  # noqa: PLC0415

    repeated = sorted({s for s in seeds if seeds.count(s) > 1})
    if repeated:
        raise ValueError(f"--seeds: {repeated[0]} given twice")
    configs = [config.seeded(cfg, s) for s in seeds]  # every seed's config checked before any work
    for seed, seeded in zip(seeds, configs, strict=True):  # every seed's folder: a run of this config, if any
        check_run(run_dir / f"seed{seed}", seeded)
    runs = []
    for i, (seed, seeded) in enumerate(zip(seeds, configs, strict=True)):
        seed_dir = run_dir / f"seed{seed}"
        print(f"== training seed {seed} ({i + 1} of {len(seeds)}): {seed_dir}", flush=True)
        with (lock or runio.run_lock)(seed_dir):
            pipeline.run_pipeline(tuple(s for s in stages if i == 0 or s != "baseline"), seeded, seed_dir, force=force)
        runs.append(seed_dir)
    done = [d for d in runs if not pipeline.unfinished(d, ("experts", "meta", "filter"), cfg.task)]
    if len(done) > 1:
        record = seeds_report.seeds_record(done, runio.command_line())
        runio.write_json(run_dir / "seeds.json", record)
        for name, r in record["rows"].items():
            print(f"{name}: {r['mean']:.3f} +- {r['std']:.3f} over {record['n_seeds']} seeds ({r['per_seed']})")
        print(f"wrote {run_dir / 'seeds.json'}")


def choose_gl(argv) -> None:
    """Pick MuJoCo's offscreen GL backend for a rendering command, before mujoco is imported (it
    loads the backend MUJOCO_GL names once, at import): EGL, else OSMesa where only its library is
    present; neither found: left unset, and the command says so in one line before its work.
    Never where the user set MUJOCO_GL, nor for a command that does not render (with MUJOCO_GL
    set, importing mujoco loads that library, and a host without one could not even simulate)."""
    spec = task_commands().get(argv[0]) if argv else None
    if "MUJOCO_GL" in os.environ or spec is None or not spec.renders(argv[1:]):
        return
    import ctypes.util  # noqa: PLC0415

    for backend, library in (("egl", "EGL"), ("osmesa", "OSMesa")):
        if ctypes.util.find_library(library):
            os.environ["MUJOCO_GL"] = backend
            return


def load_mujoco() -> None:
    """Import MuJoCo MJX once, first and quietly (it prints "Failed to import warp" to stdout on a
    machine without the optional Warp backend); ValueError in one line where the GL library that
    MUJOCO_GL names is missing."""
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            import mujoco.mjx  # noqa: F401, PLC0415
    except (AttributeError, ImportError, OSError) as err:
        if "MUJOCO_GL" not in os.environ:
            raise
        reason = f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
        raise ValueError(
            f"mujoco cannot load the GL backend MUJOCO_GL={os.environ['MUJOCO_GL']} names ({reason}): unset "
            "MUJOCO_GL, or name one this host has (egl, osmesa)"
        ) from None


def main(argv=None) -> None:
    argv = sys.argv[1:] if argv is None else list(argv)
    choose_gl(argv)  # before anything imports mujoco
    try:
        load_mujoco()
    except ValueError as err:
        sys.exit(f"error: {err}")
    args = build_parser(with_keys=any(a in ("-h", "--help") for a in argv)).parse_args(argv)
    from bumps_jax import resumable, runio  # noqa: PLC0415
    from bumps_jax.tasks import registry  # noqa: PLC0415

    try:
        registry.check_task(args.task or registry.DEFAULT)
    except ValueError as err:
        sys.exit(f"error: --task: {err}")
    run_dir = args.run_dir or default_run_dir(args.command, args.preset, args.task)
    if args.distributed and args.processes != 1:
        sys.exit(f"error: --processes {args.processes} starts its own processes; --distributed is for one that a "
                 "launcher (srun) started: give one of the two")  # fmt: skip
    try:
        if args.processes != 1 and args.command in NO_DEVICE_WORK:
            raise ValueError(f"--processes {args.processes}: {args.command} computes nothing on a device; leave it out")
        if args.processes != 1 and not args.distributed:
            from bumps_jax import launch  # noqa: PLC0415

            n = launch.check_count(args.processes)
            checked_config(args, run_dir)  # the processes' first checks, made once here
            with runio.run_lock(run_dir):
                try:
                    code = launched(args, argv, n, run_dir)
                except KeyboardInterrupt:  # its processes stopped, and the first said so here
                    code = 130
            sys.exit(code)
        if args.distributed:
            from bumps_jax.algo import sharding  # noqa: PLC0415

            sharding.initialize_distributed()
        dispatch(args)
    except ValueError as err:
        if not raised_here(err):  # a library's error deep inside a stage: its traceback says where
            raise_or_leave(args)
        leave(args, f"error: {err}")  # bad config values, missing or stale inputs: one clear line
    except (KeyboardInterrupt, resumable.Interrupted) as err:
        if isinstance(err, resumable.Interrupted) and str(err):  # it says where it stopped
            leave(args, f"interrupted: {err}")
        elif args.command in (*STAGE_COMMANDS, *PIPELINES):  # the checkpoints are the state
            leave(args, f"interrupted: rerun the same command to resume {run_dir} from what it saved (the stage in "
                  "flight's last chunk or search generation; the stages before it are done)")  # fmt: skip
        else:  # no stage ran: no checkpoint to resume from
            leave(args, f"interrupted: {args.command} stopped before it finished (run it again to do it whole)")
    except Exception:
        raise_or_leave(args)


def raised_here(err: BaseException) -> bool:
    """Whether `err` was raised by this package's own code (a message for the user: a bad value,
    a missing input), not by a library it called (JAX's, NumPy's: a fault whose traceback matters)."""
    tb = err.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return tb is not None and Path(tb.tb_frame.f_code.co_filename).resolve().is_relative_to(PACKAGE)


def raise_or_leave(args) -> None:
    """The exception being handled, with its traceback: raised again in a single process; in a
    process of a multi-process job printed, then `leave`."""
    if not args.distributed:
        raise
    traceback.print_exc()
    leave(args, "error: the traceback above")


def launched(args, argv, n: int, run_dir) -> int:
    """`--processes n`: the command as n processes (`launch.run`). A pipeline runs in the phases
    of `runner.schedule` (the baseline beside the experts and meta-policies), its pipeline.json given the
    launch's wall time from start to end (`runner.record_launch`); with several `--seeds`, the
    seeds' pipelines run side by side (`seed_phases`). The exit code."""
    import time  # noqa: PLC0415

    from bumps_jax import launch  # noqa: PLC0415

    if args.command not in PIPELINES:
        return launch.run(argv, n, run_dir)
    from bumps_jax.pipeline import runner  # noqa: PLC0415
    from bumps_jax.tasks import registry as tasks  # noqa: PLC0415

    cfg = command_config(args)
    stages = [s for s in pipeline_stages(args.command, args.stages) if s in tasks.get(cfg.task).stages]
    if args.seeds is not None:
        return launch.run(argv, n, run_dir, seed_phases(args.seeds, stages, n))
    schedule = runner.schedule(stages, n)
    phases = [[({"--stages": branch}, k) for branch, k in phase] for phase in schedule]
    start = time.perf_counter()
    code = 1
    try:
        code = launch.run(argv, n, run_dir, phases)
    finally:  # also when interrupted: a resumed run adds up its calls
        runner.record_launch(run_dir, n, schedule, time.perf_counter() - start, code == 0)
    return code


def seed_phases(seeds, stages, n: int) -> list:
    """`--seeds` over n processes: min(n, seeds) jobs side by side, job j the seeds j, j + jobs, ...
    one after another on its share of the processes (the baseline with the first seed only, as
    `run_seeds` trains it); then one process writes seeds.json over them all (every stage is
    done by then, so it only reads)."""
    jobs = min(n, len(seeds))
    branches = []
    for j in range(jobs):
        own = [s for s in stages if j == 0 or s != "baseline"]
        branches.append(({"--seeds": list(seeds[j::jobs]), "--stages": own}, n // jobs + (j < n % jobs)))
    return [branches, [({"--seeds": list(seeds), "--stages": list(stages)}, 1)]]


def leave(args, message: str) -> None:
    """End the command with `message` on stderr and exit status 1. A process of a multi-process
    job leaves at once: JAX's orderly shutdown would wait minutes for the others to get there
    (the launcher stops them, `launch.run`)."""
    if not args.distributed:
        sys.exit(message)
    print(message, file=sys.stderr, flush=True)
    sys.stdout.flush()
    os._exit(1)


if __name__ == "__main__":
    main()
