"""Ant-Goal as a BUMPS task: a 2-D context (the goal), experts as one family from a fresh policy,
states normalised for the nets."""

from bumps_jax.tasks.ant_goal import config, env, table
from bumps_jax.tasks.protocol import Task, plain_report

TASK = Task(
    name="ant_goal",
    env_class=env.AntGoalEnv,
    stages=("experts", "meta", "filter", "baseline"),
    config=config,
    report=plain_report(
        ("target goal (m)", "final distance of the torso to the goal (m)", "final torso position (m)"),
        published_blocks=table.BLOCKS.publish,
    ),
)
