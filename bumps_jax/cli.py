"""`python -m bumps_jax <stage> --preset P --run-dir D --set key=value ...`: every stage of the
pipeline from one command line. The only module that parses arguments or reads the environment.
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


def _kick_prior(args) -> None:
    from bumps_jax import prior

    payload = prior.run_stage(args.preset, args.run_dir, parse_overrides(args.set), publish=args.publish)
    print(json.dumps({k: payload[k] for k in ("mean_error_m", "valid_fraction", "wall_s")}, indent=2))


def _render(args) -> None:
    os.environ.setdefault("MUJOCO_GL", "egl" if args.gl == "egl" else "osmesa")
    from bumps_jax import render

    print(render.stance_picture(args.out))


def _showcase(args) -> None:
    """A batch of noisy episodes of the committed prior: the scene and env at a glance."""
    import jax
    import numpy as np

    from bumps_jax import kick_env, prior

    env = kick_env.KickEnv()
    params = prior.load_prior()["params"]
    rollout = prior.make_rollout(env)
    keys = jax.random.split(jax.random.key(0), args.episodes)[None]
    out = rollout(prior.clip_params(params)[None], keys, 12.0)
    print(f"{args.episodes} noisy kicks of the committed 12 m prior:")
    print(f"  resting distance {np.mean(out['distance']):.2f} +- {np.std(out['distance']):.2f} m")
    print(f"  final error      {np.mean(out['final_error']):.2f} m, valid {np.mean(out['valid']):.2f}")


STAGES = {
    "kick-prior": (_kick_prior, "optimise the keyframe kick prior (CMA-ES), evaluate and sweep it"),
    "render": (_render, "render the robot in its stance to a PNG"),
    "showcase": (_showcase, "replay the committed prior over a batch of noisy episodes"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m bumps_jax", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="stage", required=True)
    for name, (_, help_text) in STAGES.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.add_argument("--preset", default="tiny", choices=("tiny", "paper"))
        p.add_argument("--run-dir", default=None, type=Path, help="default: runs/<preset>")
        p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides")
        if name == "kick-prior":
            p.add_argument("--publish", action="store_true", help="also write assets/kick_prior.json")
        if name == "render":
            p.add_argument("--out", default="docs/stance.png")
            p.add_argument("--gl", default=os.environ.get("MUJOCO_GL", "egl"), choices=("egl", "osmesa"))
        if name == "showcase":
            p.add_argument("--episodes", type=int, default=16)
    return parser


def main(argv=None) -> None:
    args = build_parser().parse_args(argv)
    if args.run_dir is None:
        args.run_dir = Path("runs") / args.preset
    try:
        STAGES[args.stage][0](args)
    except ValueError as err:  # bad config values: one clear line, not a traceback
        sys.exit(f"error: {err}")


if __name__ == "__main__":
    main()
