"""The engines check: the committed kick prior on C MuJoCo, MJX-Warp and MJX-JAX, side by side.

    python benchmarks/engines.py [--out benchmarks/results/engines.json] [--noisy-reps 32]

Every engine plays the prior's three anchors (short, main, long) without noise at 2, 4 and 8
constraint-solver iterations (C MuJoCo also at 50: converged), and the main anchor over
`--noisy-reps` noisy episodes. The noise is drawn once, by the env's own reset, and every engine
plays the same draws: C MuJoCo (`c_replay`) replays each episode's ball start, joint angles,
friction and servo-gain scales. Rows report where the ball rests along the kick line.

An MJX engine agrees with MuJoCo when every noise-free anchor rests within `TOLERANCE_M` of C
MuJoCo at the same iterations; its chosen iteration count is the fewest whose anchors rest within
`TOLERANCE_M` of C MuJoCo converged. The two MJX backends are also timed on this device (first
call, i.e. compile plus one run, and steady physics steps/s of the noisy batch).
"""

from __future__ import annotations

import argparse
import tempfile
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from benchmarks import c_replay
from bumps_jax import cli, config, runio
from bumps_jax.algo import rollout
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model
from bumps_jax.tasks.kick import scene

ITERATIONS = (2, 4, 8)
CONVERGED = 50  # C MuJoCo's reference solve
TOLERANCE_M = 0.1
MAIN = kick_model.ANCHORS.index("main")
# Scores only (the distance metric does not depend on it): inside every env's task range.
TARGET_M = 12.0


def env_for(base_env, impl: str, iterations: int, batch: int, noisy: bool) -> kick_env.KickEnv:
    """The env of one engine at `iterations`, Warp's contact slots sized to `batch` episodes."""
    overrides = {"impl": impl, "solver_iterations": iterations, "warp_contacts": kick_env.CONTACTS_PER_EPISODE * batch}
    if not noisy:
        overrides.update({f"noise.{k}": 0.0 for k in base_env.noise})
    return kick_env.KickEnv(base_env, overrides)


def play(env: kick_env.KickEnv, tables, keys, calls: int = 1) -> tuple[dict, list[float]]:
    """Tables (N, T, 22) each over keys (N, R) in one jitted program, called `calls` times:
    (metrics of (N, R) as numpy, seconds of each call; the first compiles)."""
    fn = rollout.matched_fn(env, rollout.table_policy)
    targets = jnp.full(tables.shape[0], TARGET_M)
    times = []
    for _ in range(calls):
        t = time.perf_counter()
        metrics = jax.block_until_ready(fn(tables, targets, targets, keys))
        times.append(time.perf_counter() - t)
    return jax.tree.map(np.asarray, metrics), times


def mjx_engine(base_env, impl: str, iterations: int, tables, keys) -> dict:
    """One MJX backend at `iterations`: noise-free anchors (3,), noisy main kicks (R,), timings."""
    reps = keys.shape[1]
    quiet, (quiet_s,) = play(env_for(base_env, impl, iterations, len(tables), False), tables, keys[:, :1])
    env = env_for(base_env, impl, iterations, reps, True)
    noisy, (first_s, second_s) = play(env, tables[MAIN : MAIN + 1], keys[MAIN : MAIN + 1], calls=2)
    steps = reps * env.n_steps * env.n_substeps
    return {
        "anchors": quiet["distance"][:, 0],
        "noisy": noisy["distance"][0],
        "valid": float(np.mean(noisy["valid"])),
        "overflow": float(np.mean(noisy["overflow"])),
        "solver_limit_steps": float(np.mean(noisy["solver_limit_steps"])),
        "timing": {
            # The noise-free program's one call: compile + run of 3 episodes; for the first Warp
            # program of a run with --cold-warp-cache it also builds Warp's kernels.
            "anchors_first_call_s": round(quiet_s, 3),
            "batch": reps,
            "first_call_s": round(first_s, 3),
            "steady_call_s": round(second_s, 3),
            "compile_s": round(first_s - second_s, 3),  # the first call less a steady one
            "physics_steps_per_s": round(steps / second_s, 1),
        },
    }


def noise_draws(base_env, keys) -> list[dict]:
    """The env's own noise for each key (R,): ball offset (2,) m, joint angles (22,) rad, friction
    and servo-gain scales, as the env's reset draws them."""
    env = env_for(base_env, "jax", ITERATIONS[0], len(keys), True)
    states = jax.vmap(env.reset)(keys, jnp.full(len(keys), TARGET_M))
    qpos = np.asarray(states.pipeline_state.qpos, np.float64)
    start = scene.stance_qpos(env.mj_model)
    b = env.ids.ball_qpos
    return [
        {
            "ball_offset": qpos[i, b : b + 2] - start[b : b + 2],
            "joints": qpos[i, env.ids.joint_qpos],
            "friction_scale": float(states.info["friction_scale"][i]),
            "gain_scale": float(states.info["gain_scale"][i]),
        }
        for i in range(len(keys))
    ]


def c_kick(env: kick_env.KickEnv, actions, iterations: int, draw: dict | None, peaks: dict) -> float:
    """C MuJoCo's resting distance (m) of one kick, with one episode's noise `draw` (None: none);
    `peaks` keeps the most contacts and constraint rows seen in one physics step."""
    model = c_replay.scene_model(env, iterations)
    offset = (0.0, 0.0)
    if draw is not None:  # as KickEnv._episode_model scales them
        model.pair_friction[:] *= draw["friction_scale"]
        model.actuator_gainprm[:, 0] *= draw["gain_scale"]
        model.actuator_biasprm[:, 1] *= draw["gain_scale"]
        offset = draw["ball_offset"]

    def watch(_, data, __):
        peaks["contacts"] = max(peaks["contacts"], int(data.ncon))
        peaks["rows"] = max(peaks["rows"], int(data.nefc))

    sim = c_replay.Replay(env, offset, model=model, on_substep=watch)
    if draw is not None:
        sim.data.qpos[env.ids.joint_qpos] = draw["joints"]
        mujoco.mj_forward(sim.model, sim.data)
    for action in actions:
        sim.step(action)
    return sim.outcome().distance


def c_engine(base_env, anchors, draws, peaks: dict) -> dict:
    """C MuJoCo at every iteration count and converged: {iterations: {anchors (3,), noisy (R,)}}."""
    env = env_for(base_env, "jax", ITERATIONS[0], 1, False)
    actions = [c_replay.kick_actions(env, p) for p in anchors]
    out = {}
    for it in (*ITERATIONS, CONVERGED):
        quiet = np.array([c_kick(env, a, it, None, peaks) for a in actions])  # also warms up the scoring
        t = time.perf_counter()
        noisy = np.array([c_kick(env, actions[MAIN], it, d, peaks) for d in draws])
        seconds = time.perf_counter() - t
        out[it] = {
            "anchors": quiet,
            "noisy": noisy,
            "physics_steps_per_s": round(len(draws) * env.n_steps * env.n_substeps / seconds, 1),
        }
    return out


def table_rows(results: dict) -> list[dict]:
    """The contract's rows: one per (engine, iterations, kick, noise)."""
    rows = []
    for (engine, it), r in sorted(results.items()):
        for kick, d in zip(kick_model.ANCHORS, r["anchors"], strict=True):
            rows.append(dict(engine=engine, iterations=it, kick=kick, noise=False, distance_m=float(d), std_m=None))
        rows.append(
            dict(
                engine=engine, iterations=it, kick="main", noise=True, n=len(r["noisy"]),
                distance_m=float(np.mean(r["noisy"])), std_m=float(np.std(r["noisy"])),
            )
        )  # fmt: skip
    return rows


def agreement(results: dict) -> dict:
    """Per MJX engine and iterations: the largest |distance - C MuJoCo's| (m), noise-free anchors
    and the same noisy kicks, at the same iterations and against C converged."""
    out = {}
    for (engine, it), r in results.items():
        if engine == "c":
            continue
        c, conv = results["c", it], results["c", CONVERGED]
        out.setdefault(engine, {})[str(it)] = {
            "anchors_vs_c_m": float(np.max(np.abs(r["anchors"] - c["anchors"]))),
            "noisy_vs_c_m": float(np.max(np.abs(r["noisy"] - c["noisy"]))),
            "anchors_vs_converged_m": float(np.max(np.abs(r["anchors"] - conv["anchors"]))),
        }
    return out


def choose(agree: dict, timings: dict) -> tuple[dict, dict]:
    """(chosen engine per device, chosen iterations per engine) by the module docstring's rule."""
    iterations = {}
    for engine, by_it in agree.items():
        ok = [int(it) for it, a in by_it.items() if a["anchors_vs_converged_m"] <= TOLERANCE_M]
        iterations[engine] = min(ok) if ok else None
    agreeing = [e for e, by_it in agree.items() if all(a["anchors_vs_c_m"] <= TOLERANCE_M for a in by_it.values())]
    rate = {e: max(t["physics_steps_per_s"] for t in timings[e].values()) for e in agreeing}
    fastest = max(agreeing, key=rate.get) if agreeing else None
    if runio.device_name() == "cpu":
        # The GPU's speeds come from benchmarks/results/training.json: Warp is the faster there.
        return {"cpu": fastest, "gpu": "warp" if "warp" in agreeing else fastest}, iterations
    return {"cpu": None, "gpu": fastest}, iterations


def parse_args(argv=None):
    """(args, overrides), every argument checked (parser errors) before any work."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/results/engines.json")
    parser.add_argument("--noisy-reps", type=int, default=32, help="noisy episodes of the main anchor per engine")
    parser.add_argument("--seed", type=int, default=0, help="the noise draws")
    parser.add_argument("--engines", default="c,warp,jax", help="comma-separated subset of c,warp,jax (c required)")
    parser.add_argument("--cold-warp-cache", action="store_true", help="compile Warp's kernels into an empty cache")
    parser.add_argument("--preset", default="paper", help="the config whose env is checked")
    parser.add_argument("--set", action="append", nargs="+", default=[], metavar="KEY=VALUE",
                        help="config overrides, e.g. env.physics_dt=0.005")  # fmt: skip
    args = parser.parse_args(argv)
    engines = args.engines.split(",")
    if "c" not in engines or not set(engines) <= {"c", "warp", "jax"}:
        parser.error(f"--engines must name c and any of warp, jax; got {args.engines!r}")
    if args.noisy_reps < 2:
        parser.error(f"--noisy-reps must be >= 2, got {args.noisy_reps}")
    try:
        overrides = cli.parse_overrides(args.set)
        config.make_config(args.preset, overrides)
        for engine in set(engines) - {"c"}:
            config.make_config(args.preset, {**overrides, "env.impl": engine})
    except ValueError as err:
        parser.error(str(err))
    return args, overrides


def main(argv=None) -> dict:
    args, overrides = parse_args(argv)
    t_start = time.perf_counter()
    cfg = config.make_config(args.preset, overrides)
    if args.cold_warp_cache:
        import warp  # noqa: PLC0415

        cache = tempfile.TemporaryDirectory(prefix="warp-cache-")
        warp.config.kernel_cache_dir = cache.name
    anchors = kick_model.load_record()["anchors"]
    probe = env_for(cfg.env, "jax", ITERATIONS[0], 1, False)
    tables = kick_model.action_tables(anchors, probe.n_steps, probe.config.ctrl_dt)
    keys = rollout.repetition_keys(args.seed, len(anchors), args.noisy_reps)
    peaks = {"contacts": 0, "rows": 0}
    results, timings = {}, {}
    for it, r in c_engine(cfg.env, anchors, noise_draws(cfg.env, keys[MAIN]), peaks).items():
        results["c", it] = r
    print("c: done", flush=True)
    for engine in [e for e in args.engines.split(",") if e != "c"]:
        for it in ITERATIONS:
            r = results[engine, it] = mjx_engine(cfg.env, engine, it, tables, keys)
            timings.setdefault(engine, {})[str(it)] = r["timing"]
            print(f"{engine} {it}: anchors {np.round(r['anchors'], 3)} noisy {np.mean(r['noisy']):.3f} m", flush=True)
    agree = agreement(results)
    chosen, iterations = choose(agree, timings)
    payload = {
        "rows": table_rows(results),
        "chosen": chosen,
        "iterations": iterations,
        "rule": (
            f"an MJX engine agrees when every noise-free anchor rests within {TOLERANCE_M} m of C MuJoCo at the "
            f"same solver iterations; its iterations: the fewest of {list(ITERATIONS)} within {TOLERANCE_M} m of "
            f"C MuJoCo at {CONVERGED}; chosen: Warp on a GPU when it agrees, the faster agreeing one on this device"
        ),
        "agreement": agree,
        "noise_draws": "the env's reset draws, the same on every engine",
        "c_peak_per_episode": {"contacts": peaks["contacts"], "constraint_rows": peaks["rows"]},
        "timings": {
            "device": runio.device_name(),
            "note": "measured on this device; first call = compile + one run, compile_s = first less steady call; "
            "warp kernel cache " + ("cold (empty) at the first warp program" if args.cold_warp_cache else "as found"),
            "mjx": timings,
            "c_physics_steps_per_s": {str(it): results["c", it]["physics_steps_per_s"] for it in ITERATIONS},
        },
        # Each MJX engine's noisy env at the first iteration count (rows name their own count).
        "engine_envs": {
            e: kick_env.resolved(env_for(cfg.env, e, ITERATIONS[0], args.noisy_reps, True).config)
            for e in args.engines.split(",")
            if e != "c"
        },
    }
    record = {**runio.provenance(cfg.preset, time.perf_counter() - t_start, config.resolved_env(cfg)), **payload}
    runio.write_json(args.out, record)
    print(f"wrote {args.out}")
    return record


if __name__ == "__main__":
    main()
