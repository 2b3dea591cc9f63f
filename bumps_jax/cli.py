"""Every stage of the BUMPS pipeline from one command line.

    python -m bumps_jax <stage> --preset tiny|paper --run-dir D --set key=value ...

The only module that parses arguments or touches the environment.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path


def parse_overrides(items: list[str]) -> dict:
    """['a.b=1', 'c=[1, 2]'] -> {'a.b': 1, 'c': [1, 2]}; values are JSON, else plain strings."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise SystemExit(f"--set expects key=value, got {item!r}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return {k: tuple(v) if isinstance(v, list) else v for k, v in out.items()}


# -- the stages: each reads and writes under the run directory -------------------------------


def _kick_prior(run_dir: Path, preset: str, overrides: dict, publish: bool = False) -> None:
    from bumps_jax import prior

    payload = prior.run_stage(preset, run_dir / "prior", overrides, publish=publish)
    print(json.dumps({k: payload[k] for k in ("mean_error_m", "valid_fraction", "wall_s")}, indent=2))


def _train_experts(run_dir: Path, preset: str, overrides: dict) -> None:
    from bumps_jax import experts, prior

    # A run that made its own kick prior starts from that record, not from the committed asset,
    # which a kick-prior run elsewhere may have rewritten since; a prior_path override wins.
    own = run_dir / "prior" / prior.RUN_PRIOR_JSON
    if own.is_file() and "prior_path" not in overrides:
        overrides = {**overrides, "prior_path": str(own)}
    cfg = experts.make_config(experts.preset_config(preset), overrides)
    programs = experts.compile_programs(cfg)
    out = experts.train_experts(cfg, run_dir / "experts", programs=programs)
    experts.evaluate_run(cfg, run_dir / "experts", out["state"], programs, out["wall_s"])
    print((run_dir / "experts" / "experts.md").read_text())


def _meta_train(run_dir: Path, preset: str, overrides: dict, synthetic_experts: bool = False) -> None:
    from bumps_jax import experts, meta

    cfg = meta.make_config(preset, overrides)
    experts_dir = run_dir / "experts"
    if synthetic_experts:
        family, experts_json = meta.load_experts("synthetic", None), None
    elif (experts_dir / "final_params").exists():
        family, experts_json = experts.family(experts_dir), experts_dir / "experts.json"
    else:
        raise ValueError(f"no trained experts in {experts_dir}: run train-experts first, or pass --synthetic-experts")
    payload = meta.run(cfg, run_dir / "meta", family, experts_json)
    print(meta.table1_markdown(payload["rows"]))


def _filter(run_dir: Path, preset: str, overrides: dict) -> None:
    from bumps_jax import filtering

    payload = filtering.run(filtering.make_config(preset, overrides), run_dir / "meta", run_dir / "filter")
    print(filtering.table2_markdown(payload["rows"]))


def _report(run_dir: Path, preset: str, overrides: dict) -> None:
    from bumps_jax import report

    path = report.write(run_dir)
    print(path.read_text())
    print(f"wrote {path}")


# Each stage's output file, for `reproduce` to skip what is done and up to date.
OUTPUTS = {
    "kick-prior": "prior/kick_prior.json",
    "train-experts": "experts/experts.json",
    "meta-train": "meta/table1.json",
    "filter": "filter/table2.json",
}


# `--set` keys of the whole pipeline name their stage first: experts.ppo.total_env_steps=...
PREFIXES = {"prior": "kick-prior", "experts": "train-experts", "meta": "meta-train", "filter": "filter"}


def split_overrides(overrides: dict, stages: tuple[str, ...]) -> dict:
    """{'experts.ppo.lr': x} -> {'train-experts': {'ppo.lr': x}}; SystemExit naming a bad key."""
    out = {stage: {} for stage in stages}
    for key, value in overrides.items():
        prefix, _, rest = key.partition(".")
        stage = PREFIXES.get(prefix)
        if stage not in out or not rest:
            names = ", ".join(f"{p}." for p, s in PREFIXES.items() if s in stages)
            raise SystemExit(f"--set {key!r}: pipeline overrides start with a stage ({names})")
        out[stage][rest] = value
    return out


def _pipeline(run_dir: Path, preset: str, stages: tuple[str, ...], overrides: dict | None = None) -> None:
    """Run `stages` in order, skipping one whose output exists and is newer than its input's.

    Writes run_dir/pipeline.json: each stage's wall time in this call and the total.
    """
    import time

    from bumps_jax import results

    per_stage = split_overrides(overrides or {}, stages)
    timing_path = run_dir / "pipeline.json"
    timing = json.loads(timing_path.read_text()) if timing_path.exists() else {"stages": {}}
    _count_killed_call(run_dir, timing)
    previous, counted = None, False
    for stage in stages:
        out = run_dir / OUTPUTS[stage]
        fresh = out.exists() and (previous is None or out.stat().st_mtime >= previous.stat().st_mtime)
        if fresh:
            print(f"== {stage}: up to date ({out})")
        else:
            print(f"== {stage}", flush=True)
            if not counted:  # this invocation's share: a report says whether the run was resumed
                timing["calls"], counted = timing.get("calls", 0) + 1, True
            t0 = time.perf_counter()
            extra = {"publish": True} if stage == "kick-prior" else {}
            # A SIGKILL skips the `finally` below; this mark lets the next call count the lost time.
            timing["open"] = {"stage": stage, "started": time.time()}
            results.write_json(timing_path, timing)
            try:
                STAGES[stage][0](run_dir, preset, per_stage[stage], **extra)
            finally:  # also when interrupted (Ctrl-C, `timeout -s INT`): a resumed stage adds up its parts
                timing.pop("open", None)
                timing["stages"][stage] = timing["stages"].get(stage, 0.0) + time.perf_counter() - t0
                total = sum(timing["stages"].values())
                timing.update(results.provenance(preset, total))
                timing.update({"overrides": {k: str(v) for k, v in (overrides or {}).items()}, "total_wall_s": total})
                results.write_json(timing_path, timing)
        previous = out
    _report(run_dir, preset, {})


def _count_killed_call(run_dir: Path, timing: dict) -> None:
    """Add a call that was killed mid-stage (its `open` mark is left) to `timing`, in place.

    Its time is counted up to the stage's last write under run_dir (a checkpoint, a progress
    row): what came after it was lost and is redone by this call, so it is not known."""
    opened = timing.pop("open", None)
    if not opened:
        return
    stage_dir = (run_dir / OUTPUTS[opened["stage"]]).parent
    writes = [p.stat().st_mtime for p in stage_dir.rglob("*") if p.is_file()] if stage_dir.exists() else []
    lost = max([0.0, *(t - opened["started"] for t in writes)])
    timing["stages"][opened["stage"]] = timing["stages"].get(opened["stage"], 0.0) + lost
    timing["killed_calls"] = timing.get("killed_calls", 0) + 1
    print(f"== a previous call was killed during {opened['stage']}: counting its {lost:.0f} s up to its last write")


def _demo(run_dir: Path, preset: str, overrides: dict) -> None:
    """The pipeline at CPU size; the kick prior is the committed one (assets/)."""
    _pipeline(run_dir, "tiny", ("train-experts", "meta-train", "filter"), overrides)


def _reproduce(run_dir: Path, preset: str, overrides: dict) -> None:
    """The paper preset end to end (a GPU job); a rerun resumes or skips finished stages."""
    _pipeline(run_dir, "paper", ("kick-prior", "train-experts", "meta-train", "filter"), overrides)


def _publish(run_dir: Path, preset: str, overrides: dict) -> None:
    from bumps_jax import report

    for path in report.publish(run_dir):
        print(f"wrote {path}")


def _render(run_dir: Path, preset: str, overrides: dict, out: str = "docs/stance.png") -> None:
    from bumps_jax import render

    print(render.stance_picture(out))


def _video(run_dir: Path, preset: str, overrides: dict, out: str | None = None) -> None:
    """A GIF of filtered kicks of a finished run: the (4, 256) net at three test tasks."""
    import jax
    import ml_collections
    import numpy as np

    from bumps_jax import kick_env, meta, render

    table2 = run_dir / "filter" / "table2.json"
    if not table2.exists():
        raise ValueError(f"no {table2}: run the filter stage first")
    payload = json.loads(table2.read_text())
    tasks, chosen = np.asarray(payload["tasks"]), np.asarray(payload["chosen_contexts"]["filtered_4x256"])
    picks = [int(np.argmin(np.abs(tasks - t))) for t in (8.0, 12.0, 16.0)]
    picks = sorted(set(picks))
    meta_cfg = ml_collections.ConfigDict(json.loads((run_dir / "meta" / "config.json").read_text()))
    depth, width = meta_cfg.nets["meta_4x256"]
    apply_fn, params = meta.load_policy(run_dir / "meta" / "meta_4x256", depth, width, meta_cfg.train)
    params = jax.tree.map(lambda a: a[0], params)
    path = render.kick_gif(
        out or run_dir / "filtered_kicks.gif", kick_env.KickEnv(), apply_fn, params, chosen[picks], tasks[picks]
    )
    print(f"wrote {path}")


def _showcase(run_dir: Path, preset: str, overrides: dict, episodes: int = 16) -> None:
    """A batch of noisy episodes of the committed prior: the scene and env at a glance."""
    import jax
    import numpy as np

    from bumps_jax import kick_env, prior

    env = kick_env.KickEnv()
    rollout = prior.make_rollout(env)
    keys = jax.random.split(jax.random.key(0), episodes)[None]
    out = rollout(prior.clip_params(prior.load_prior()["params"])[None], keys, 12.0)
    print(f"{episodes} noisy kicks of the committed 12 m prior:")
    print(f"  resting distance {np.mean(out['distance']):.2f} +- {np.std(out['distance']):.2f} m")
    print(f"  final error      {np.mean(out['final_error']):.2f} m, valid {np.mean(out['valid']):.2f}")


STAGES = {
    "kick-prior": (_kick_prior, "optimise the keyframe kick prior (CMA-ES), evaluate and sweep it"),
    "train-experts": (_train_experts, "train one PPO expert per task, all in one vmapped program"),
    "meta-train": (_meta_train, "behaviour-clone the experts into the two contextual meta-policies"),
    "filter": (_filter, "policy filtering: pick each test task's best context; Table 2"),
    "report": (_report, "write report.md: our tables beside the paper's, figures, timings"),
    "demo": (_demo, "the whole pipeline at CPU size (tiny preset), ending with a report"),
    "reproduce": (_reproduce, "the whole pipeline at the paper's size (a GPU), resumable"),
    "publish": (_publish, "copy a finished run's results, figures and prior into the repo; rebuild docs/results.md"),
    "render": (_render, "render the robot in its stance to a PNG"),
    "video": (_video, "render a GIF of filtered kicks at three distances from a finished run"),
    "showcase": (_showcase, "replay the committed prior over a batch of noisy episodes"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m bumps_jax", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="stage", required=True)
    for name, (_, help_text) in STAGES.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.add_argument("--preset", default="tiny", choices=("tiny", "paper"))
        p.add_argument("--run-dir", default=None, type=Path, help="default: runs/<preset> (runs/demo for demo)")
        p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides, JSON values")
        p.add_argument(
            "--distributed", action="store_true", help="one process per host of a multi-host job (jax.distributed)"
        )
        if name == "kick-prior":
            p.add_argument("--publish", action="store_true", help="also write the committed copies (assets, results)")
        if name == "meta-train":
            p.add_argument("--synthetic-experts", action="store_true", help="clone the prior-based stand-in experts")
        if name == "render":
            p.add_argument("--out", default="docs/stance.png")
        if name == "video":
            p.add_argument("--out", default=None, help="default: <run-dir>/filtered_kicks.gif")
        if name == "showcase":
            p.add_argument("--episodes", type=int, default=16)
    return parser


EXTRA_ARGS = {"kick-prior": ("publish",), "meta-train": ("synthetic_experts",), "render": ("out",), "video": ("out",),
              "showcase": ("episodes",)}  # fmt: skip


def main(argv=None) -> None:
    args = build_parser().parse_args(argv)
    run_dir = args.run_dir or Path("runs") / ("demo" if args.stage == "demo" else args.preset)
    if args.stage in ("render", "video"):
        # Offscreen rendering needs a GL backend before mujoco loads one: EGL unless told
        # otherwise. Only here: with MUJOCO_GL set, importing mujoco loads that GL library, and
        # a host without one (a CPU box, a bare GPU node) could then not even simulate.
        os.environ.setdefault("MUJOCO_GL", "egl")
    extra = {k: getattr(args, k) for k in EXTRA_ARGS.get(args.stage, ())}
    if args.distributed:
        from bumps_jax import sharding

        sharding.initialize_distributed()
    try:
        STAGES[args.stage][0](run_dir, args.preset, parse_overrides(args.set), **extra)
    except ValueError as err:  # bad config values: one clear line, not a traceback
        sys.exit(f"error: {err}")
    except KeyboardInterrupt:  # Ctrl-C or a scheduler's SIGINT: the checkpoints are the state
        sys.exit(f"interrupted: rerun the same command to resume {run_dir} from its last checkpoint")


if __name__ == "__main__":
    main()
