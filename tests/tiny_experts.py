"""The tiny expert-training config of test_experts.py: conftest builds its programs once per test worker."""

from bumps_jax import config

N_STEPS = 75  # control steps of one kick episode

# Two tasks, 4 episodes per update, 2 chunks of 1 update: seconds per chunk on a CPU.
OVERRIDES = {
    "experts.tasks": (8.0, 12.0),
    "experts.bc.steps": 300,
    "experts.ppo.num_envs": 4,
    "experts.ppo.num_minibatches": 2,
    "experts.ppo.num_epochs": 1,
    "experts.ppo.total_env_steps": 4 * N_STEPS * 2,
    "experts.ppo.init_log_std": -4.0,
    "experts.updates_per_chunk": 1,
    "experts.eval.repetitions": 2,
    "experts.tune.generations": 0,  # the blended prior as it is; tuning has its own test
}


def pipeline_config(**extra):
    """The tiny pipeline config with these experts; `extra`: more dotted overrides."""
    return config.make_config("tiny", {**OVERRIDES, **extra})
