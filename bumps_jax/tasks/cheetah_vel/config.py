"""HalfCheetah-Vel's config sections (`cheetah_vel` in `config`'s tree) and its `tiny` preset.

Its env, experts, meta and filter sections have the kick's layout where the stages share code;
`config.default_config` puts them under `cheetah_vel`, and `config.task_view` puts them at the top
when `task: cheetah_vel` is selected.
"""

from __future__ import annotations

import copy

import ml_collections

from bumps_jax.algo import ppo_config
from bumps_jax.pipeline import validation

# Meta-training velocities (m/s): a grid of 0.25 m/s over PEARL's U[0, 3] range.
from bumps_jax.tasks.cheetah_vel import env as cheetah_env

# Meta-training velocities (m/s): a grid of 0.25 m/s over PEARL's U[0, 3] range.
TRAIN_TASKS = tuple(round(0.25 * i, 2) for i in range(13))
# The 30 held-out test velocities (m/s): numpy.random.default_rng(2026).uniform(0, 3), rounded to 3
# decimals, the first 30 draws (none within 0.005 m/s of the training grid). Fixed here, so that
# every run is scored on the same ones.
TEST_TASKS = (
    0.537, 1.92, 1.402, 1.112, 1.065, 2.372, 2.715, 0.532, 1.958, 0.895, 2.901, 2.76, 1.908, 2.258, 1.545,
    2.478, 1.345, 1.016, 0.834, 0.679, 1.577, 1.293, 1.99, 0.039, 1.343, 1.096, 0.586, 1.785, 1.306, 0.9,
)  # fmt: skip


def _experts() -> ml_collections.ConfigDict:
    """PPO from a fresh policy with Brax's published halfcheetah hyperparameters, mapped onto whole
    200-step episodes."""
    experts = ml_collections.ConfigDict()
    experts.tasks = TRAIN_TASKS  # m/s, one expert each
    experts.seed = 0
    experts.updates_per_chunk = 10  # PPO updates per compiled chunk; progress and a checkpoint between
    experts.keep_checkpoints = 3
    experts.ppo = ppo_config.default_config()
    # Brax's halfcheetah PPO (its training notebook): 2048 envs x 20-step unrolls, 32 minibatches,
    # 8 epochs per batch, discount 0.95, lr 3e-4, entropy 1e-3, reward scaling 1, observation
    # normalisation; GAE lambda 0.95, clip 0.3 and value weight 0.5 are Brax's defaults.
    experts.ppo.num_envs = 512  # whole 200-step episodes per update: 102,400 steps (Brax: 327,680)
    experts.ppo.num_minibatches = 16  # 32 episodes = 6,400 steps each (Brax: 10,240)
    experts.ppo.num_epochs = 8
    experts.ppo.total_env_steps = 512 * 200 * 100  # 10.24 M per expert, 100 updates
    experts.ppo.learning_rate = 3e-4
    experts.ppo.value_learning_rate = 3e-4  # Brax: one Adam for both nets
    experts.ppo.discount = 0.95
    experts.ppo.gae_lambda = 0.95
    experts.ppo.clip_epsilon = 0.3
    experts.ppo.entropy_cost = 1e-3
    experts.ppo.reward_scaling = 1.0
    experts.ppo.normalize_observations = True
    experts.ppo.policy_hidden = (32, 32, 32, 32)  # Brax's default PPO nets
    experts.ppo.value_hidden = (256, 256, 256, 256, 256)
    experts.ppo.init_log_std = -0.37  # std 0.69: Brax's tanh-normal starts at softplus(0)
    experts.eval = ml_collections.ConfigDict()
    experts.eval.repetitions = 20  # episodes per expert on its own velocity (reset noise on)
    experts.eval.seed = 1
    return experts


def _baseline(experts: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
    """Multi-task PPO: one policy that sees the target velocity, trained from a fresh init by the
    experts' PPO on velocities drawn per episode from their range."""
    b = ml_collections.ConfigDict()
    b.seeds = 3  # independent runs, trained side by side
    b.updates_per_chunk = 10  # PPO updates per compiled chunk; progress and a checkpoint between
    b.keep_checkpoints = 3
    b.eval_tasks = TEST_TASKS  # m/s: scored on the held-out test velocities, as BUMPS is
    b.eval_repetitions = 20  # episodes per test velocity and seed (reset noise on)
    b.eval_seed = 7
    b.ppo = copy.deepcopy(experts.ppo)  # the experts' PPO hyperparameters and nets ...
    # ... with each episode's target drawn from U[lo, hi] of the experts' velocities (m/s) ...
    b.ppo.sample_task_range = (min(experts.tasks), max(experts.tasks))
    # ... and per seed the env steps that all of one BUMPS run's experts used together
    # (13 experts x 10.24 M = 133.12 M), in as many updates as one expert makes (100): each update
    # rolls out the episodes of all the experts' updates of one round (13 x 512), in the experts'
    # 16 minibatches.
    b.ppo.num_envs = len(experts.tasks) * experts.ppo.num_envs
    b.ppo.total_env_steps = len(experts.tasks) * experts.ppo.total_env_steps
    # A second arm: the same seeds at this policy learning rate, trained beside the first
    # (ppo.learning_rate) in one program; None: the first arm only.
    b.extra_learning_rate = ml_collections.FieldReference(None, field_type=float)
    return b


def sections(meta: ml_collections.ConfigDict, filter_: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
    """HalfCheetah-Vel's sections (env, experts, meta, filter, baseline), sized to run in 15 minutes on one
    H100 (docs/decisions.md). `meta` and `filter_` are fresh copies of the kick's sections (the same
    keys); this task's velocities and sizes replace theirs."""
    cfg = ml_collections.ConfigDict()
    cfg.env = cheetah_env.default_config()
    experts = cfg.experts = _experts()
    cfg.baseline = _baseline(experts)
    # Warp's contact pool holds the larger of the two training programs: the experts' 13 x 512
    # episodes, or the baseline's seeds x arms x 13 x 512.
    largest = max(len(experts.tasks) * experts.ppo.num_envs, validation.baseline_runs(cfg.baseline))
    cfg.env.warp_contacts = cheetah_env.CONTACTS_PER_GEOM * 8 * largest
    cfg.meta = meta
    cfg.meta.dataset.repetitions = 8  # episodes per expert, reset noise on: the states a closed loop meets
    cfg.meta.train.learning_rate = 1e-3
    cfg.meta.train.batch_size = 256
    cfg.meta.train.epochs = 300  # 20,800 pairs: 82 steps per epoch
    cfg.meta.train.decay_every = 50
    cfg.meta.train.chunk = 25
    cfg.meta.eval.tasks = TEST_TASKS
    cfg.meta.eval.repetitions = 20
    cfg.filter = filter_
    cfg.filter.tasks = TEST_TASKS
    cfg.filter.context_range = (0.0, 3.0)  # m/s: sampled contexts form a grid over this range ...
    cfg.filter.context_step = 0.1  # ... of this step (31 contexts)
    cfg.filter.high_context_step = 0.02  # the "high sample rate" variant (151 contexts)
    cfg.filter.width = 0.3  # m/s: a task's candidates are the contexts within +- width of it
    cfg.filter.halving_rungs = (2, 8, 32)
    cfg.filter.eval_repetitions = 20
    return cfg


# The `tiny` preset's overrides of these sections (dotted keys under `cheetah_vel`): HalfCheetah-Vel
# at CPU size: 10-step episodes, 2 experts, 2 PPO updates, a short BC; a baseline of 2 seeds x 4 updates.
TINY = {
    "cheetah_vel.env.episode_steps": 10,
    "cheetah_vel.env.warp_contacts": cheetah_env.CONTACTS_PER_GEOM * 8 * 16,
    "cheetah_vel.experts.tasks": (0.5, 2.0),
    "cheetah_vel.experts.updates_per_chunk": 1,
    "cheetah_vel.experts.keep_checkpoints": 2,
    "cheetah_vel.experts.ppo.num_envs": 4,
    "cheetah_vel.experts.ppo.num_minibatches": 2,
    "cheetah_vel.experts.ppo.num_epochs": 2,
    "cheetah_vel.experts.ppo.total_env_steps": 4 * 10 * 2,
    "cheetah_vel.experts.ppo.policy_hidden": (32, 32),
    "cheetah_vel.experts.ppo.value_hidden": (32, 32),
    "cheetah_vel.experts.eval.repetitions": 2,
    "cheetah_vel.meta.dataset.repetitions": 2,
    "cheetah_vel.meta.train.epochs": 20,
    "cheetah_vel.meta.train.chunk": 10,
    "cheetah_vel.meta.train.decay_every": 10,
    "cheetah_vel.meta.train.batch_size": 64,
    "cheetah_vel.meta.eval.tasks": (1.2,),
    "cheetah_vel.meta.eval.repetitions": 2,
    "cheetah_vel.filter.tasks": (1.2,),
    "cheetah_vel.filter.context_step": 0.5,
    "cheetah_vel.filter.high_context_step": 0.25,
    "cheetah_vel.filter.width": 0.5,
    "cheetah_vel.filter.selection": "fixed",
    "cheetah_vel.filter.selection_repetitions": 2,
    "cheetah_vel.filter.halving_rungs": (1, 2),
    "cheetah_vel.filter.eval_repetitions": 2,
    "cheetah_vel.filter.block": 16,
    "cheetah_vel.baseline.seeds": 2,
    "cheetah_vel.baseline.updates_per_chunk": 2,
    "cheetah_vel.baseline.keep_checkpoints": 2,
    "cheetah_vel.baseline.eval_tasks": TEST_TASKS[:2],
    "cheetah_vel.baseline.eval_repetitions": 2,
    "cheetah_vel.baseline.ppo.sample_task_range": (0.5, 2.0),  # the tiny experts' velocities
    "cheetah_vel.baseline.ppo.num_envs": 4,
    "cheetah_vel.baseline.ppo.num_minibatches": 2,
    "cheetah_vel.baseline.ppo.num_epochs": 2,
    "cheetah_vel.baseline.ppo.total_env_steps": 2 * 4 * 10 * 2,  # the 2 tiny experts' steps: 4 updates
    "cheetah_vel.baseline.ppo.policy_hidden": (32, 32),
    "cheetah_vel.baseline.ppo.value_hidden": (32, 32),
}
