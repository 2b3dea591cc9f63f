"""`make bench`: every speed of the pipeline, measured side by side in one run on one device.

For each physics backend (`--backends`, default MJX-JAX and MuJoCo Warp), at the env's step:
- raw physics steps/s of our scene and env-steps/s of the kick task, at the experts' batch;
- aggregate PPO env-steps/s of all experts in one vmapped program;
- filtering rollouts/s and the wall time of the high-sample-rate variant (1091 contexts).
On the config's own backend (`env.impl`) only:
- a generation of the experts' tuning (every task's CMA-ES at once) as one run plays it, and
  the `tune.restarts` runs' searches in one batch instead (its Warp pool that many times larger);
- the experts again with GAE as a device loop of one iteration per step (Brax's way) against
  the unrolled GAE of the config (`experts.ppo.unroll_gae`);
- Brax's `ppo.train` on one task (one expert's batch) and at the experts' total batch;
- BC (meta-training) gradient steps/s of both meta-policies, each in its own program, both in
  one, and both stacked in one (every layer of both nets one batched matmul).
Several devices: `benchmarks/scaling.py` measures the same work on one GPU and on several.

Every time is a program's second call (its first compiles); compile times are reported apart.
Wall times of whole stages computed from a measured rate are listed under `projections`.
Results are written after each section, so a run cut short keeps what it measured.

    python -m benchmarks.bench --preset paper                        # GPU: benchmarks/results/training.json
    python -m benchmarks.bench --skip scene experts brax bc filter tuning --record experts_gae  # own record
    python -m benchmarks.bench --preset tiny --out-dir runs/bench    # CPU smoke test
"""

from __future__ import annotations

import argparse
import copy
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import scene_bench
from bumps_jax import cli, config, runio
from bumps_jax.algo import bc, filtering, rollout, sharding
from bumps_jax.pipeline import expert_programs
from bumps_jax.tasks.kick import cmaes, starting_kicks
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model
from bumps_jax.tasks.kick import scoring as kick_scoring
from experiments import brax_compat

# What each preset measures: the paper's sizes on a GPU; CPU-sized for a smoke test.
SIZES = {
    "paper": {
        "bench_updates": 2,
        "brax_epochs": 4,
        "bc_chunk": 1000,
        "filter_step": 0.01,
        "filter_reps": 10,
        "tuning_generations": 5,
    },
    "tiny": {
        "bench_updates": 1,
        "brax_epochs": 2,
        "bc_chunk": 20,
        "filter_step": 2.0,
        "filter_reps": 1,
        "tuning_generations": 1,
    },
}
SECTIONS = ("scene", "experts", "gae", "brax", "bc", "filter", "tuning")  # what --skip can leave out
# Ten of our updates' worth of env steps per Brax training epoch, so that each epoch's own
# timing is long enough to mean something.
UPDATES_PER_BRAX_EPOCH = 10


class Work(NamedTuple):
    """A measured piece of work: `run()` does it once (its first call compiles)."""

    run: Callable[[], Any]
    amount: int  # what one call does: env steps (experts) or rollouts (filtering)
    detail: dict  # its sizes, for the record


def timed(fn, *args):
    """(output, first-call seconds, second-call seconds)."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, first, time.perf_counter() - t0


def bench_scene(cfg, batch: int) -> dict:
    """Physics steps/s at `batch` (the experts' episodes) and at 8192, env steps/s at `batch`."""
    env = kick_env.KickEnv(cfg.env)
    big = kick_env.KickEnv(derived(cfg, {"env.warp_contacts": kick_env.CONTACTS_PER_EPISODE * 8192}).env)
    return {
        "scene_batch": batch,
        "physics_steps_per_s": scene_bench.physics_rate(env.mj_model, batch, env_cfg=env.config),
        "physics_steps_per_s_8192": scene_bench.physics_rate(big.mj_model, 8192, env_cfg=big.config),
        "env_steps_per_s": scene_bench.env_rate(env, batch),
    }


def derived(cfg, overrides: dict):
    """A copy of the pipeline config `cfg` with dotted `overrides` set, checked as `make_config` checks."""
    out = copy.deepcopy(cfg)
    for key, value in overrides.items():
        config.set_leaf(out, key, value)
    config.validate(out)
    return out


def expert_config(cfg, updates: int, workload: int = 1):
    """`cfg` with its experts' budget cut to `updates` updates (one chunk), starting from the
    prior's blended kicks as they are; with `workload` K, every task K times (each its own seed)
    and Warp's contact pool K times the preset's, so that every episode keeps its contact slots."""
    n_steps = kick_env.KickEnv(cfg.env).n_steps
    return derived(cfg, {
        "env.warp_contacts": cfg.env.warp_contacts * workload,
        "experts.ppo.total_env_steps": cfg.experts.ppo.num_envs * n_steps * updates,
        "experts.updates_per_chunk": updates,
        "experts.tasks": tuple(cfg.experts.tasks) * workload,
        "experts.tune.generations": 0,
        "experts.tune.anchor_starts": False,
    })  # fmt: skip


def experts_work(cfg, updates: int, mesh, workload: int = 1, seed: int | None = None):
    """The work of one chunk of the experts (amount: env steps): `run()` trains `updates` PPO
    updates of every task at once (K = `workload` copies of each, seeds from `seed`, default the
    config's); the same state goes in at every call, so each call does the same work."""
    cut = expert_config(cfg, updates, workload)
    programs = expert_programs.compile_programs(cut, mesh=mesh)
    tasks = np.asarray(cut.experts.tasks, np.float32)
    n = len(tasks)
    record = kick_model.load_record(kick_model.ASSET)  # the starting kicks are a workload here, whatever the env
    kicks, _ = starting_kicks.starting_kicks(cut, record)
    seed = cut.experts.seed if seed is None else seed
    state, _ = expert_programs.run_init(programs, expert_programs.task_rngs(seed, n), tasks, kicks)
    run = lambda: expert_programs.run_chunk(programs, state, tasks)  # noqa: E731
    return Work(run, n * updates * programs.trainer.steps_per_update, {"n_tasks": n})


def bench_experts(cfg, updates: int, mesh, workload: int = 1) -> dict:
    """One chunk of PPO updates of every task at once; aggregate env-steps/s over real tasks."""
    run, steps, detail = experts_work(cfg, updates, mesh, workload)
    _, first, wall = timed(run)
    n = detail["n_tasks"]
    full = cfg.experts.ppo.total_env_steps * n
    return {
        "n_tasks": n,
        "workload": workload,
        "n_devices": mesh.size,
        "experts_env_steps_per_s": steps / wall,
        "experts_chunk_compile_s": first - wall,
        # The preset's whole PPO budget at this rate (BC, tuning and host work between chunks aside).
        "experts_ppo_projected_s": full / (steps / wall),
    }


def tuning_projection(cfg, generation_s: float, batched_generation_s: float, runs: int) -> dict:
    """The tuning's `tune.generations` for `runs` runs, one run after another at `generation_s` a
    generation against all in one batch at `batched_generation_s` (polish and fresh scoring aside)."""
    generations = int(cfg.experts.tune.generations)
    return {
        "tuning_runs": runs,
        "tuning_projected_s": runs * generations * generation_s,
        "tuning_batched_projected_s": generations * batched_generation_s,
        "tuning_batched_vs_sequential": runs * generation_s / batched_generation_s,
    }


def bench_tuning(cfg, mesh, generations: int) -> dict:
    """Seconds per generation of the experts' tuning (the preset's population, repetitions and
    leashes; every task from the prior's kick): the tasks of one run, then the `tune.restarts` runs'
    tasks in one batch (at least two runs), each chain leashed within its own run."""
    e = cfg.experts
    runs = max(int(e.tune.restarts), 2)
    targets = np.asarray(e.tasks, np.float32)
    starts = np.tile(np.asarray(kick_model.load_record(kick_model.ASSET)["params"], np.float32), (len(targets), 1))
    fitness_json = kick_scoring.fitness_json_of(cfg.prior.fitness)
    leash, centre_fn = cmaes.tuning_leash(targets, float(e.tune.neighbour_leash))
    out = {}
    for label, k in (("", 1), ("_batched", runs)):
        env = kick_env.KickEnv(derived(cfg, {"env.warp_contacts": cfg.env.warp_contacts * k}).env)
        search = cmaes.kick_search(env, mesh, int(e.tune.population_size), int(e.tune.repetitions),
                                   float(e.tune.sigma_init), fitness_json)  # fmt: skip
        x0 = np.tile(starts, (k, 1))

        def run(search=search, x0=x0, k=k):
            seeds = list(range(k))  # each run its own key, as the tuning batches them
            return cmaes.run_search(search, x0, np.tile(targets, k), np.ones_like(x0, bool), generations, seeds,
                                    say=lambda *a, **kw: None, leash=leash,
                                    centre_fn=cmaes.per_run(centre_fn, k, len(targets)))  # fmt: skip

        _, first, wall = timed(run)
        out[f"tuning_generation_s{label}"] = wall / generations
        out[f"tuning_compile_s{label}"] = first - wall
        out[f"tuning_episodes_per_call{label}"] = k * len(targets) * e.tune.population_size * e.tune.repetitions
    return out | tuning_projection(cfg, out["tuning_generation_s"], out["tuning_generation_s_batched"], runs)


def bench_brax(cfg, epochs: int, all_tasks: bool = False) -> dict:
    """Brax's ppo.train on one task with one expert's batch, or (`all_tasks`) on every expert's
    task at once with the experts' total batch; its own post-compile sps. Keys get the suffix
    `_total_batch` for the second."""
    tasks = tuple(cfg.experts.tasks) if all_tasks else (float(cfg.experts.tasks[len(cfg.experts.tasks) // 2]),)
    env = kick_env.KickEnv(derived(cfg, {"env.tasks": tasks}).env)
    p = copy.deepcopy(cfg.experts.ppo)
    p.num_envs = cfg.experts.ppo.num_envs * len(tasks)
    sps = []
    start = time.perf_counter()
    brax_compat.train(
        p,
        env,
        num_timesteps=epochs * UPDATES_PER_BRAX_EPOCH * p.num_envs * env.n_steps,
        num_evals=epochs + 1,  # one report per training epoch; the first includes compiling
        run_evals=False,
        max_devices_per_host=1,  # one device, as our experts in this measurement
        progress_fn=lambda step, metrics: sps.append(float(metrics.get("training/sps", float("nan")))),
    )
    suffix = "_total_batch" if all_tasks else ""
    out = {"brax_ppo_env_steps_per_s": sps[-1], "brax_ppo_sps_per_epoch": sps, "brax_ppo_num_envs": p.num_envs,
           "brax_ppo_wall_s": time.perf_counter() - start}  # fmt: skip
    out = {k + suffix: v for k, v in out.items()}
    out["brax_tasks_m" + suffix] = list(tasks)
    return out


def bc_inputs(cfg, chunk: int) -> tuple:
    """(meta.train with `chunk` epochs per chunk, the meta nets {name: MetaPolicy}, random obs and
    actions as many as the experts' dataset has pairs, the seed keys): what a BC bench trains on."""
    n_rows = len(cfg.experts.tasks) * kick_env.KickEnv(cfg.env).n_steps
    train_cfg = derived(cfg, {"meta.train.chunk": chunk}).meta.train
    rng = np.random.default_rng(0)
    obs = jnp.asarray(rng.uniform(size=(n_rows, 2)), jnp.float32)
    actions = jnp.asarray(rng.normal(size=(n_rows, 22)), jnp.float32)
    models = {name: bc.MetaPolicy(depth, width) for name, (depth, width) in cfg.meta.nets.items()}
    return train_cfg, models, obs, actions, bc.seed_keys(train_cfg)


def bench_bc(cfg, chunk: int) -> dict:
    """Gradient steps/s of the meta stage's BC loop (`bc.make_trainer`: both nets stacked in one
    program) on a dataset of the experts' size, timed over `chunk` epochs; both nets' full
    schedules projected. Its keys keep the name the loop was measured under before it became
    the only one (`bc_stacked_batched_*`), so that older records compare."""
    train_cfg, models, obs, actions, keys = bc_inputs(cfg, chunk)
    n_rows = len(obs)
    epoch_steps = bc.steps_per_epoch(train_cfg, n_rows)
    steps = chunk * epoch_steps * train_cfg.n_seeds  # per net
    out: dict = {"bc_steps_per_epoch": epoch_steps, "bc_unroll": bc.steps_unrolled(epoch_steps)}
    init, step_chunk = bc.make_trainer(models, train_cfg, n_rows)
    (_, losses), first, wall = timed(lambda s, f=step_chunk: f(s, obs, actions, keys), init(keys))
    key = "bc_stacked_batched"
    out[f"{key}_steps_per_s"] = steps / wall  # gradient steps of each net per second, both nets at once
    out[f"{key}_compile_s"] = first - wall
    out[f"{key}_last_loss"] = {name: float(np.asarray(v)[:, -1].mean()) for name, v in losses.items()}
    out[f"{key}_wall_s"] = train_cfg.epochs * epoch_steps / (steps / wall)
    return out


class KickFamily(NamedTuple):
    """A contextual policy of known cost and real kicks: the committed prior's family at the
    strength its calibration gives for the asked distance. Leaves may carry a stacking axis."""

    anchors: jax.Array  # (3, 14) short, main, long
    calibration: jax.Array  # (n, 2) rows (strength, distance m)


def kick_family_policy(env: kick_env.KickEnv):
    """apply_fn(KickFamily, obs (2,)) -> action (22,): the blended kick for the context obs[1] asks."""
    lo, hi = env.config.task_range

    def apply(params: KickFamily, obs):
        kick = kick_model.kick_for(params.anchors, params.calibration, lo + obs[1] * (hi - lo))
        return rollout.table_policy(kick_model.keyframes_to_actions(kick, env.n_steps, env.config.ctrl_dt), obs)

    return apply


def filter_work(cfg, step: float, reps: int, mesh, workload: int = 1, seed: int = 0):
    """The work of the high-sample-rate variant (amount: rollouts): `run()` is it end to end (selection
    over the fine context grid with `reps` x `workload` rollouts per context, then the fresh
    evaluation of each test task), with the prior's kick family as the contextual policy; `seed`
    picks its noise."""
    f = cfg.filter
    reps *= workload
    env = kick_env.KickEnv(cfg.env)
    record = kick_model.load_record(kick_model.ASSET)  # a workload here, whatever the env
    family = KickFamily(jnp.asarray(record["anchors"]), jnp.asarray(kick_model.calibration(record)))
    params = jax.tree.map(lambda a: a[None], family)
    grid = rollout.grid_fn(env, kick_family_policy(env), mesh)
    tasks = np.asarray(f.tasks)
    contexts = filtering.candidate_contexts(tasks, filtering.context_grid(*f.context_range, step))
    sel_key, eval_key = filtering.noise_keys(seed)

    def run():
        sel = filtering.filter_policy(grid, params, contexts, tasks, f.width, reps, sel_key,
                                      task_range=cfg.env.task_range, block=f.block, multiple=sharding.ways(mesh),
                                      **filtering.scoring(env))  # fmt: skip
        chosen = sel.contexts[sel.chosen]
        ways = sharding.ways(mesh)
        return filtering.evaluate_chosen(grid, params, chosen, tasks, f.eval_repetitions, eval_key, f.block, ways)

    return Work(run, len(contexts) * reps + len(tasks) * f.eval_repetitions, {"filter_contexts": len(contexts)})


def bench_filter(cfg, step: float, reps: int, mesh, workload: int = 1) -> dict:
    """The high-sample-rate variant end to end (`filter_work`): rollouts/s."""
    run, rollouts, detail = filter_work(cfg, step, reps, mesh, workload)
    _, first, wall = timed(run)
    return {
        "n_devices": mesh.size,
        "workload": workload,
        **detail,
        "filter_rollouts": rollouts,
        "filter_rollouts_per_s": rollouts / wall,
        "filter_high_sample_wall_s": wall,
        "filter_compile_s": first - wall,
    }


def parse_args(argv=None):
    """(args, pipeline config), every argument checked (parser errors) before any work."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", choices=tuple(SIZES), default="paper")
    parser.add_argument("--set", action="append", nargs="+", default=[], metavar="KEY=VALUE",
                        help="config overrides, e.g. env.physics_dt=0.005")  # fmt: skip
    parser.add_argument("--out-dir", default="benchmarks/results")
    parser.add_argument("--record", default="training",
                        help="the record's file name in --out-dir, without .json: a bench of some sections "
                             "(--skip) keeps its own record, e.g. --record experts_gae")  # fmt: skip
    parser.add_argument("--skip", nargs="*", default=(), choices=SECTIONS)
    parser.add_argument("--backends", nargs="+", default=list(kick_env.IMPLS), choices=kick_env.IMPLS,
                        help="physics backends measured side by side (the config's own is measured last)")  # fmt: skip
    args = parser.parse_args(argv)
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", args.record) or args.record.endswith(".json"):
        parser.error(f"--record {args.record!r}: a file name without folders or .json (letters, digits, '_', '.', '-')")
    try:
        cfg = config.make_config(args.preset, cli.parse_overrides(args.set))
        runio.check_writable(args.out_dir)
    except ValueError as err:
        parser.error(str(err))
    return args, cfg


def sections(cfg, size: dict, backends, one) -> list:
    """(name, measurement, where its result goes) in the order they run: a backend's sections
    go into `backends.<impl>`, the others into the record's top level. The config's own backend
    (`env.impl`) runs last, with the GAE variants, Brax and BC."""
    own = cfg.env.impl
    batch = len(cfg.experts.tasks) * cfg.experts.ppo.num_envs
    out = []
    for impl in sorted(backends, key=lambda b: b == own):
        b_cfg = derived(cfg, {"env.impl": impl})
        out += [
            ("experts", lambda c=b_cfg: bench_experts(c, size["bench_updates"], one), impl),
            ("filter", lambda c=b_cfg: bench_filter(c, size["filter_step"], size["filter_reps"], one), impl),
            ("scene", lambda c=b_cfg: bench_scene(c, batch), impl),
        ]

    def experts_gae(unroll: bool):
        """The experts' rate with GAE unrolled or as a loop, keys suffixed `_gae_unrolled` / `_gae_loop`."""
        part = bench_experts(derived(cfg, {"experts.ppo.unroll_gae": unroll}), size["bench_updates"], one)
        suffix = "_gae_unrolled" if unroll else "_gae_loop"
        return {f"{key}{suffix}": value for key, value in part.items() if key.startswith("experts_")}

    return out + [
        ("tuning", lambda: bench_tuning(cfg, one, size["tuning_generations"]), None),
        ("gae", lambda: experts_gae(False), None),
        ("gae", lambda: experts_gae(True), None),
        ("brax", lambda: bench_brax(cfg, size["brax_epochs"]), None),
        ("brax", lambda: bench_brax(cfg, size["brax_epochs"], all_tasks=True), None),
        ("bc", lambda: bench_bc(cfg, size["bc_chunk"]), None),
    ]


def ratios(training: dict, own: str) -> None:
    """The side-by-side ratios of what `training` holds so far (in place)."""
    per = training["backends"]
    for key in ("experts_env_steps_per_s", "physics_steps_per_s", "env_steps_per_s", "filter_rollouts_per_s"):
        if key in per.get("jax", {}) and key in per.get("warp", {}):
            training[f"{key.removesuffix('_per_s')}_warp_vs_jax"] = per["warp"][key] / per["jax"][key]
    mine = per.get(own, {})
    if "experts_env_steps_per_s_gae_loop" in training and "experts_env_steps_per_s_gae_unrolled" in training:
        training["experts_gae_unrolled_vs_loop"] = (
            training["experts_env_steps_per_s_gae_unrolled"] / training["experts_env_steps_per_s_gae_loop"]
        )
    for suffix in ("", "_total_batch"):
        brax = training.get(f"brax_ppo_env_steps_per_s{suffix}")
        if brax and "experts_env_steps_per_s" in mine:
            training[f"experts_vs_brax{suffix}"] = mine["experts_env_steps_per_s"] / brax


def main(argv=None) -> dict:
    args, cfg = parse_args(argv)
    out_dir = Path(args.out_dir)
    start = time.perf_counter()
    one = sharding.device_mesh(1)
    own = cfg.env.impl
    # Every program splits its batch with `jax.jit` over a mesh (`sharding.over_batch`), here of one device.
    training: dict = {"n_devices_used": 1, "devices_visible": len(jax.devices()), "sharding": "jit", "backend": own,
                      "backends": {}}  # fmt: skip
    training["projections"] = [
        "experts_ppo_projected_s", "experts_ppo_projected_s_gae_loop", "experts_ppo_projected_s_gae_unrolled",
        "bc_wall_s", "bc_joint_wall_s", "bc_stacked_wall_s", "bc_stacked_batched_wall_s",
        "tuning_projected_s", "tuning_batched_projected_s",
    ]  # fmt: skip
    for name, fn, into in sections(cfg, SIZES[args.preset], args.backends, one):
        if name in args.skip:
            continue
        part = fn()
        part.pop("n_devices", None)
        (training["backends"].setdefault(into, {}) if into else training).update(part)
        print({k: v for k, v in part.items() if not isinstance(v, list)}, flush=True)
        ratios(training, own)
        print(f"[bench] {name}{f' ({into})' if into else ''} done at {time.perf_counter() - start:.0f} s", flush=True)
        prov = runio.provenance(cfg.preset, time.perf_counter() - start, config.resolved_env(cfg))
        # Written after each section: a run cut short keeps what it measured.
        runio.write_json(out_dir / f"{args.record}.json", {**training, **prov})
    return training


if __name__ == "__main__":
    main()
