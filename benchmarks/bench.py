"""`make bench`: every speed of the pipeline, measured side by side in one run on one device.

- raw MJX physics steps/s of our scene and env-steps/s of the kick task, at the experts' batch;
- aggregate PPO env-steps/s of all experts in one vmapped program vs Brax's `ppo.train` on one
  task (same env, same batch per task, same device);
- BC (meta-training) gradient steps/s of both meta-policies;
- filtering rollouts/s and the wall time of the high-sample-rate variant (1091 contexts).
With more than one device visible it also measures the experts and filtering on a mesh of one
device and on a mesh of all of them (`bumps_jax.sharding`) and writes the scaling record;
`--scale-workload K` runs those two on K times the preset's work (K copies of every expert,
each its own seed; K times the filtering repetitions), for a lab that outgrows one device.

Every time is a program's second call (its first compiles); compile times are reported apart.
Results are written after each section, so a run cut short keeps what it measured.

    python benchmarks/bench.py --preset paper                 # GPU: benchmarks/results/*.json
    python benchmarks/bench.py --preset tiny --out-dir runs/bench   # CPU smoke test
    python benchmarks/bench.py --only scaling --scale-workload 2    # several GPUs, twice the work
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # `experiments`, `benchmarks` as scripts

from benchmarks import scene_bench  # noqa: E402
from bumps_jax import evaluate, experts, filtering, kick_env, meta, results, sharding, synthetic_experts  # noqa: E402

# What each preset measures: the paper's sizes on a GPU; CPU-sized for a smoke test.
SIZES = {
    "paper": {"bench_updates": 2, "brax_epochs": 4, "bc_chunk": 1000, "filter_step": 0.01, "filter_reps": 10},
    "tiny": {"bench_updates": 1, "brax_epochs": 2, "bc_chunk": 20, "filter_step": 2.0, "filter_reps": 1},
}


UPDATES_PER_BRAX_EPOCH = 10


def timed(fn, *args):
    """(output, first-call seconds, second-call seconds)."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, first, time.perf_counter() - t0


def bench_scene(batch: int) -> dict:
    env = kick_env.KickEnv()
    return {
        "scene_batch": batch,
        "physics_steps_per_s": scene_bench.physics_rate(env.mj_model, batch),
        "env_steps_per_s": scene_bench.env_rate(env, batch),
    }


def expert_config(preset: str, updates: int, workload: int = 1):
    """The preset's experts with the budget cut to `updates` updates (one chunk); with
    `workload` K, every task K times (K experts per task, each on its own seed)."""
    cfg = experts.preset_config(preset)
    steps = cfg.ppo.num_envs * kick_env.KickEnv().n_steps * updates
    overrides = {"ppo.total_env_steps": steps, "updates_per_chunk": updates, "tasks": tuple(cfg.tasks) * workload}
    return experts.make_config(cfg, overrides)


def bench_experts(preset: str, updates: int, mesh, method: str = "jit", workload: int = 1) -> dict:
    """One chunk of PPO updates of every task at once; aggregate env-steps/s over real tasks."""
    cfg = expert_config(preset, updates, workload)
    programs = experts.compile_programs(cfg, mesh=mesh, method=method)
    n = len(cfg.tasks)
    kicks, _ = experts.starting_kicks(experts.make_config(cfg, {"tune.generations": 0}), verbose=False)
    state, _ = experts.run_init(programs, experts.task_rngs(cfg.seed, n), cfg.tasks, kicks)
    _, first, wall = timed(lambda s: experts.run_chunk(programs, s, cfg.tasks), state)
    steps = n * updates * programs.trainer.steps_per_update
    full = experts.preset_config(preset).ppo.total_env_steps * n
    return {
        "n_tasks": n,
        "workload": workload,
        "n_devices": mesh.size,
        "experts_env_steps_per_s": steps / wall,
        "experts_chunk_compile_s": first - wall,
        # The preset's whole PPO budget at this rate (BC, tuning and host work between chunks aside).
        "experts_wall_s": full / (steps / wall),
    }


def bench_brax(preset: str, epochs: int) -> dict:
    """Brax's ppo.train on one task with the preset's per-task batch; its own post-compile sps."""
    from experiments import compare_brax_ppo  # noqa: PLC0415 (installs the device_put_replicated shim)

    cfg = experts.preset_config(preset)
    target = float(cfg.tasks[len(cfg.tasks) // 2])
    env = kick_env.KickEnv(config_overrides={"tasks": (target,)})
    p = cfg.ppo
    sps = []
    start = time.perf_counter()
    compare_brax_ppo.brax_ppo.train(
        **compare_brax_ppo.brax_settings(p, env),
        # Ten of our updates' worth of env steps per Brax training epoch, so that each epoch's
        # own timing is long enough to mean something.
        num_timesteps=epochs * UPDATES_PER_BRAX_EPOCH * p.num_envs * env.n_steps,
        num_evals=epochs + 1,  # one report per training epoch; the first includes compiling
        run_evals=False,
        max_devices_per_host=1,  # one GPU, as our experts in this measurement
        progress_fn=lambda step, metrics: sps.append(float(metrics.get("training/sps", float("nan")))),
    )
    return {"brax_ppo_env_steps_per_s": sps[-1], "brax_ppo_sps_per_epoch": sps, "brax_task_m": target,
            "brax_ppo_wall_s": time.perf_counter() - start}  # fmt: skip


def bench_bc(preset: str, chunk: int) -> dict:
    """Gradient steps/s of each meta-policy's BC loop on a dataset of the experts' size, timed
    over `chunk` epochs."""
    cfg = meta.make_config(preset, {"train.chunk": chunk})
    n_rows = len(experts.preset_config(preset).tasks) * kick_env.KickEnv().n_steps
    rng = np.random.default_rng(0)
    obs = jnp.asarray(rng.uniform(size=(n_rows, 2)), jnp.float32)
    actions = jnp.asarray(rng.normal(size=(n_rows, 22)), jnp.float32)
    keys = meta.seed_keys(cfg.train)
    epoch_steps = meta.steps_per_epoch(cfg.train, n_rows)
    out, total = {"bc_steps_per_epoch": epoch_steps}, 0.0
    for name, (depth, width) in cfg.nets.items():
        init, step_chunk = meta.make_trainer(meta.MetaPolicy(depth, width), cfg.train, n_rows)
        state = init(keys)
        _, first, wall = timed(lambda s, f=step_chunk: f(s, obs, actions, keys), state)
        rate = chunk * epoch_steps * cfg.train.n_seeds / wall
        out[f"bc_steps_per_s_{name}"] = rate
        total += cfg.train.epochs * epoch_steps / rate
    out["bc_steps_per_s"] = min(v for k, v in out.items() if k.startswith("bc_steps_per_s_"))
    # Both nets' full schedules (train.epochs passes each) at the measured rates.
    out["bc_wall_s"] = total
    return out


def bench_filter(preset: str, step: float, reps: int, mesh, method: str = "jit", workload: int = 1) -> dict:
    """The high-sample-rate variant end to end (selection over the fine context grid, then the
    fresh evaluation of each test task), with the contextual stand-in policy: rollouts/s."""
    cfg = filtering.make_config(preset)
    reps *= workload
    env = kick_env.KickEnv()
    params = jax.tree.map(lambda a: a[None], synthetic_experts.synthetic_contextual_params())
    grid = evaluate.grid_fn(env, synthetic_experts.contextual_apply, mesh, method)
    tasks = np.asarray(cfg.tasks)
    contexts = filtering.candidate_contexts(tasks, filtering.context_grid(*cfg.context_range, step))
    sel_key, eval_key = filtering.noise_keys(0)
    ball = filtering.ball_start_xy(env)

    def run(_):
        sel = filtering.filter_policy(
            grid, params, contexts, tasks, cfg.width, reps, sel_key, ball, cfg.block, mesh.size
        )
        chosen = sel.contexts[sel.chosen]
        return filtering.evaluate_chosen(
            grid, params, chosen, tasks, cfg.eval_repetitions, eval_key, cfg.block, mesh.size
        )

    _, first, wall = timed(run, None)
    rollouts = len(contexts) * reps + len(tasks) * cfg.eval_repetitions
    return {
        "n_devices": mesh.size,
        "workload": workload,
        "filter_contexts": len(contexts),
        "filter_rollouts": rollouts,
        "filter_rollouts_per_s": rollouts / wall,
        "filter_high_sample_wall_s": wall,
        "filter_compile_s": first - wall,
    }


def reproduce_record(pipeline_json: Path, device: str) -> dict:
    """The committed full `reproduce`'s wall time, with the device it ran on, if that is `device`
    (it is not measured here: the pipeline records it). Empty otherwise: a bench record on
    another device (e.g. a CPU smoke test) would set the GPU's pipeline time beside its own."""
    if not pipeline_json.exists():
        return {}
    pipeline = json.loads(pipeline_json.read_text())
    if pipeline["device"] != device:
        return {}
    return {
        "reproduce_wall_s": pipeline["total_wall_s"],
        "reproduce_stages_s": pipeline["stages"],
        "reproduce_device": pipeline["device"],
        "reproduce_date": pipeline["date"],
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", choices=tuple(SIZES), default="paper")
    parser.add_argument("--out-dir", default="benchmarks/results")
    parser.add_argument(
        "--skip", nargs="*", default=(), choices=("scene", "experts", "brax", "bc", "filter", "scaling")
    )
    parser.add_argument("--only", nargs="*", default=(), choices=("scaling",), help="run only the scale-out sections")
    parser.add_argument("--sharding", choices=sharding.METHODS, default="jit", help="how batches are split")
    parser.add_argument(
        "--scale-workload",
        type=int,
        default=1,
        help="the scale-out sections run K times the preset's work, on one device and on all",
    )
    args = parser.parse_args(argv)
    size = SIZES[args.preset]
    out_dir = Path(args.out_dir)
    start = time.perf_counter()
    one = sharding.device_mesh(1)
    n_dev = len(jax.devices())
    training: dict = {"n_devices_used": 1, "devices_visible": n_dev, "sharding": args.sharding}
    pipeline_json = Path(__file__).resolve().parent.parent / "results" / "pipeline.json"
    training.update(reproduce_record(pipeline_json, results.device_name()))
    scaling: dict = {"devices": n_dev, "sharding": args.sharding}
    physics_dt = kick_env.KickEnv().physics_dt  # every section's env is the default one

    def save(section: str) -> None:
        print(f"[bench] {section} done at {time.perf_counter() - start:.0f} s", flush=True)
        prov = results.provenance(args.preset, time.perf_counter() - start, physics_dt_s=physics_dt)
        if "scaling" not in args.only:  # a scale-out-only run leaves the one-device record alone
            results.write_json(out_dir / "training.json", {**training, **prov})
        if any(k.endswith("_speedup") for k in scaling):  # at least one ratio measured
            results.write_json(out_dir / "scaling.json", {**scaling, **prov})

    cfg = experts.preset_config(args.preset)
    batch = len(cfg.tasks) * cfg.ppo.num_envs
    scale_out = n_dev > 1 and "scaling" not in args.skip
    every = sharding.device_mesh() if scale_out else one

    if args.scale_workload < 1:
        parser.error(f"--scale-workload must be a positive integer, got {args.scale_workload}")
    k = args.scale_workload
    scaling["workload"] = k

    def experts_on(mesh, workload=1):
        return lambda: bench_experts(args.preset, size["bench_updates"], mesh, args.sharding, workload)

    def filter_on(mesh, workload=1):
        return lambda: bench_filter(
            args.preset, size["filter_step"], size["filter_reps"], mesh, args.sharding, workload
        )

    # Each scale-out measurement follows its one-device run (a run cut short keeps whole
    # ratios); the experts' one comes last, as the program most likely to fail to compile.
    # A scale-out section at the preset's own workload reuses the one-device value just measured;
    # at a larger workload it measures one device itself, then all.
    sections = [
        ("experts", experts_on(one), "training"),
        ("filter", filter_on(one), "training"),
        ("scaling-filter", (filter_on(one, k), filter_on(every, k)), "filter_rollouts_per_s"),
        ("brax", lambda: bench_brax(args.preset, size["brax_epochs"]), "training"),
        ("scene", lambda: bench_scene(batch), "training"),
        ("bc", lambda: bench_bc(args.preset, size["bc_chunk"]), "training"),
        ("scaling-experts", (experts_on(one, k), experts_on(every, k)), "experts_env_steps_per_s"),
    ]
    for name, fn, into in sections:
        source = name.removeprefix("scaling-")
        if name in args.skip or (name == source and "scaling" in args.only):
            continue
        if name != source and (not scale_out or (k == 1 and source in args.skip)):
            continue
        if into == "training":
            part = fn()
            part.pop("n_devices", None)
            training.update(part)
        else:  # the same measurement on one device and on every device
            alone = training[into] if k == 1 and into in training else fn[0]()[into]
            part = fn[1]()
            scaling[into] = {"1": alone, str(n_dev): part[into]}  # {n_devices: value}
            scaling[into.replace("_per_s", "_speedup")] = part[into] / alone
            scaling[f"{source}_workload_detail"] = {kk: v for kk, v in part.items() if not isinstance(v, list)}
        print({kk: v for kk, v in part.items() if not isinstance(v, list)}, flush=True)
        if "brax_ppo_env_steps_per_s" in training and "experts_env_steps_per_s" in training:
            training["experts_vs_brax"] = training["experts_env_steps_per_s"] / training["brax_ppo_env_steps_per_s"]
        if "env_steps_per_s" in training and "experts_env_steps_per_s" in training:
            training["experts_vs_env_rate"] = training["experts_env_steps_per_s"] / training["env_steps_per_s"]
        save(name if into == "training" else f"scaling {into}")
    return training


if __name__ == "__main__":
    main()
