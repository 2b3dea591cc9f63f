"""Scene benchmark: raw MJX physics steps/s and env steps/s of the kick scene, by batch size,
and the solver/contact design choices measured against each other, all on the env's own
backend (`env.impl`; `--set env.impl=jax` for MJX-JAX).

    python -m benchmarks.scene_bench --out benchmarks/results/scene.json [--quick]

Each design variant is timed on the device (physics steps/s at one batch size) and checked for
physics with the C MuJoCo engine (`benchmarks.c_replay`): the committed kick prior replayed
without noise, where the ball rests and whether the robot stays up. A faster variant only counts
if the kick survives.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from benchmarks import c_replay
from bumps_jax import cli, config, runio
from bumps_jax.algo import rollout
from bumps_jax.envs import physics
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model
from bumps_jax.tasks.kick import scene

BATCHES = (1024, 4096, 8192, 16384)
VARIANTS = (
    "default", "converged", "iterations_1", "iterations_4", "ls_iterations_2", "cg_4", "eulerdamp_on",
    "elliptic_cone", "ball_condim_6", "timestep_4ms", "with_fall_and_r_foot_contacts", "with_joint_limits",
)  # fmt: skip
# Variants that change the physics step: the env they are replayed in runs at it too.
VARIANT_PHYSICS_DT = {"timestep_4ms": 0.004}


def variant_model(name: str, timestep: float) -> mujoco.MjModel:
    """The scene at `timestep` s with one design choice changed (name 'default' = as committed)."""
    if name not in VARIANTS:
        raise ValueError(f"unknown variant {name!r}; choose from {VARIANTS}")
    spec = mujoco.MjSpec.from_file(str(scene.SCENE_XML))
    if name == "with_fall_and_r_foot_contacts":  # the contacts we dropped, put back
        for geom in ("torso", "r_foot"):
            other = "floor" if geom == "torso" else "ball"
            spec.add_pair(name=f"{geom}_{other}", geomname1=geom, geomname2=other, condim=3)
    if name == "with_joint_limits":
        spec.option.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_LIMIT)
    model = spec.compile()
    model.opt.timestep = VARIANT_PHYSICS_DT.get(name, timestep)
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
    elif name == "converged":  # the reference the others are judged against
        model.opt.iterations, model.opt.ls_iterations = 20, 20
    return model


def physics_rate(model: mujoco.MjModel, batch: int, n_steps: int = 100, repeats: int = 3, env_cfg=None) -> float:
    """mjx.step calls per second, summed over a batch of standing robots; on the backend of
    `env_cfg` (`physics.put_physics`; None: MJX-JAX). On Warp, ValueError if the batch
    overflowed the contact pool (`env_cfg.warp_contacts`): its steps would not be the scene's."""
    mx, blank = physics.put_physics(model, env_cfg) if env_cfg is not None else (mjx.put_model(model), None)
    qpos0 = jnp.asarray(scene.stance_qpos(model))
    ids = scene.scene_ids(model)

    def init(key):
        noise = 0.01 * jax.random.normal(key, (scene.N_JOINTS,))
        qpos = qpos0.at[ids.joint_qpos].add(noise)
        data = mjx.make_data(mx) if blank is None else blank
        return data.replace(qpos=qpos, ctrl=jnp.asarray(scene.STANCE))

    @jax.jit
    def run(data):
        def body(d, _):
            return jax.vmap(mjx.step, in_axes=(None, 0))(mx, d), None

        return jax.lax.scan(body, data, None, n_steps)[0]

    data = jax.jit(jax.vmap(init))(jax.random.split(jax.random.key(0), batch))
    _, overflowed, _ = jax.vmap(physics.read_flags)(run(data))  # the first (compiling) call
    if bool(jnp.any(overflowed)):
        pool = getattr(env_cfg, "warp_contacts", None)
        raise ValueError(f"batch {batch}: Warp's contact pool ({pool} slots) overflowed; size env.warp_contacts to it")
    return batch * n_steps / best_time(run, data, repeats, warm=True)


def sized_env(env_cfg, batch: int, per_episode: int = kick_env.CONTACTS_PER_EPISODE) -> kick_env.KickEnv:
    """The kick env of `env_cfg` with Warp's contact pool sized to `batch` episodes of at most
    `per_episode` contacts (a capacity, not physics: records do not compare it)."""
    return kick_env.KickEnv(kick_env.make_config(env_cfg, {"warp_contacts": per_episode * batch}))


def env_rate(env: kick_env.KickEnv, batch: int, repeats: int = 3) -> float:
    """Env steps per second (one step = env.n_substeps physics steps + reward and metrics): whole
    noisy episodes of the committed prior's main kick (`rollout.matched_fn`, one policy x `batch`)."""
    params = kick_model.load_record(kick_model.ASSET)["params"]  # a fixed workload, whatever the env
    tables = kick_model.action_tables(params[None], env.n_steps, env.config.ctrl_dt)
    program = rollout.matched_fn(env, rollout.table_policy)
    target = jnp.full((1,), 12.0, jnp.float32)
    keys = rollout.repetition_keys(1, 1, batch)
    return batch * env.n_steps / best_time(lambda k: program(tables, target, target, k), keys, repeats)


def best_time(fn, arg, repeats: int, warm: bool = False) -> float:
    """The fastest of `repeats` calls of fn(arg) after a first (compiling) one, in seconds; `warm`:
    the caller made that first call."""
    if not warm:
        jax.block_until_ready(fn(arg))
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(arg))
        best = min(best, time.perf_counter() - t0)
    return best


def replay_prior_in_c(env: kick_env.KickEnv, model: mujoco.MjModel) -> dict:
    """The committed prior's main kick, no noise, in C MuJoCo (`model`, at env's physics step):
    where the ball rests (world frame, and as the env scores it), whether the robot stays up."""
    params = kick_model.load_record(kick_model.ASSET)["params"]  # the probe kick, whatever the variant
    out = c_replay.replay(env, c_replay.kick_actions(env, params), model=model)
    return {
        "rest_x_m": out.rest_x,
        "rest_y_m": out.rest_y,
        "distance_m": out.distance,
        "lateral_m": out.lateral,
        "ball_top_speed_m_s": out.max_ball_speed,
        "robot_stood": not out.fallen,
    }


def parse_args(argv=None):
    """(args, preset, overrides), every argument checked (parser errors) before any work."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/results/scene.json")
    parser.add_argument("--quick", action="store_true", help="small batches, for a CPU smoke test")
    parser.add_argument("--variant-batch", type=int, default=8192)
    parser.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated subset of VARIANTS")
    parser.add_argument("--preset", default="paper", help="the config whose env is measured")
    parser.add_argument("--set", action="append", nargs="+", default=[], metavar="KEY=VALUE",
                        help="config overrides, e.g. env.physics_dt=0.005")  # fmt: skip
    args = parser.parse_args(argv)
    unknown = [v for v in args.variants.split(",") if v not in VARIANTS]
    if unknown:
        parser.error(f"--variants: unknown {unknown}; choose from {list(VARIANTS)}")
    try:
        overrides = cli.parse_overrides(args.set)
        for dt in {None, *VARIANT_PHYSICS_DT.values()}:
            config.make_config(args.preset, {**overrides, **({"env.physics_dt": dt} if dt else {})})
    except ValueError as err:
        parser.error(str(err))
    return args, overrides


def main(argv=None) -> None:
    args, overrides = parse_args(argv)
    batches = (8, 16) if args.quick else BATCHES
    variant_batch = 8 if args.quick else args.variant_batch
    t_start = time.perf_counter()
    cfg = config.make_config(args.preset, overrides)
    env = kick_env.KickEnv(cfg.env)
    model = env.mj_model
    physics, env_steps = {}, {}
    for b in batches:  # every rate on the env's own backend (env.impl), its pool sized to the batch
        env_b = sized_env(cfg.env, b)
        physics[str(b)] = physics_rate(model, b, env_cfg=env_b.config)
        env_steps[str(b)] = env_rate(env_b, b)
        print(
            f"batch {b:6d}: physics {physics[str(b)]:12,.0f} steps/s   env {env_steps[str(b)]:12,.0f} steps/s",
            flush=True,
        )
    payload = {
        "quick": args.quick,
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
        "impl": env.config.impl,  # every rate above and every variant's: the env's own backend
    }
    runio.write_json(
        args.out, {**runio.provenance(cfg.preset, time.perf_counter() - t_start, config.resolved_env(cfg)), **payload}
    )
    for name in args.variants.split(","):
        dt = VARIANT_PHYSICS_DT.get(name)
        variant_env = (
            kick_env.KickEnv(config.make_config(args.preset, {**overrides, "env.physics_dt": dt}).env) if dt else env
        )
        m = variant_model(name, variant_env.physics_dt)
        # Two contact slots per contact pair, as the committed scene's pool has (12 for 6 pairs).
        per_episode = kick_env.CONTACTS_PER_EPISODE * m.npair // model.npair
        pooled = sized_env(variant_env.config, variant_batch, per_episode)
        rate = physics_rate(m, variant_batch, env_cfg=pooled.config)
        row = {
            "physics_steps_per_s": rate,
            "sim_seconds_per_s": rate * m.opt.timestep,
            **replay_prior_in_c(variant_env, m),
        }
        payload["variants"][name] = row
        print(
            f"{name:18s} {rate:12,.0f} steps/s  {row['sim_seconds_per_s']:10,.0f} sim-s/s  "
            f"rest {row['rest_x_m']:6.2f} m  stood {row['robot_stood']}",
            flush=True,
        )
        # Written after every variant: a run cut short still leaves what it measured.
        runio.write_json(
            args.out,
            {**runio.provenance(cfg.preset, time.perf_counter() - t_start, config.resolved_env(cfg)), **payload},
        )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
