"""Scene benchmark: raw MJX physics steps/s and env steps/s of the kick scene, by batch size,
and the solver/contact design choices measured against each other.

    python benchmarks/scene_bench.py --out benchmarks/results/scene.json [--quick]

Each design variant is timed on the GPU (physics steps/s at one batch size) and checked for
physics with the C MuJoCo engine: the committed kick prior replayed without noise, where the
ball rests and whether the robot stays up. A faster variant only counts if the kick survives.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from bumps_jax import kick_env, prior, results, scene

BATCHES = (1024, 4096, 8192, 16384)


def variant_model(name: str) -> mujoco.MjModel:
    """The scene with one design choice changed (name 'default' = as committed)."""
    spec = mujoco.MjSpec.from_file(str(scene.SCENE_XML))
    if name == "with_fall_and_r_foot_contacts":  # the contacts we dropped, put back
        for geom in ("torso", "r_foot"):
            other = "floor" if geom == "torso" else "ball"
            spec.add_pair(name=f"{geom}_{other}", geomname1=geom, geomname2=other, condim=3)
    if name == "with_joint_limits":
        spec.option.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_LIMIT)
    model = spec.compile()
    if name == "iterations_1":
        model.opt.iterations, model.opt.ls_iterations = 1, 4
    elif name == "iterations_4":
        model.opt.iterations, model.opt.ls_iterations = 4, 8
    elif name == "ls_iterations_2":
        model.opt.ls_iterations = 2
    elif name == "cg_4":
        model.opt.solver, model.opt.iterations, model.opt.ls_iterations = int(mujoco.mjtSolver.mjSOL_CG), 4, 4
    elif name == "eulerdamp_on":
        model.opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_EULERDAMP)
    elif name == "elliptic_cone":
        model.opt.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    elif name == "ball_condim_6":
        ball_pairs = [i for i in range(model.npair) if "ball" in mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_PAIR, i)]
        model.pair_dim[ball_pairs] = 6
    elif name == "timestep_4ms":
        model.opt.timestep = 0.004
    elif name == "converged":  # the reference the others are judged against
        model.opt.iterations, model.opt.ls_iterations = 20, 20
    elif name not in ("default", "with_fall_and_r_foot_contacts", "with_joint_limits"):
        raise ValueError(f"unknown variant {name!r}")
    return model


VARIANTS = (
    "default", "converged", "iterations_1", "iterations_4", "ls_iterations_2", "cg_4", "eulerdamp_on",
    "elliptic_cone", "ball_condim_6", "timestep_4ms", "with_fall_and_r_foot_contacts", "with_joint_limits",
)  # fmt: skip


def physics_rate(model: mujoco.MjModel, batch: int, n_steps: int = 100, repeats: int = 3) -> float:
    """mjx.step calls per second, summed over a batch of standing robots."""
    mx = mjx.put_model(model)
    qpos0 = jnp.asarray(scene.stance_qpos(model))
    ids = scene.scene_ids(model)

    def init(key):
        noise = 0.01 * jax.random.normal(key, (scene.N_JOINTS,))
        qpos = qpos0.at[ids.joint_qpos].add(noise)
        return mjx.make_data(mx).replace(qpos=qpos, ctrl=jnp.asarray(scene.STANCE))

    @jax.jit
    def run(data):
        def body(d, _):
            return jax.vmap(mjx.step, in_axes=(None, 0))(mx, d), None

        return jax.lax.scan(body, data, None, n_steps)[0]

    data = jax.jit(jax.vmap(init))(jax.random.split(jax.random.key(0), batch))
    jax.block_until_ready(run(data))  # compile
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(run(data))
        best = min(best, time.perf_counter() - t0)
    return batch * n_steps / best


def env_rate(env: kick_env.KickEnv, batch: int, repeats: int = 3) -> float:
    """Env steps per second (one step = 4 physics steps + reward and metrics), whole episodes."""
    actions = prior.keyframes_to_actions(jnp.asarray(prior.load_prior()["params"]), env.n_steps)

    @jax.jit
    def run(keys):
        def episode(key):
            state = env.reset(key, 12.0)
            state, _ = jax.lax.scan(lambda s, a: (env.step(s, a), None), state, actions)
            return state.metrics["final_error"]

        return jax.vmap(episode)(keys)

    keys = jax.random.split(jax.random.key(1), batch)
    jax.block_until_ready(run(keys))
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(run(keys))
        best = min(best, time.perf_counter() - t0)
    return batch * env.n_steps / best


def replay_prior_in_c(model: mujoco.MjModel) -> dict:
    """The committed prior, no noise, in C MuJoCo: where the ball rests, whether the robot falls."""
    ids = scene.scene_ids(model)
    data = kick_env.mj_data_for(model)
    n_sub = int(round(0.02 / model.opt.timestep))
    actions = np.asarray(prior.keyframes_to_actions(jnp.asarray(prior.load_prior()["params"]), 75))
    command = scene.STANCE.copy()
    lo, hi = ids.joint_range[:, 0], ids.joint_range[:, 1]
    min_torso, top_speed = np.inf, 0.0
    for action in actions:
        ramp = kick_env.servo_ramp(command, action, lo, hi, scene.MAX_JOINT_SPEED * 0.02, n_sub)
        command = ramp[-1]
        for ctrl in ramp:
            data.ctrl[:] = ctrl
            mujoco.mj_step(model, data)
            top_speed = max(top_speed, np.linalg.norm(data.qvel[ids.ball_qvel : ids.ball_qvel + 3]))
        min_torso = min(min_torso, data.xpos[ids.torso_body][2])
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, data.qpos[ids.ball_qpos + 3 : ids.ball_qpos + 7])
    angvel = rot.reshape(3, 3) @ data.qvel[ids.ball_qvel + 3 : ids.ball_qvel + 6]
    rest = np.asarray(
        kick_env.rest_point(
            data.qpos[ids.ball_qpos : ids.ball_qpos + 3], data.qvel[ids.ball_qvel : ids.ball_qvel + 3],
            angvel, scene.rolling_decel_rate(),
        )
    )  # fmt: skip
    return {
        "rest_x_m": float(rest[0]),
        "rest_y_m": float(rest[1]),
        "ball_top_speed_m_s": float(top_speed),
        "robot_stood": bool(min_torso > kick_env.default_config().fall_height),
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/results/scene.json")
    parser.add_argument("--quick", action="store_true", help="small batches, for a CPU smoke test")
    parser.add_argument("--variant-batch", type=int, default=8192)
    parser.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated subset of VARIANTS")
    args = parser.parse_args(argv)
    batches = (8, 16) if args.quick else BATCHES
    variant_batch = 8 if args.quick else args.variant_batch
    t_start = time.perf_counter()
    env = kick_env.KickEnv()
    model = scene.load_model()
    physics, env_steps = {}, {}
    for b in batches:
        physics[str(b)] = physics_rate(model, b)
        env_steps[str(b)] = env_rate(env, b)
        print(
            f"batch {b:6d}: physics {physics[str(b)]:12,.0f} steps/s   env {env_steps[str(b)]:12,.0f} steps/s",
            flush=True,
        )
    payload = {
        "physics_steps_per_s": physics,
        "env_steps_per_s": env_steps,
        "variants_batch": variant_batch,
        "variants": {},
        "scene": {
            "timestep": float(model.opt.timestep),
            "iterations": int(model.opt.iterations),
            "ls_iterations": int(model.opt.ls_iterations),
            "contact_pairs": int(model.npair),
            "nv": int(model.nv),
        },
    }
    preset = "quick" if args.quick else "paper"
    results.write_json(args.out, {**results.provenance(preset, time.perf_counter() - t_start), **payload})
    variants = payload["variants"]
    for name in args.variants.split(","):
        m = variant_model(name)
        rate = physics_rate(m, variant_batch)
        row = {"physics_steps_per_s": rate, "sim_seconds_per_s": rate * m.opt.timestep, **replay_prior_in_c(m)}
        variants[name] = row
        print(
            f"{name:18s} {rate:12,.0f} steps/s  {row['sim_seconds_per_s']:10,.0f} sim-s/s  "
            f"rest {row['rest_x_m']:6.2f} m  stood {row['robot_stood']}",
            flush=True,
        )
        # Written after every variant: a run cut short still leaves what it measured.
        results.write_json(args.out, {**results.provenance(preset, time.perf_counter() - t_start), **payload})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
