"""Run by test_sharding.py as PROCESSES processes of JAX's multi-process runtime on this host
(`jax.distributed`, the coordinator on localhost), each with N_DEVICES host devices (XLA reads
the device count once, at start-up): trains tiny experts into the run directory argv[1], filters
a stand-in contextual policy and steps kick episodes through a small contact pool, every batch
split over the processes and each process's devices, and the first process prints what they
produced as JSON. The single-process, single-device side of the first two runs in the test's
own process.

The experts and the filtering run on PointGoal (a point mass, nothing collides): what is tested
is how batches split, pad, gather and resume, which no task changes, and its programs compile
and run in seconds where the kick's Warp physics on a CPU took minutes (on a CPU each device's
share of a Warp physics step is a callback into Python, one at a time). Its Warp backend runs
them, as the kick's does, so the experts' and the filtering's physics are split over devices
as Warp's. The contact pool is the kick's: it is what a device stepping other devices' episodes
would overflow.
"""

import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax import config
from bumps_jax.algo import bc, filtering, rollout, sharding
from bumps_jax.pipeline import expert_programs
from bumps_jax.pipeline.stages import experts
from bumps_jax.tasks import registry
from bumps_jax.tasks.kick import env as kick_env

# Two processes of two devices and three tiny experts: one on each device, one of them a padded
# copy, so padding and unpadding run.
PROCESSES = 2
N_DEVICES = 2
TASKS = ((0.7, 0.0), (0.0, 0.7), (-0.7, 0.0))  # goals (x, y) m

# PointGoal's tiny experts on Warp: 4 whole episodes per update, 2 chunks of 1 update. An episode
# is 10 control steps of one physics step each (Warp's cost on a CPU is per physics call).
N_STEPS = 10
EXPERTS = {
    "task": "point_goal",
    "env.impl": "warp",
    "env.episode_steps": N_STEPS,
    "env.physics_dt": 0.1,
    "experts.tasks": TASKS,
    "experts.updates_per_chunk": 1,
    "experts.ppo.num_envs": 4,
    "experts.ppo.num_minibatches": 2,
    "experts.ppo.num_epochs": 1,
    "experts.ppo.total_env_steps": 4 * N_STEPS * 2,
    # One family: 2 centre candidates compared after 1 update (the choice made by the first
    # process, read by the other), the chosen one alone for 1 more, every expert from it; the
    # sharded side stops after one chunk of each phase and resumes (`train`).
    "experts.family.centre_updates": 2,
    "experts.family.candidates": 2,
    "experts.family.choose_after": 1,
}


def experts_config():
    """The tiny experts' config: both sides of the test train it."""
    return config.make_config("tiny", EXPERTS)


def make_env(cfg=None):
    """PointGoal's env of the experts' config (Warp physics)."""
    cfg = cfg or experts_config()
    return registry.make_env(cfg.task, cfg.env)


def quiet(*args, **kwargs):
    pass


def train(env, run_dir: Path) -> dict:
    cfg = experts_config()  # 3 tasks on 2 devices of 2 processes: one padded copy
    programs = expert_programs.compile_programs(cfg, env, mesh=sharding.device_mesh(N_DEVICES, impl="warp"))
    # Stop after one chunk and resume: the sharded path must also restore checkpoints.
    experts.train(cfg, run_dir, programs, say=quiet, stop_after_chunks=1)
    out = experts.train(cfg, run_dir, programs, say=quiet)
    leaves = jax.tree.leaves(expert_programs.expert_params(out["state"]))
    return {"params": [np.asarray(x).tolist() for x in leaves], "finished": out["finished"]}


def contextual_params():
    """A stand-in contextual policy (a stack of one): a PD push toward `scale` x its goal, so
    that it stops short of the goal and filtering has a choice to make."""
    return {"gain": jnp.array([3.0]), "damping": jnp.array([1.5]), "scale": jnp.array([0.8])}


def contextual_apply(params, obs):
    """obs (6,): position, velocity and the goal normalised over (-1, 1) -> action (2,)."""
    goal = params["scale"] * (2.0 * obs[4:6] - 1.0)
    return jnp.clip(params["gain"] * (goal - obs[:2]) - params["damping"] * obs[2:4], -1.0, 1.0)


def contextual_grid(env, mesh=None):
    """(grid, params): every-pair rollouts of the stand-in policy, split over `mesh`."""
    return rollout.grid_fn(env, contextual_apply, mesh), contextual_params()


# The selection episodes (6 tasks' and sampled contexts x 3 reps) in calls of 8 (2 on each of 4
# devices, the last call padded).
EPISODES_PER_CALL = 8


def filter_synthetic(env, grid, params, n_devices: int) -> dict:
    """Selection for three goals by `grid` split over `n_devices` (every device of every
    process), in calls of EPISODES_PER_CALL episodes."""
    tasks = np.array([[0.5, 0.2], [-0.2, 0.5], [-0.4, -0.3]])
    sampled = [[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5]]
    contexts = filtering.candidate_contexts(tasks, sampled)  # 6 candidates x 3 reps = 18 episodes
    sel_key, _ = filtering.noise_keys(0)
    sel = filtering.filter_policy(
        grid,
        params,
        contexts,
        tasks,
        0.5,
        3,
        sel_key,
        task_range=tuple(env.config.task_range),
        block=EPISODES_PER_CALL // n_devices,
        multiple=n_devices,
        **filtering.scoring(env),
    )
    return {"chosen": sel.chosen.tolist(), "distance": sel.distance.tolist(), "scores": sel.scores.tolist()}


# Warp's contact pool for 4 episodes, and 16 episodes split over the 4 devices: 4 on each.
POOL_EPISODES = 4


def pool_per_device() -> dict:
    """One control step of POOL_EPISODES kick episodes on each device of each process, with a
    contact pool for POOL_EPISODES: whether any overflowed, and whether the program gathers a
    batch across devices (it must not: each device steps only its own share of the episodes)."""
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


# Two nets of the meta stage trained on stand-in pairs: each process trains its own (net i on
# process i % PROCESSES) and takes the other's state from its owner after every chunk.
NETS = {"wide": (2, 8), "deep": (3, 4)}


def nets_data():
    rng = np.random.default_rng(2)
    n = 120
    obs, actions = rng.uniform(size=(n, 2)).astype(np.float32), rng.normal(size=(n, 3)).astype(np.float32)
    return bc.Dataset(obs, actions, np.zeros(n, np.float32))


def nets_config():
    cfg = config.make_config("tiny").meta.train
    cfg.unlock()
    cfg.update({"learning_rate": 1e-2, "decay_every": 2, "epochs": 4, "chunk": 2, "batch_size": 64, "n_seeds": 2})
    cfg.lock()
    return cfg


def train_nets(run_dir: Path) -> dict:
    """The nets stopped after one chunk and resumed (the split path restores too): each net's
    final params and progress rows."""
    models = {name: bc.MetaPolicy(depth, width, 3) for name, (depth, width) in NETS.items()}
    dirs = {name: run_dir / name for name in NETS}
    bc.train_nets(models, nets_data(), nets_config(), dirs, quiet, max_chunks=1)
    states = bc.train_nets(models, nets_data(), nets_config(), dirs, quiet)
    return {
        name: {"params": [np.asarray(x).tolist() for x in jax.tree.leaves(states[name].params)],
               "rows": (dirs[name] / "progress.csv").read_text().splitlines()[1:] if jax.process_index() == 0 else []}
        for name in NETS
    }  # fmt: skip


def main() -> None:
    sharding.initialize_distributed()
    assert jax.process_count() == PROCESSES and len(jax.local_devices()) == N_DEVICES, jax.devices()
    env = make_env()
    out = {"experts": train(env, Path(sys.argv[1]))}
    mesh = sharding.device_mesh(N_DEVICES, impl="warp")
    grid, params = contextual_grid(env, mesh)
    out["filter"] = filter_synthetic(env, grid, params, sharding.ways(mesh))
    out["pool"] = pool_per_device()
    out["nets"] = train_nets(Path(sys.argv[1]) / "nets")
    out["nets_trained_here"] = sharding.own_items(list(NETS))  # the first process's share
    if jax.process_index() == 0:
        json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
