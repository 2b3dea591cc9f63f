"""Run by test_sharding.py as PROCESSES processes of JAX's multi-process runtime on this host
(`jax.distributed`, the coordinator on localhost), each with N_DEVICES host devices (XLA reads
the device count once, at start-up): trains tiny experts into the run directory argv[1], filters
a synthetic family and steps episodes through a small contact pool, every batch split over the
processes and each process's devices, and the first process prints what they produced as JSON.
The single-process, single-device side of the first two runs in the test's own process (the
filtering on conftest's program that test_filtering.py uses too)."""

import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import stand_ins
import tiny_experts

from bumps_jax import config
from bumps_jax.algo import filtering, rollout, sharding
from bumps_jax.pipeline.stages import experts
from bumps_jax.tasks.kick import env as kick_env

# Two processes of two devices and three tiny experts: one on each device, one of them a padded
# copy, so padding and unpadding run. On a CPU each device's share of a Warp physics step is a
# callback into Python, one at a time, so every device more adds its steps' cost (one process:
# 4 devices 124 s, 3 devices 93 s, 2 devices 72 s).
PROCESSES = 2
N_DEVICES = 2
TASKS = (8.0, 12.0, 16.0)


def experts_config():
    """The tiny experts' config (tiny_experts.py) with TASKS: both sides of the test train it."""
    return tiny_experts.pipeline_config(**{"experts.tasks": TASKS})


def quiet(*args, **kwargs):
    pass


def train(env, run_dir: Path) -> dict:
    cfg = experts_config()  # 3 tasks on 2 devices: one padded copy
    programs = experts.compile_programs(cfg, env, mesh=sharding.device_mesh(N_DEVICES, impl="warp"))
    # Stop after one chunk and resume: the sharded path must also restore checkpoints.
    experts.train(cfg, run_dir, programs, say=quiet, stop_after_chunks=1)
    out = experts.train(cfg, run_dir, programs, say=quiet)
    leaves = jax.tree.leaves(experts.expert_params(out["state"]))
    return {"params": [np.asarray(x).tolist() for x in leaves], "finished": out["finished"]}


# The 18 selection episodes in calls of 20 (5 on each of 4 devices, the last call padded): a
# call costs its 600 physics steps on every device, nearly whatever its batch.
EPISODES_PER_CALL = 20


def filter_synthetic(env, grid, params, n_devices: int) -> dict:
    """Selection of a synthetic family by `grid` split over `n_devices` (every device of every
    process), in calls of EPISODES_PER_CALL episodes."""
    tasks = np.array([10.0, 13.0, 15.0])
    contexts = filtering.candidate_contexts(tasks, [9.0, 11.5, 14.0])  # 6 candidates x 3 reps = 18 episodes
    sel_key, _ = filtering.noise_keys(0)
    block = EPISODES_PER_CALL // n_devices
    task_range = tuple(env.config.task_range)
    sel = filtering.filter_policy(
        grid,
        params,
        contexts,
        tasks,
        2.0,
        3,
        sel_key,
        task_range=task_range,
        block=block,
        multiple=n_devices,
        **filtering.scoring(env),
    )
    return {"chosen": sel.chosen.tolist(), "distance": sel.distance.tolist(), "scores": sel.scores.tolist()}


# Warp's contact pool for 4 episodes, and 16 episodes split over the 4 devices: 4 on each.
POOL_EPISODES = 4


def pool_per_device() -> dict:
    """One control step of POOL_EPISODES episodes on each device of each process, with a contact
    pool for POOL_EPISODES: whether any overflowed, and whether the program gathers a batch across
    devices (it must not: each device steps only its own share of the episodes)."""
    pool = {"warp_contacts": kick_env.CONTACTS_PER_EPISODE * POOL_EPISODES}
    env = kick_env.KickEnv(config.make_config("tiny").env, pool)

    def step(keys):
        def one(key):
            state = env.step(env.reset(key, 10.0), jnp.zeros(env.action_size))
            return state.info["overflow"], state.pipeline_state.qpos

        return jax.vmap(one)(keys)

    program = sharding.over_batch(step, sharding.device_mesh(N_DEVICES, impl="warp"), (True,))
    keys = jax.random.split(jax.random.key(0), PROCESSES * N_DEVICES * POOL_EPISODES)
    overflow, qpos = program(keys)
    return {
        "overflow": np.asarray(overflow).tolist(),
        "finite": bool(np.isfinite(np.asarray(qpos)).all()),
        "gathers": "all-gather" in program.lower(keys).compile().as_text(),
    }


def main() -> None:
    sharding.initialize_distributed()
    assert jax.process_count() == PROCESSES and len(jax.local_devices()) == N_DEVICES, jax.devices()
    env = kick_env.KickEnv(config.make_config("tiny").env)
    out = {"experts": train(env, Path(sys.argv[1]))}
    mesh = sharding.device_mesh(N_DEVICES, impl="warp")
    params = jax.tree.map(lambda a: a[None], stand_ins.synthetic_contextual_params())
    grid = rollout.grid_fn(env, stand_ins.contextual_apply, mesh)
    out["filter"] = filter_synthetic(env, grid, params, sharding.ways(mesh))
    out["pool"] = pool_per_device()
    if jax.process_index() == 0:
        json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
