"""PointGoal's config: its env and stage sections (`schema.sections` with its goals and sizes),
its presets and its checks.

A context is a goal (x, y) m, so every list of contexts is a tuple of (x, y) pairs, and
filtering's `context_range` is the box each coordinate spans (its grid is the 2-D grid of
`context_step` over that box).
"""

from __future__ import annotations

import copy

import ml_collections
import numpy as np

from bumps_jax.schema import sections as stage_sections
from bumps_jax.tasks.point_goal import env as point_env

# Training goals (m): the 0.5 m grid's points on the unit disc (13 goals).
TRAIN_TASKS = tuple(
    (x, y) for x in (-1.0, -0.5, 0.0, 0.5, 1.0) for y in (-1.0, -0.5, 0.0, 0.5, 1.0) if x * x + y * y <= 1.0
)
# The 30 test goals (m): uniform on the unit disc, numpy's default_rng(2026), rounded to 1 mm.
TEST_TASKS = point_env.disc_goals(30, 1.0, seed=2026)


def experts() -> ml_collections.ConfigDict:
    """PPO from a fresh policy on each training goal."""
    experts = stage_sections.experts(TRAIN_TASKS)  # goals (x, y) m, one expert each
    experts.updates_per_chunk = 10  # speed and logging only: PPO updates per compiled chunk
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
    experts.eval.repetitions = 20  # episodes per expert on its own goal (reset noise on)
    experts.family = stage_sections.family()  # every expert from its own fresh policy
    return experts


def baseline(experts: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
    """Multi-task PPO: one policy that sees the goal, from a fresh init, on goals drawn per
    episode from the box (-1, 1)^2 m (each coordinate U[-1, 1]), with the env steps of all the
    experts together."""
    b = stage_sections.baseline(copy.deepcopy(experts.ppo), TEST_TASKS, (-1.0, 1.0))  # each coordinate, m
    b.seeds = 3  # independent runs, trained side by side
    b.updates_per_chunk = 10  # speed and logging only: PPO updates per compiled chunk
    b.eval_repetitions = 20  # episodes per test goal and seed
    b.ppo.num_envs = len(experts.tasks) * experts.ppo.num_envs  # every expert's episodes in one update
    b.ppo.total_env_steps = len(experts.tasks) * experts.ppo.total_env_steps  # every expert's steps
    b.extra_learning_rate = None  # one arm only
    return b


def sections() -> ml_collections.ConfigDict:
    """PointGoal's tree but `preset` and `task` (env, experts, meta, filter, baseline) at GPU size."""
    cfg = ml_collections.ConfigDict()
    cfg.env = point_env.default_config()  # the point mass's physics, reset noise and reward
    cfg.experts = experts()
    cfg.baseline = baseline(cfg.experts)
    cfg.meta = stage_sections.closed_loop_meta(TEST_TASKS, action_noise=0.0, clip_labels=False)  # no DART
    # m: each coordinate of the sampled goals' grid over (-1, 1) of step 0.1 (21 x 21; the high
    # sample rate's 0.05: 41 x 41); a test goal's candidates lie within 0.3 m of it.
    cfg.filter = stage_sections.filtering(TEST_TASKS, (-1.0, 1.0), 0.1, 0.05, 0.3)
    cfg.filter.halving_rungs = (2, 8, 32)
    cfg.filter.eval_repetitions = 20
    return cfg


# Each preset: dotted overrides of the defaults. "tiny": a few minutes on a CPU core; four experts
# at the disc's compass points learn to reach their goals in 60 PPO updates.
TINY_TEST = ((0.5, 0.2), (-0.2, 0.5), (-0.4, -0.3))  # m: the tiny preset's test goals, between its experts'
PRESETS: dict[str, dict] = {
    "paper": {},
    "tiny": {
        "experts.tasks": ((0.7, 0.0), (0.0, 0.7), (-0.7, 0.0), (0.0, -0.7)),
        "experts.updates_per_chunk": 20,
        "experts.keep_checkpoints": 2,
        "experts.ppo.num_envs": 32,
        "experts.ppo.num_minibatches": 4,
        "experts.ppo.total_env_steps": 32 * 30 * 60,
        "experts.eval.repetitions": 8,
        "meta.dataset.repetitions": 8,
        "meta.train.epochs": 200,
        "meta.train.chunk": 50,
        "meta.train.decay_every": 50,
        "meta.train.batch_size": 128,
        "meta.eval.tasks": TINY_TEST,
        "meta.eval.repetitions": 4,
        "filter.tasks": TINY_TEST,
        "filter.context_step": 0.25,
        "filter.high_context_step": 0.125,
        "filter.width": 0.3,
        "filter.selection": "fixed",
        "filter.selection_repetitions": 2,
        "filter.halving_rungs": (1, 2),
        "filter.eval_repetitions": 4,
        "filter.block": 64,
        "baseline.seeds": 2,
        "baseline.updates_per_chunk": 20,
        "baseline.keep_checkpoints": 2,
        "baseline.eval_tasks": TINY_TEST,
        "baseline.eval_repetitions": 4,
        "baseline.ppo.num_envs": 4 * 32,
        "baseline.ppo.num_minibatches": 4,
        "baseline.ppo.total_env_steps": 4 * 32 * 30 * 60,  # the 4 tiny experts' steps
    },
}


def validate(cfg: ml_collections.ConfigDict) -> None:
    """PointGoal's own checks: every list of goals a tuple of (x, y) pairs."""
    goals = {"experts.tasks": cfg.experts.tasks, "meta.eval.tasks": cfg.meta.eval.tasks,
             "filter.tasks": cfg.filter.tasks, "baseline.eval_tasks": cfg.baseline.eval_tasks}  # fmt: skip
    for key, values in goals.items():
        if np.asarray(values, dtype=object).ndim != 2 or np.shape(values)[1:] != (point_env.CONTEXT_SIZE,):
            raise ValueError(f"{key} must be a list of goals (x, y) m, got {values!r}")
