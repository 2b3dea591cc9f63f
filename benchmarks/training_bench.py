"""Training throughput: the vmapped experts (all tasks, one program) and Brax's ppo.train on one
task, same device, same process. Times exclude compiling (each program runs once first).

    python benchmarks/training_bench.py --preset paper --out benchmarks/results/training.json
    python benchmarks/training_bench.py --preset tiny --out runs/bench/training.json   # smoke test
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # for `experiments` as a script

from bumps_jax import experts, kick_env, results  # noqa: E402
from experiments import compare_brax_ppo  # noqa: E402


def _timed(fn, *args):
    start = time.perf_counter()
    out = fn(*args)
    jax.block_until_ready(out)
    return out, time.perf_counter() - start


def bench_experts(cfg, programs) -> dict:
    """BC and one PPO chunk of all tasks, each timed on its second call."""
    n_tasks = len(cfg.tasks)
    rngs, targets = experts.task_rngs(cfg.seed, n_tasks), jnp.asarray(cfg.tasks, jnp.float32)
    (state, _), bc_first = _timed(programs.init, rngs, targets)
    _, bc_wall = _timed(programs.init, rngs, targets)
    _, chunk_first = _timed(programs.chunk, state, targets)
    _, chunk_wall = _timed(programs.chunk, state, targets)
    steps = n_tasks * cfg.updates_per_chunk * programs.trainer.steps_per_update
    n_chunks = programs.trainer.n_updates // cfg.updates_per_chunk
    return {
        "n_tasks": n_tasks,
        "experts_env_steps_per_s": steps / chunk_wall,
        "experts_chunk_wall_s": chunk_wall,
        "experts_chunk_compile_s": chunk_first - chunk_wall,
        # The whole budget at this rate (chunks x timed chunk); host work between chunks aside.
        "experts_wall_s": n_chunks * chunk_wall,
        "bc_steps_per_s": n_tasks * cfg.bc.steps / bc_wall,
        "bc_wall_s": bc_wall,
    }


def bench_brax(cfg, target: float) -> dict:
    """Brax's ppo.train on one task with the preset's batch; its own post-compile 'training/sps'."""
    env = kick_env.KickEnv(config_overrides={"tasks": (target,)})
    p = cfg.ppo
    steps_per_epoch = p.num_envs * env.n_steps
    sps = []
    from brax.training.agents.ppo import train as brax_ppo

    start = time.perf_counter()
    brax_ppo.train(
        environment=env,
        num_timesteps=3 * steps_per_epoch,
        num_envs=int(p.num_envs),
        episode_length=env.n_steps,
        unroll_length=env.n_steps,
        batch_size=int(p.num_envs // p.num_minibatches),
        num_minibatches=int(p.num_minibatches),
        num_updates_per_batch=int(p.num_epochs),
        learning_rate=float(p.learning_rate),
        discounting=float(p.discount),
        gae_lambda=float(p.gae_lambda),
        network_factory=compare_brax_ppo.brax_network_factory(p),
        num_evals=4,  # 3 training epochs, each reporting its own sps; the first one compiles
        run_evals=False,
        progress_fn=lambda step, metrics: sps.append(float(metrics.get("training/sps", float("nan")))),
    )
    return {
        "brax_ppo_env_steps_per_s": sps[-1],
        "brax_ppo_sps_per_epoch": sps,
        "brax_ppo_wall_s": time.perf_counter() - start,
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", choices=experts.PRESETS, default="paper")
    parser.add_argument("--out", default="runs/bench/training.json")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    cfg = experts.preset_config(args.preset)
    programs = experts.compile_programs(cfg)
    out = bench_experts(cfg, programs)
    out.update(bench_brax(cfg, float(cfg.tasks[len(cfg.tasks) // 2])))
    out["speedup_vs_brax"] = out["experts_env_steps_per_s"] / out["brax_ppo_env_steps_per_s"]
    out.update(results.provenance(args.preset, time.perf_counter() - start))
    print({k: v for k, v in out.items() if not isinstance(v, dict)})
    results.write_json(args.out, out)
    return out


if __name__ == "__main__":
    main()
