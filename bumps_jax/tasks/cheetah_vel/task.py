"""HalfCheetah-Vel as a BUMPS task: experts from fresh policies, states normalised for the nets."""

from bumps_jax.tasks.cheetah_vel import config, env, table
from bumps_jax.tasks.protocol import Task, plain_report

TASK = Task(
    name="cheetah_vel",
    env_class=env.CheetahVelEnv,
    stages=("experts", "meta", "filter", "baseline"),
    config=config,
    report=plain_report(
        ("target velocity (m/s)", "mean velocity error (m/s)", "achieved mean velocity (m/s)"),
        published_blocks=table.BLOCKS.publish,
    ),
)
