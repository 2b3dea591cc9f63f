"""PointGoal's config sections (`point_goal` in `config`'s tree), its `TINY` preset and its checks.

Its sections have the other tasks' layout; a context is a goal (x, y) m, so every list of
contexts is a tuple of (x, y) pairs, and filtering's `context_range` is the box each coordinate
spans (its grid is the 2-D grid of `context_step` over that box).
"""

from __future__ import annotations

import copy

import ml_collections
import numpy as np

from bumps_jax.algo import ppo_config
from bumps_jax.tasks.point_goal import env as point_env

# Training goals (m): the 0.5 m grid's points on the unit disc (13 goals).
TRAIN_TASKS = tuple(
    (x, y) for x in (-1.0, -0.5, 0.0, 0.5, 1.0) for y in (-1.0, -0.5, 0.0, 0.5, 1.0) if x * x + y * y <= 1.0
)
# The 30 test goals (m): uniform on the unit disc, numpy's default_rng(2026), rounded to 1 mm.
TEST_TASKS = point_env.disc_goals(30, 1.0, seed=2026)


def _experts() -> ml_collections.ConfigDict:
    experts = ml_collections.ConfigDict()
    experts.tasks = TRAIN_TASKS  # goals (x, y) m, one expert each
    experts.seed = 0
    experts.updates_per_chunk = 10  # PPO updates per compiled chunk; progress and a checkpoint between
    experts.keep_checkpoints = 3
    experts.ppo = ppo_config.default_config()
    experts.ppo.num_envs = 256  # whole 30-step episodes per update: 7,680 steps
    experts.ppo.num_minibatches = 8
    experts.ppo.num_epochs = 4
    experts.ppo.total_env_steps = 256 * 30 * 100  # 100 updates per expert
    experts.ppo.learning_rate = 3e-3
    experts.ppo.value_learning_rate = 3e-3
    experts.ppo.discount = 0.95
    experts.ppo.gae_lambda = 0.95
    experts.ppo.entropy_cost = 1e-3
    experts.ppo.reward_scaling = 1.0
    experts.ppo.normalize_observations = True
    experts.ppo.policy_hidden = (32, 32)
    experts.ppo.value_hidden = (64, 64)
    experts.ppo.init_log_std = -0.5
    experts.eval = ml_collections.ConfigDict()
    experts.eval.repetitions = 20  # episodes per expert on its own goal (reset noise on)
    experts.eval.seed = 1
    return experts


def _baseline(experts: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
    """Multi-task PPO: one policy that sees the goal, from a fresh init, on goals drawn per
    episode from the box (-1, 1)^2 m (each coordinate U[-1, 1]), with the env steps of all the
    experts together."""
    b = ml_collections.ConfigDict()
    b.seeds = 3
    b.updates_per_chunk = 10
    b.keep_checkpoints = 3
    b.eval_tasks = TEST_TASKS
    b.eval_repetitions = 20
    b.eval_seed = 7
    b.ppo = copy.deepcopy(experts.ppo)
    b.ppo.sample_task_range = (-1.0, 1.0)  # each coordinate of each episode's goal (m)
    b.ppo.num_envs = len(experts.tasks) * experts.ppo.num_envs
    b.ppo.total_env_steps = len(experts.tasks) * experts.ppo.total_env_steps
    b.extra_learning_rate = ml_collections.FieldReference(None, field_type=float)
    return b


def sections(meta: ml_collections.ConfigDict, filter_: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
    """PointGoal's sections (env, experts, meta, filter, baseline) at GPU size. `meta` and
    `filter_` are fresh copies of the kick's sections (the same keys); this task's goals and
    sizes replace theirs."""
    cfg = ml_collections.ConfigDict()
    cfg.env = point_env.default_config()
    experts = cfg.experts = _experts()
    cfg.baseline = _baseline(experts)
    cfg.meta = meta
    cfg.meta.dataset.repetitions = 8  # episodes per expert, reset noise on
    cfg.meta.train.learning_rate = 1e-3
    cfg.meta.train.batch_size = 256
    cfg.meta.train.epochs = 300
    cfg.meta.train.decay_every = 50
    cfg.meta.train.chunk = 25
    cfg.meta.eval.tasks = TEST_TASKS
    cfg.meta.eval.repetitions = 20
    cfg.filter = filter_
    cfg.filter.tasks = TEST_TASKS
    cfg.filter.context_range = (-1.0, 1.0)  # m: each coordinate of the sampled goals' grid ...
    cfg.filter.context_step = 0.1  # ... of this step (21 x 21 contexts)
    cfg.filter.high_context_step = 0.05  # the "high sample rate" variant (41 x 41)
    cfg.filter.width = 0.3  # m: a task's candidates are the contexts within this distance of it
    cfg.filter.halving_rungs = (2, 8, 32)
    cfg.filter.eval_repetitions = 20
    return cfg


# The `tiny` preset's overrides (dotted keys under `point_goal`): a few minutes on a CPU core.
# Four experts at the disc's compass points learn to reach their goals in 60 PPO updates.
TINY = {
    "point_goal.experts.tasks": ((0.7, 0.0), (0.0, 0.7), (-0.7, 0.0), (0.0, -0.7)),
    "point_goal.experts.updates_per_chunk": 20,
    "point_goal.experts.keep_checkpoints": 2,
    "point_goal.experts.ppo.num_envs": 32,
    "point_goal.experts.ppo.num_minibatches": 4,
    "point_goal.experts.ppo.total_env_steps": 32 * 30 * 60,
    "point_goal.experts.eval.repetitions": 8,
    "point_goal.meta.dataset.repetitions": 8,
    "point_goal.meta.train.epochs": 200,
    "point_goal.meta.train.chunk": 50,
    "point_goal.meta.train.decay_every": 50,
    "point_goal.meta.train.batch_size": 128,
    "point_goal.meta.eval.tasks": ((0.5, 0.2), (-0.2, 0.5), (-0.4, -0.3)),
    "point_goal.meta.eval.repetitions": 4,
    "point_goal.filter.tasks": ((0.5, 0.2), (-0.2, 0.5), (-0.4, -0.3)),
    "point_goal.filter.context_step": 0.25,
    "point_goal.filter.high_context_step": 0.125,
    "point_goal.filter.width": 0.3,
    "point_goal.filter.selection": "fixed",
    "point_goal.filter.selection_repetitions": 2,
    "point_goal.filter.halving_rungs": (1, 2),
    "point_goal.filter.eval_repetitions": 4,
    "point_goal.filter.block": 64,
    "point_goal.baseline.seeds": 2,
    "point_goal.baseline.updates_per_chunk": 20,
    "point_goal.baseline.keep_checkpoints": 2,
    "point_goal.baseline.eval_tasks": ((0.5, 0.2), (-0.2, 0.5), (-0.4, -0.3)),
    "point_goal.baseline.eval_repetitions": 4,
    "point_goal.baseline.ppo.num_envs": 4 * 32,
    "point_goal.baseline.ppo.num_minibatches": 4,
    "point_goal.baseline.ppo.total_env_steps": 4 * 32 * 30 * 60,  # the 4 tiny experts' steps
}


def validate(c, prefix: str = "point_goal.") -> None:
    """PointGoal's sections (`sections`), keys named with `prefix`: the env's own checks, every
    list of goals a tuple of (x, y) pairs in the task range, and the stages' shared checks."""
    from bumps_jax.pipeline import validation  # noqa: PLC0415 (the checks import the algorithm modules)

    try:
        point_env.validate_config(c.env)
    except ValueError as err:
        raise ValueError(f"{prefix}{err}") from None
    n_steps, task_range = int(c.env.episode_steps), tuple(c.env.task_range)
    goals = {"experts.tasks": c.experts.tasks, "meta.eval.tasks": c.meta.eval.tasks,
             "filter.tasks": c.filter.tasks, "baseline.eval_tasks": c.baseline.eval_tasks}  # fmt: skip
    for key, values in goals.items():
        if np.asarray(values, dtype=object).ndim != 2 or np.shape(values)[1:] != (point_env.CONTEXT_SIZE,):
            raise ValueError(f"{prefix}{key} must be a list of goals (x, y) m, got {values!r}")
    e = c.experts
    validation.targets(e.tasks, task_range, f"{prefix}experts.tasks")
    validation.positive_ints(e, f"{prefix}experts.", ("updates_per_chunk", "keep_checkpoints"))
    validation.positive_ints(e.eval, f"{prefix}experts.eval.", ("repetitions",))
    validation.ppo_section(e.ppo, f"{prefix}experts.ppo.", n_steps, task_range)
    validation.chunk_divides(e, f"{prefix}experts.", int(e.ppo.total_env_steps // (e.ppo.num_envs * n_steps)))
    validation.meta(c.meta, task_range, prefix, task="point_goal")
    validation.filtering(c.filter, task_range, prefix)
    if c.filter.net_seed >= c.meta.train.n_seeds:
        raise ValueError(f"{prefix}filter.net_seed {c.filter.net_seed} names no network: "
                         f"{prefix}meta.train.n_seeds is {c.meta.train.n_seeds}")  # fmt: skip
    validation.baseline(c.baseline, task_range, n_steps, prefix)
