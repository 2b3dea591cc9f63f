"""Run by test_sharding.py in a fresh process with 4 host devices (XLA reads the device
count once, at start-up): trains tiny experts and filters a synthetic family on a mesh of 1
device and on a mesh of 4, and prints what each produced as JSON."""

import json
import sys
import tempfile
from pathlib import Path

import jax
import numpy as np

from bumps_jax import evaluate, experts, filtering, kick_env, sharding, synthetic_experts

TINY = {
    "tasks": (8.0, 12.0, 16.0),  # 3 tasks on 4 devices: one padded copy
    "bc.steps": 200,
    "tune.generations": 0,  # the blended prior as it is (tuning costs two more compiles per mesh)
    "ppo.num_envs": 4,
    "ppo.num_minibatches": 2,
    "ppo.num_epochs": 1,
    "ppo.total_env_steps": 4 * 75 * 2,
    "updates_per_chunk": 1,
}


def train(env, n_devices: int, run_dir: Path) -> dict:
    cfg = experts.make_config(overrides=TINY)
    programs = experts.compile_programs(cfg, env, mesh=sharding.device_mesh(n_devices))
    # Stop after one chunk and resume: the sharded path must also restore checkpoints.
    experts.train_experts(cfg, run_dir, verbose=False, stop_after_chunks=1, programs=programs)
    out = experts.train_experts(cfg, run_dir, verbose=False, programs=programs)
    leaves = jax.tree.leaves(experts.expert_params(out["state"]))
    return {"params": [np.asarray(x).tolist() for x in leaves], "finished": out["finished"]}


def filter_synthetic(env, n_devices: int) -> dict:
    mesh = sharding.device_mesh(n_devices)
    params = jax.tree.map(lambda a: a[None], synthetic_experts.synthetic_contextual_params())
    grid = evaluate.grid_fn(env, synthetic_experts.contextual_apply, mesh)
    tasks = np.array([10.0, 13.0, 15.0])
    contexts = filtering.candidate_contexts(tasks, [9.0, 11.5, 14.0])  # 6 candidates x 3 reps = 18 episodes
    sel_key, _ = filtering.noise_keys(0)
    sel = filtering.filter_policy(
        grid, params, contexts, tasks, 2.0, 3, sel_key, filtering.ball_start_xy(env), multiple=mesh.size
    )
    return {"chosen": sel.chosen.tolist(), "distance": sel.distance.tolist(), "scores": sel.scores.tolist()}


def main() -> None:
    assert len(jax.devices()) == 4, jax.devices()
    env = kick_env.KickEnv()
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for n in (1, 4):
            out[n] = {"experts": train(env, n, Path(tmp) / f"run{n}"), "filter": filter_synthetic(env, n)}
    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
