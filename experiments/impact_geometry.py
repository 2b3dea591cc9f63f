"""Where the experts' starting kicks strike the ball, and how the strike moves with the ball.

Replays kicks (an experts run's starting_kicks.json) without noise in C MuJoCo (the scene's
model, the env's servo ramp) with the ball moved a few millimetres along the kick line, and
records the first contact between the robot and the ball: how far above the ball's centre it
is, how steeply its normal points up, how fast the foot moves, and where the ball comes to rest.
A strike through the centre with a level foot would change little when the ball moves; one on
the ball's upper back changes its angle, and with it the ball's speed. Writes
<out-dir>/impact_geometry_cpu.json.

    python experiments/impact_geometry.py --kicks docs/experts_starting_kicks.json --targets 8 12 18
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import mujoco
import numpy as np

from bumps_jax import experts, kick_env, prior, results, scene

OFFSETS_MM = (-10.0, -5.0, 0.0, 5.0, 10.0)


def strike(model, params: np.ndarray, ball_dx: float, ctrl_dt: float = 0.02, horizon_s: float = 1.5) -> dict:
    """One noise-free kick in `model` (the scene) with the ball moved `ball_dx` m forward: the
    first robot-ball contact and the ball's resting distance (m ahead of its nominal start)."""
    ids = scene.scene_ids(model)
    data = mujoco.MjData(model)
    qpos = scene.stance_qpos(model)
    start_x = qpos[ids.ball_qpos]
    qpos[ids.ball_qpos] += ball_dx
    data.qpos[:] = qpos
    data.ctrl[:] = scene.STANCE
    mujoco.mj_forward(model, data)
    n_substeps = round(ctrl_dt / model.opt.timestep)
    n_steps = round(horizon_s / ctrl_dt)
    actions = np.asarray(prior.keyframes_to_actions(params, n_steps, ctrl_dt))
    low, high = ids.joint_range[:, 0], ids.joint_range[:, 1]
    command, contact = scene.STANCE.copy(), None
    for k in range(n_steps):
        ramp = kick_env.servo_ramp(command, actions[k], low, high, scene.MAX_JOINT_SPEED * ctrl_dt, n_substeps)
        for ctrl in ramp:
            data.ctrl[:] = ctrl
            mujoco.mj_step(model, data)
            if contact is None:
                contact = _robot_ball_contact(model, data, ids, k)
        command = ramp[-1]
    q, v = ids.ball_qpos, ids.ball_qvel
    quat = data.qpos[q + 3 : q + 7]
    angvel = np.zeros(3)
    mujoco.mju_rotVecQuat(angvel, data.qvel[v + 3 : v + 6], quat)
    rest = kick_env.rest_point(data.qpos[q : q + 3], data.qvel[v : v + 3], angvel, scene.rolling_decel_rate())
    return {"contact": contact, "distance_m": float(rest[0] - start_x), "lateral_m": float(rest[1] - qpos[q + 1])}


def _robot_ball_contact(model, data, ids, step: int) -> dict | None:
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
    args = parser.parse_args(argv)
    try:
        kicks = experts.read_starting_kicks(args.kicks, args.targets)
    except ValueError as err:
        parser.error(f"--targets: {err}")

    start = time.perf_counter()
    model = scene.load_model()
    rows = {}
    for target, params in kicks.items():
        rows[str(target)] = by_offset = {str(mm): strike(model, params, mm / 1000.0) for mm in OFFSETS_MM}
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
    payload = {"kicks": args.kicks, "offsets_mm": list(OFFSETS_MM), "targets": rows,
               **results.provenance("impact_geometry", time.perf_counter() - start,
                                    physics_dt_s=model.opt.timestep)}  # fmt: skip
    print(results.write_json(Path(args.out_dir) / "impact_geometry_cpu.json", payload))


if __name__ == "__main__":
    main()
