"""PointGoal as a BUMPS task: a 2-D context (the goal), experts from fresh policies, states
normalised for the nets."""

from bumps_jax.tasks.point_goal import config, env
from bumps_jax.tasks.protocol import Task, plain_report

TASK = Task(
    name="point_goal",
    env_class=env.PointGoalEnv,
    stages=("experts", "meta", "filter", "baseline"),
    config=config,
    report=plain_report(("target goal (m)", "mean final distance to the goal (m)", "final position (m)")),
)
