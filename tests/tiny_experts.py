"""The tiny expert-training config of test_experts.py and test_sharding.py (and of the process
that test starts): conftest compiles its programs once for both files (~70 s on a CPU)."""

from bumps_jax import experts

N_STEPS = 75  # control steps of one kick episode

# Two tasks, 4 episodes per update, 2 chunks of 1 update: seconds per chunk on a CPU.
OVERRIDES = {
    "tasks": (8.0, 12.0),
    "bc.steps": 300,
    "ppo.num_envs": 4,
    "ppo.num_minibatches": 2,
    "ppo.num_epochs": 1,
    "ppo.total_env_steps": 4 * N_STEPS * 2,
    "ppo.init_log_std": -4.0,
    "updates_per_chunk": 1,
    "eval.repetitions": 2,
    "tune.generations": 0,  # the blended prior as it is; tuning has its own test
}


def config(**extra):
    return experts.make_config(overrides={**OVERRIDES, **extra})
