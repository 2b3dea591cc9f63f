"""Run by test_sharding.py in a fresh process with 4 host devices (XLA reads the device
count once, at start-up): trains tiny experts and filters a synthetic family on a mesh of 4
devices, and prints what they produced as JSON. The single-device side of both runs in the
test's own process, on programs that test_experts.py and test_filtering.py compile anyway."""

import json
import sys
import tempfile
from pathlib import Path

import jax
import numpy as np
import stand_ins
import tiny_experts

from bumps_jax import config, filtering, kick_env, rollout, sharding
from bumps_jax.stages import experts


def quiet(*args, **kwargs):
    pass


def train(env, run_dir: Path) -> dict:
    cfg = tiny_experts.pipeline_config()  # 2 tasks on 4 devices: two padded copies
    programs = experts.compile_programs(cfg, env, mesh=sharding.device_mesh(4))
    # Stop after one chunk and resume: the sharded path must also restore checkpoints.
    experts.train(cfg, run_dir, programs, say=quiet, stop_after_chunks=1)
    out = experts.train(cfg, run_dir, programs, say=quiet)
    leaves = jax.tree.leaves(experts.expert_params(out["state"]))
    return {"params": [np.asarray(x).tolist() for x in leaves], "finished": out["finished"]}


EPISODES_PER_CALL = 8  # the filtering tests' block: the single-device side reuses their program


def filter_synthetic(env, grid, params, n_devices: int) -> dict:
    """Selection of a synthetic family by `grid` split over `n_devices`, in calls of 8 episodes."""
    tasks = np.array([10.0, 13.0, 15.0])
    contexts = filtering.candidate_contexts(tasks, [9.0, 11.5, 14.0])  # 6 candidates x 3 reps = 18 episodes
    sel_key, _ = filtering.noise_keys(0)
    block = EPISODES_PER_CALL // n_devices
    task_range = tuple(env.config.task_range)
    sel = filtering.filter_policy(
        grid, params, contexts, tasks, 2.0, 3, sel_key, task_range=task_range, block=block, multiple=n_devices
    )
    return {"chosen": sel.chosen.tolist(), "distance": sel.distance.tolist(), "scores": sel.scores.tolist()}


def main() -> None:
    assert len(jax.devices()) == 4, jax.devices()
    env = kick_env.KickEnv(config.make_config("tiny").env)
    with tempfile.TemporaryDirectory() as tmp:
        out = {"experts": train(env, Path(tmp))}
    params = jax.tree.map(lambda a: a[None], stand_ins.synthetic_contextual_params())
    grid = rollout.grid_fn(env, stand_ins.contextual_apply, sharding.device_mesh(4))
    out["filter"] = filter_synthetic(env, grid, params, 4)
    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
