"""Ant-Goal's config: its env and stage sections (`schema.sections` with its goals and sizes),
its presets and its checks.

A context is a goal (x, y) m, so every list of contexts is a tuple of (x, y) pairs, and
filtering's `context_range` is the box each coordinate spans (its grid is the 2-D grid of
`context_step` over that box).

The `paper` preset is sized for one GPU: its numbers are mapped from Brax's published ant PPO, a
starting point; of its three seeds (`results/ant_goal/`) one family learned to walk
(docs/ant_goal.md). The `tiny` preset runs the whole pipeline on a CPU in minutes and trains
nothing useful.
"""

from __future__ import annotations

import copy
import math

import ml_collections
import numpy as np

from bumps_jax.algo import ppo_config
from bumps_jax.schema import sections as stage_sections
from bumps_jax.schema import validation
from bumps_jax.tasks.ant_goal import env as ant_env

# Training goals (m): the centre and three rings about it, a hexagonal pattern of about 1 m
# spacing over the goal disc: ring k (k = 1, 2, 3) has 6 k goals at radius k m, angles 2 pi j / 6k
# (1 + 6 + 12 + 18 = 37). Every test goal lies within 0.65 m of one.
TRAIN_TASKS = ((0.0, 0.0),) + tuple(
    (round(k * math.cos(2 * math.pi * j / (6 * k)), 3), round(k * math.sin(2 * math.pi * j / (6 * k)), 3))
    for k in (1, 2, 3)
    for j in range(6 * k)
)
# The 30 test goals (m): `ant_env.disc_goals(30, 3.0, seed=2026)`, drawn as PEARL's `sample_tasks`
# draws them (angle U[0, 2 pi), radius 3 sqrt(U[0, 1])) from numpy.random.default_rng(2026),
# rounded to 1 mm. Fixed here, so that every run is scored on the same ones.
TEST_TASKS = (
    (0.593, 1.238), (-1.79, -2.161), (-2.623, 0.547), (-1.605, 1.698), (-1.079, 1.393), (0.735, -2.825),
    (1.864, -1.264), (0.87, 1.771), (-1.633, -2.332), (-0.507, 1.618), (2.449, -0.516), (1.472, -0.811),
    (-1.008, -1.156), (0.043, -2.511), (-1.426, -0.136), (0.967, -1.872), (-2.166, 0.728), (-0.69, 1.106),
    (-0.447, 2.526), (0.329, 2.197), (-2.334, -0.382), (-1.66, 0.77), (-1.009, -1.662), (2.103, 0.17),
    (-1.947, 0.664), (-1.633, 1.848), (0.767, 2.146), (-1.602, -1.087), (-0.117, 0.05), (-0.826, 2.542),
)  # fmt: skip


def experts() -> ml_collections.ConfigDict:
    """PPO with Brax's published ant hyperparameters, mapped onto whole 200-step episodes, the
    experts as one family from a centre expert."""
    experts = stage_sections.experts(TRAIN_TASKS)  # goals (x, y) m, one expert each
    # Speed and logging only: PPO updates per compiled chunk (2 divides the centre's 74 updates).
    experts.updates_per_chunk = 2
    experts.ppo = ppo_config.brax_defaults()
    # Brax's ant PPO (its training notebook, notebooks/training.ipynb): 4096 envs, 5-step
    # unrolls, batch 2048 x 32 minibatches (327,680 steps per batch, 10,240 per minibatch),
    # 4 epochs per batch (num_updates_per_batch), discount 0.97, lr 3e-4, entropy 1e-2, reward
    # scaling 10, observation normalisation, 50 M steps; GAE lambda 0.95, clip 0.3 and value
    # weight 0.5 are its defaults, as are its nets.
    experts.ppo.num_envs = 512  # whole 200-step episodes per update: 102,400 steps (Brax: 327,680)
    experts.ppo.num_minibatches = 16  # 32 episodes = 6,400 steps each (Brax: 10,240)
    experts.ppo.num_epochs = 4
    # One family: the expert at the centre goal (0, 0) trains 74 updates alone, then all 37
    # continue from it for 100 updates each, their goals moving out from the centre over the
    # first 30: 3,774 updates of 102,400 steps in all (386.5 M; Brax's ant runs forward in 50 M).
    experts.family = stage_sections.family()
    experts.family.centre_updates = 74  # 2 x 37: the baseline's budget is whole updates of all 37
    experts.family.ramp_updates = 30
    experts.ppo.total_env_steps = 512 * 200 * 100  # 10.24 M per expert after the centre's 7.58 M
    experts.ppo.discount = 0.97
    # The distance term as progress toward the goal: w = 1 / (1 - discount) turns -|p - g|_1 into
    # (|p - g|_1 - |p' - g|_1) / (1 - discount) per step, an action's own effect, as Brax's ant
    # pays forward speed (potential-based: the same optimal policy).
    experts.ppo.potential_shaping = 1.0 / (1.0 - experts.ppo.discount)
    experts.ppo.entropy_cost = 1e-2
    experts.ppo.reward_scaling = 10.0
    experts.eval.repetitions = 20  # episodes per expert on its own goal (reset noise on)
    return experts


# The baseline's PPO updates per compiled chunk, at most (`DERIVED` takes a divisor of its updates).
BASELINE_CHUNK = 6


def baseline(experts: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
    """Multi-task PPO: one policy that sees the goal, trained from a fresh init by the experts'
    PPO (hyperparameters and nets) on goals drawn per episode from the box (-3, 3)^2 m (each
    coordinate U[-3, 3]: the goal disc and its corners beyond it), scored on the test goals as
    BUMPS is."""
    b = stage_sections.baseline(copy.deepcopy(experts.ppo), TEST_TASKS, (-3.0, 3.0))  # each coordinate, m
    b.seeds = 3  # independent runs, trained side by side
    b.updates_per_chunk = BASELINE_CHUNK  # speed and logging only: PPO updates per compiled chunk
    b.eval_repetitions = 20  # episodes per test goal and seed (reset noise on)
    # ... and per seed the env steps of one BUMPS run's experts together (`DERIVED`): each update
    # rolls out the episodes of all the experts' updates of one round (37 x 512), in the experts'
    # 16 minibatches: 102 updates.
    b.extra_learning_rate = None  # one arm only
    return b


def sections() -> ml_collections.ConfigDict:
    """Ant-Goal's tree but `preset` and `task` (env, experts, meta, filter, baseline), sized for
    one GPU."""
    cfg = ml_collections.ConfigDict()
    cfg.env = ant_env.default_config()  # the ant's physics, reset noise and reward
    cfg.experts = experts()
    cfg.baseline = baseline(cfg.experts)
    # DART cloning as the cheetah's (its noise 0.2, labels clipped to [-1, 1]); 59,200 pairs: 232 steps an epoch
    cfg.meta = stage_sections.closed_loop_meta(TEST_TASKS)
    # m: each coordinate of the sampled goals' grid over (-3, 3) of step 0.25 (25 x 25; the high
    # sample rate's 0.125: 49 x 49); a test goal's candidates lie within 0.5 m of it.
    cfg.filter = stage_sections.filtering(TEST_TASKS, (-3.0, 3.0), 0.25, 0.125, 0.5)
    cfg.filter.halving_rungs = (2, 8, 32)
    cfg.filter.eval_repetitions = 20
    return cfg


# Keys computed from others after the preset and `--set` (`config.derive`), unless set there: the
# baseline's budget per seed is one run's experts' (centre candidates included), and Warp's
# contact pool holds the larger training program.
DERIVED = stage_sections.equal_budget_derived(ant_env.MAX_CONTACTS[True], BASELINE_CHUNK)


def validate(cfg: ml_collections.ConfigDict) -> None:
    """Ant-Goal's own checks: every list of goals a tuple of (x, y) pairs, and Warp's
    pool holding each training program."""
    goals = {"experts.tasks": cfg.experts.tasks, "meta.eval.tasks": cfg.meta.eval.tasks,
             "filter.tasks": cfg.filter.tasks, "baseline.eval_tasks": cfg.baseline.eval_tasks}  # fmt: skip
    for key, values in goals.items():
        if np.asarray(values, dtype=object).ndim != 2 or np.shape(values)[1:] != (ant_env.CONTEXT_SIZE,):
            raise ValueError(f"{key} must be a list of goals (x, y) m, got {values!r}")
    if cfg.env.impl == "warp":
        per_episode = ant_env.contacts_per_episode(bool(cfg.env.all_contacts))
        programs = {"experts": len(cfg.experts.tasks) * cfg.experts.ppo.num_envs,
                    "baseline": validation.baseline_runs(cfg.baseline)}  # fmt: skip
        for name, n in programs.items():
            if n > cfg.env.warp_contacts // per_episode:
                raise ValueError(
                    f"env.warp_contacts {cfg.env.warp_contacts} holds {cfg.env.warp_contacts // per_episode} "
                    f"episodes, but the {name} program runs {n}: set it to at least {n * per_episode}"
                )


# The tiny preset's goals (m): three experts, the centre (0, 0) first, and one test goal between them.
TINY_TASKS = ((0.0, 0.0), (1.5, 0.0), (0.0, 1.5))
TINY_TEST = ((0.8, 0.4),)

# Each preset: dotted overrides of the defaults. "tiny": Ant-Goal at CPU size (about a minute on
# a CPU, most of it compiling): 5-step episodes, 3 experts of 2 PPO updates after a centre of 2,
# tiny nets, a short BC, filtering over a 2 m grid; a baseline of 2 seeds x 8 updates (the
# experts' and the centre's steps).
PRESETS: dict[str, dict] = {
    "paper": {},
    "tiny": {
        "env.episode_steps": 5,
        "env.warp_contacts": ant_env.MAX_CONTACTS[True] * 16,
        "experts.tasks": TINY_TASKS,
        "experts.updates_per_chunk": 1,
        "experts.keep_checkpoints": 2,
        "experts.ppo.num_envs": 4,
        "experts.ppo.num_minibatches": 2,
        "experts.ppo.num_epochs": 2,
        "experts.ppo.total_env_steps": 4 * 5 * 2,
        "experts.family.centre_updates": 2,
        "experts.family.ramp_updates": 1,
        "experts.ppo.policy_hidden": (16, 16),
        "experts.ppo.value_hidden": (16, 16),
        "experts.eval.repetitions": 2,
        "meta.nets.meta_4x256": (1, 16),
        "meta.nets.meta_11x128": (1, 16),
        "meta.dataset.repetitions": 2,
        "meta.train.epochs": 20,
        "meta.train.chunk": 10,
        "meta.train.decay_every": 10,
        "meta.train.batch_size": 30,  # every pair of its dataset (3 experts x 2 episodes x 5 steps) in one batch
        "meta.eval.tasks": TINY_TEST,
        "meta.eval.repetitions": 2,
        "filter.tasks": TINY_TEST,
        "filter.context_step": 2.0,  # 4 x 4 goals over (-3, 3)
        "filter.high_context_step": 1.5,  # 5 x 5
        "filter.width": 2.0,
        "filter.selection": "fixed",
        "filter.selection_repetitions": 2,
        "filter.halving_rungs": (1, 2),
        "filter.eval_repetitions": 2,
        "filter.block": 16,  # the contact pool's 16 episodes: each block one physics call
        "baseline.seeds": 2,
        "baseline.updates_per_chunk": 2,
        "baseline.keep_checkpoints": 2,
        "baseline.eval_tasks": TEST_TASKS[:2],
        "baseline.eval_repetitions": 2,
        "baseline.ppo.num_envs": 4,
        "baseline.ppo.num_minibatches": 2,
        "baseline.ppo.num_epochs": 2,
        "baseline.ppo.policy_hidden": (16, 16),
        "baseline.ppo.value_hidden": (16, 16),
    },
}
