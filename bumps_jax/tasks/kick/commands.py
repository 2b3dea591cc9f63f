"""The kick's own commands (`COMMANDS`): render (the stance), video (filtered kicks of a run),
showcase (the committed prior's kicks) and kick (the shipped meta-policy kicking to a target).

Each takes the pipeline config, the run directory and the parsed arguments; each checks its
inputs (with their paths) before any long work. This module imports nothing heavy at import: the
command line reads `COMMANDS` before MuJoCo loads.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bumps_jax import runio
from bumps_jax.tasks.protocol import Command


def render(cfg, run_dir: Path, args) -> None:
    from bumps_jax.tasks.kick import render as render_mod  # noqa: PLC0415

    out = Path(args.out) if args.out else run_dir / "stance.png"
    runio.check_writable(out.parent, "output folder", create=not args.out)  # a folder the user named must exist
    render_mod.check_gl()
    print(f"wrote {render_mod.stance_picture(out)}")


def video(cfg, run_dir: Path, args) -> None:
    """A GIF of filtered kicks of a finished run: the (4, 256) net at the test tasks nearest 8, 12, 16 m."""
    import jax  # noqa: PLC0415

    from bumps_jax.algo import bc  # noqa: PLC0415
    from bumps_jax.pipeline.stages import meta as meta_stage  # noqa: PLC0415
    from bumps_jax.tasks.kick import env as kick_env  # noqa: PLC0415
    from bumps_jax.tasks.kick import render  # noqa: PLC0415

    table2 = runio.read_json(run_dir / "filter" / "table2.json", "run the filter stage first")
    obs_norm = meta_stage.run_obs_norm(run_dir)
    out = Path(args.out) if args.out else run_dir / "filtered_kicks.gif"
    runio.check_writable(out.parent, "output folder", create=not args.out)
    render.check_gl()
    tasks, chosen = np.asarray(table2["tasks"]), np.asarray(table2["chosen_contexts"]["filtered_4x256"])
    picks = sorted({int(np.argmin(np.abs(tasks - t))) for t in (8.0, 12.0, 16.0)})
    depth, width = cfg.meta.nets["meta_4x256"]
    apply_fn, params = bc.load_policy(run_dir / "meta" / "meta_4x256", depth, width, cfg.meta.train, obs_norm=obs_norm)
    params = jax.tree.map(lambda a: a[cfg.filter.net_seed], params)
    env = kick_env.KickEnv(cfg.env)
    path = render.kick_gif(out, env, apply_fn, params, chosen[picks], tasks[picks])
    print(f"wrote {path}")


def showcase(cfg, run_dir: Path, args) -> None:
    """A batch of noisy episodes of the committed prior's main kick: the scene and env at a glance."""
    import jax  # noqa: PLC0415
    import jax.numpy as jnp  # noqa: PLC0415

    from bumps_jax.algo import rollout  # noqa: PLC0415
    from bumps_jax.tasks.kick import env as kick_env  # noqa: PLC0415
    from bumps_jax.tasks.kick import keyframes as kick_model  # noqa: PLC0415

    if args.episodes < 1:
        raise ValueError(f"--episodes must be a positive integer, got {args.episodes}")
    record = kick_model.load_record(kick_model.ASSET, env_cfg=cfg.env)
    env = kick_env.KickEnv(cfg.env)
    table = kick_model.action_tables(kick_model.clip_params(record["params"])[None], env.n_steps, env.dt)
    keys = jax.random.split(jax.random.key(0), args.episodes)[None]
    target = jnp.full((1,), 12.0)
    out = rollout.matched_fn(env, rollout.table_policy)(table, target, target, keys)
    print(f"{args.episodes} noisy kicks of the committed 12 m prior:")
    print(f"  resting distance {np.mean(out['distance']):.2f} +- {np.std(out['distance']):.2f} m")
    print(f"  final error      {np.mean(out['final_error']):.2f} m, valid {np.mean(out['valid']):.2f}")


def kick(cfg, run_dir: Path, args) -> None:
    """Kick to --target with a shipped meta-policy: filter a context, then --kicks noisy kicks."""
    import time  # noqa: PLC0415

    from bumps_jax import config  # noqa: PLC0415
    from bumps_jax.tasks.kick import policies  # noqa: PLC0415

    t0 = time.perf_counter()
    for name, value in (("--kicks", args.kicks), ("--selection-reps", args.selection_reps)):
        if value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value}")
    if args.gif:
        from bumps_jax.tasks.kick import render  # noqa: PLC0415

        if Path(args.gif).suffix.lower() != ".gif" or Path(args.gif).is_dir():
            raise ValueError(f"--gif {args.gif!r}: give a file name ending in .gif")
        runio.check_writable(Path(args.gif).parent, "the GIF's folder", create=False)
        render.check_gl()  # before the kicks, not after them
    directory = args.policies or policies.ASSET_DIR
    if not (Path(directory) / policies.MANIFEST).is_file():
        raise ValueError(f"no shipped policies in {directory}: {policies.HOW_TO_MAKE}")
    manifest = runio.read_json(Path(directory) / policies.MANIFEST, "a shipped-policies manifest")
    # The policies' own physics, with only the env keys the user set on the command line.
    env_overrides = {k.removeprefix("env."): v for k, v in config.overrides_of(cfg).items() if k.startswith("env.")}
    from bumps_jax.algo import sharding  # noqa: PLC0415

    n_devices = sharding.device_mesh(impl=policies.env_config(manifest, env_overrides).impl).size
    env_cfg = policies.kick_env_config(manifest, env_overrides, args.kicks, n_devices)
    if args.net not in manifest.get("nets", {}):
        raise ValueError(f"--net {args.net!r}: the shipped nets are {sorted(manifest.get('nets', {}))}")
    from bumps_jax.tasks.kick import env as kick_env  # noqa: PLC0415

    target = float(kick_env.check_targets([args.target], tuple(env_cfg.task_range))[0])
    shipped = policies.load(directory, env_cfg)
    out = policies.filtered_kicks(shipped, args.net, target, args.kicks, env_cfg, args.selection_reps, args.seed,
                                  kicks_progress(args.kicks))  # fmt: skip
    for line in policies.describe(shipped, args.net, target, out, time.perf_counter() - t0):
        print(line)
    if args.gif:
        from bumps_jax.algo import bc  # noqa: PLC0415

        entry = shipped.manifest["nets"][args.net]
        model = bc.MetaPolicy(entry["depth"], entry["width"], obs_norm=bc.obs_norm_of_record(entry))
        apply_fn = bc.policy_apply(model)
        env = kick_env.KickEnv(env_cfg)
        # the printed kick nearest their median resting distance, replayed with its own noise
        shown = int(np.argmin(np.abs(out.distance - np.median(out.distance))))
        path = render.kick_gif(args.gif, env, apply_fn, shipped.nets[args.net], [out.context], [target],
                               keys=out.keys[shown : shown + 1])  # fmt: skip
        print(f"wrote {path}: kick {shown + 1} of the {len(out.distance)} above ({out.distance[shown]:.2f} m)")


def kicks_progress(n_kicks: int, lines: int = 10):
    """`filtered_kicks`' progress: a line with an ETA about every 1/`lines` of the kicks, where they
    take more than `lines` calls (none for the default 16)."""
    from bumps_jax import resumable  # noqa: PLC0415
    from bumps_jax.tasks.kick import policies  # noqa: PLC0415

    if n_kicks <= lines * policies.KICK_BLOCK:
        return None
    clock, shown = resumable.Clock(n_kicks), [0]

    def progress(done: int, total: int) -> None:
        if done - shown[0] >= total / lines or done == total:
            shown[0] = done
            print(f"kicks {done}/{total}  {clock.tick(done)}", flush=True)

    return progress


def picture_arguments(p) -> None:
    p.add_argument("--out", default=None, help="the picture's path")


def showcase_arguments(p) -> None:
    p.add_argument("--episodes", type=int, default=16)


def kick_arguments(p) -> None:
    p.add_argument("--target", type=float, required=True, help="target distance (m)")
    p.add_argument("--kicks", type=int, default=16, help="noisy kicks at the chosen context (default 16)")
    p.add_argument("--net", default="meta_4x256", help="meta_4x256 (default) or meta_11x128")
    p.add_argument("--gif", default=None, help="also render one of the printed kicks to this GIF")
    p.add_argument("--selection-reps", type=int, default=4, help="noisy kicks per candidate context")
    p.add_argument("--seed", type=int, default=0, help="noise of the selection and the kicks")
    p.add_argument("--policies", type=Path, default=None, help="shipped policies (default: assets/policies)")


COMMANDS = {
    "render": Command(
        "render the robot in its stance to a PNG", render, picture_arguments,
        renders=lambda args: True, writes_run=lambda args: args.out is None,
    ),
    "video": Command(
        "render a GIF of filtered kicks at three distances from a finished run", video, picture_arguments,
        renders=lambda args: True, needs_run=True,
    ),
    "showcase": Command("replay the committed prior over a batch of noisy episodes", showcase, showcase_arguments),
    "kick": Command(
        "kick to a target with the shipped meta-policy (assets/policies/): filter a context, then N noisy kicks",
        kick, kick_arguments, own_options_only=True,
        renders=lambda args: any(a == "--gif" or a.startswith("--gif=") for a in args),
    ),
}  # fmt: skip
