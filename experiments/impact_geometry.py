"""Where the experts' starting kicks strike the ball, and how the strike moves with the ball.

Replays kicks (an experts run's starting_kicks.json) without noise in C MuJoCo
(`benchmarks.c_replay`: the env's control loop and scoring) with the ball moved a few
millimetres along the kick line, and records the first contact between the robot and the ball:
how far above the ball's centre it is, how steeply its normal points up, how fast the foot
moves, and where the ball comes to rest. A strike through the centre with a level foot would
change little when the ball moves; one on the ball's upper back changes its angle, and with it
the ball's speed. Writes <out-dir>/impact_geometry_cpu.json.

    python experiments/impact_geometry.py --kicks docs/experts_starting_kicks.json --targets 8 12 18
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import mujoco
import numpy as np

from benchmarks import c_replay
from bumps_jax import cli, config, runio
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import scene, starting_kicks

OFFSETS_MM = (-10.0, -5.0, 0.0, 5.0, 10.0)


def strike(env: kick_env.KickEnv, params: np.ndarray, ball_dx: float) -> dict:
    """One noise-free kick (params (14,)) in C MuJoCo with the ball moved `ball_dx` m forward: the
    first robot-ball contact and where the ball rests (m ahead of its nominal start, and left)."""
    first: dict = {}
    ids = scene.scene_ids(env.mj_model)

    def watch(model, data, step):
        if not first:
            first.update(robot_ball_contact(model, data, ids, step) or {})

    out = c_replay.replay(env, c_replay.kick_actions(env, params), ball_offset=(ball_dx, 0.0), on_substep=watch)
    return {"contact": first or None, "distance_m": out.distance, "lateral_m": out.lateral}


def robot_ball_contact(model: mujoco.MjModel, data: mujoco.MjData, ids: scene.SceneIds, step: int) -> dict | None:
    """The first contact of the ball with anything but the floor (control step `step`), or None."""
    con = data.contact
    for i in range(data.ncon):
        pair = (int(con.geom1[i]), int(con.geom2[i]))
        if ids.ball_geom not in pair or ids.floor_geom in pair:
            continue
        other = pair[1] if pair[0] == ids.ball_geom else pair[0]
        # MuJoCo's contact normal points from geom1 to geom2: turn it to push the ball.
        normal = con.frame[i, :3] * (1.0 if pair[1] == ids.ball_geom else -1.0)
        body_vel = np.zeros(6)
        mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_GEOM, other, body_vel, 0)
        return {
            "step": step,
            "geom": mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, other),
            "height_above_centre_m": float(con.pos[i, 2] - data.qpos[ids.ball_qpos + 2]),
            "normal_elevation_deg": float(np.degrees(np.arcsin(np.clip(-normal[2], -1.0, 1.0)))),
            "foot_velocity_xz_m_s": [float(body_vel[3]), float(body_vel[5])],
        }
    return None


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--kicks", default="docs/experts_starting_kicks.json", help="an experts run's kicks")
    parser.add_argument("--targets", type=float, nargs="+", default=[8.0, 12.0, 15.0, 18.0])
    parser.add_argument("--out-dir", default="experiments/results")
    parser.add_argument("--preset", default="paper", help="the config whose env replays the kicks")
    parser.add_argument("--set", action="append", nargs="+", default=[], metavar="KEY=VALUE",
                        help="config overrides, e.g. env.physics_dt=0.005")  # fmt: skip
    args = parser.parse_args(argv)
    try:
        cfg = config.make_config(args.preset, cli.parse_overrides(args.set))
        kicks = starting_kicks.read_starting_kicks(args.kicks, args.targets)
    except ValueError as err:
        parser.error(str(err))

    start = time.perf_counter()
    env = kick_env.KickEnv(cfg.env)
    rows = {}
    for target, params in kicks.items():
        rows[str(target)] = by_offset = {str(mm): strike(env, params, mm / 1000.0) for mm in OFFSETS_MM}
        distances = [by_offset[str(mm)]["distance_m"] for mm in OFFSETS_MM]
        slope = np.polyfit(np.asarray(OFFSETS_MM) / 10.0, distances, 1)[0]
        rows[str(target)]["distance_per_cm_of_ball_m"] = float(slope)
        hit = by_offset["0.0"]["contact"] or {}
        height_cm = 100 * hit.get("height_above_centre_m", np.nan)
        print(
            f"{target:5.1f} m  rests {' '.join(f'{d:5.2f}' for d in distances)} m for ball {OFFSETS_MM} mm"
            f" ({slope:+.2f} m per cm); hit by {hit.get('geom')} {height_cm:.1f} cm above centre,"
            f" normal {hit.get('normal_elevation_deg', np.nan):.0f} deg down into it",
            flush=True,
        )
    payload = {
        "kicks": args.kicks,
        "offsets_mm": list(OFFSETS_MM),
        "targets": rows,
        **runio.provenance(cfg.preset, time.perf_counter() - start, config.resolved_env(cfg)),
    }
    print(runio.write_json(Path(args.out_dir) / "impact_geometry_cpu.json", payload))


if __name__ == "__main__":
    main()
