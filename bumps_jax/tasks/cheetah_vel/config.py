"""HalfCheetah-Vel's config: its env and stage sections (the stages' own, `schema.sections`,
with its velocities and sizes), its presets and its checks."""

from __future__ import annotations

import copy

import ml_collections

from bumps_jax.algo import ppo_config
from bumps_jax.schema import sections as stage_sections
from bumps_jax.schema import validation
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


def experts() -> ml_collections.ConfigDict:
    """PPO from a fresh policy with Brax's published halfcheetah hyperparameters, mapped onto whole
    200-step episodes."""
    experts = stage_sections.experts(TRAIN_TASKS)  # m/s, one expert each
    experts.updates_per_chunk = 10  # speed and logging only: PPO updates per compiled chunk
    experts.ppo = ppo_config.brax_defaults()
    # Brax's halfcheetah PPO (its training notebook): 2048 envs x 20-step unrolls, 32 minibatches,
    # 8 epochs per batch, discount 0.95, lr 3e-4, entropy 1e-3, reward scaling 1, observation
    # normalisation; GAE lambda 0.95, clip 0.3 and value weight 0.5 are Brax's defaults.
    experts.ppo.num_envs = 512  # whole 200-step episodes per update: 102,400 steps (Brax: 327,680)
    experts.ppo.num_minibatches = 4  # 128 episodes = 25,600 steps each (Brax: 10,240; docs/decisions.md)
    experts.ppo.num_epochs = 8
    # One family: 8 candidates for the 1.5 m/s expert train 40 updates side by side, the upright
    # one of least error goes on alone to 130 (another 8 where all 8 run flipped, at most 3
    # rounds), then all 13 continue from it for 90 updates each, their targets moving out from
    # 1.5 m/s over the first 30: 1,580 updates of 102,400 steps in one round (161.79 M).
    experts.family = stage_sections.family()
    experts.family.centre_updates = 130
    experts.family.candidates = 8
    experts.family.choose_after = 40
    experts.family.rounds = 3
    experts.family.ramp_updates = 30
    experts.ppo.total_env_steps = 512 * 200 * 90  # 9.216 M per expert after the centre's 41.98 M
    experts.ppo.discount = 0.95
    experts.ppo.entropy_cost = 1e-3
    experts.ppo.reward_scaling = 1.0
    experts.eval.repetitions = 20  # episodes per expert on its own velocity (reset noise on)
    return experts


# The baseline's PPO updates per compiled chunk, at most (`DERIVED` takes a divisor of its updates).
BASELINE_CHUNK = 10


def baseline(experts: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
    """Multi-task PPO: one policy that sees the target velocity, trained from a fresh init by the
    experts' PPO (hyperparameters and nets) on velocities drawn per episode from their range,
    scored on the held-out test velocities as BUMPS is."""
    b = stage_sections.baseline(copy.deepcopy(experts.ppo), TEST_TASKS, (min(experts.tasks), max(experts.tasks)))
    b.seeds = 3  # independent runs, trained side by side
    b.updates_per_chunk = BASELINE_CHUNK  # speed and logging only: PPO updates per compiled chunk
    b.eval_repetitions = 20  # episodes per test velocity and seed (reset noise on)
    # ... and per seed the env steps of one BUMPS run's experts together (`DERIVED`): each update
    # rolls out the episodes of all the experts' updates of one round (13 x 512), in 16
    # minibatches of 83,200 steps.
    b.ppo.num_minibatches = 16
    b.extra_learning_rate = None  # one arm only
    return b


def sections() -> ml_collections.ConfigDict:
    """HalfCheetah-Vel's tree but `preset` and `task` (env, experts, meta, filter, baseline), sized
    to run in 15 minutes on one H100 (docs/decisions.md)."""
    cfg = ml_collections.ConfigDict()
    cfg.env = cheetah_env.default_config()  # the cheetah's physics, reset noise and reward
    cfg.experts = experts()
    cfg.baseline = baseline(cfg.experts)
    # DART cloning (noise 0.2, labels clipped to [-1, 1]; docs/decisions.md); 20,800 pairs: 82 steps an epoch
    cfg.meta = stage_sections.closed_loop_meta(TEST_TASKS)
    # m/s: contexts on a 0.1 grid over 0-3 (31; the high sample rate's 0.02: 151), within +- 0.3.
    cfg.filter = stage_sections.filtering(TEST_TASKS, (0.0, 3.0), 0.1, 0.02, 0.3)
    cfg.filter.halving_rungs = (2, 8, 32)
    cfg.filter.eval_repetitions = 20
    return cfg


# Keys computed from others after the preset and `--set` (`config.derive`), unless set there: the
# baseline's budget per seed is one run's experts' (centre candidates included), and Warp's
# contact pool holds the larger training program.
DERIVED = stage_sections.equal_budget_derived(cheetah_env.CONTACTS_PER_GEOM * 8, BASELINE_CHUNK)


def validate(cfg: ml_collections.ConfigDict) -> None:
    """HalfCheetah-Vel's own checks: Warp's pool holding each training program."""
    if cfg.env.impl == "warp":
        per_episode = cheetah_env.contacts_per_episode(bool(cfg.env.all_contacts))
        programs = {"experts": len(cfg.experts.tasks) * cfg.experts.ppo.num_envs,
                    "baseline": validation.baseline_runs(cfg.baseline)}  # fmt: skip
        for name, n in programs.items():
            if n > cfg.env.warp_contacts // per_episode:
                raise ValueError(
                    f"env.warp_contacts {cfg.env.warp_contacts} holds {cfg.env.warp_contacts // per_episode} "
                    f"episodes, but the {name} program runs {n}: set it to at least {n * per_episode}"
                )


# Each preset: dotted overrides of the defaults. "tiny": HalfCheetah-Vel at CPU size: 10-step
# episodes, 2 experts of 2 PPO updates after a centre of 3 (2 candidates compared after 1, in up to 2
# rounds), a short BC; a baseline of 2 seeds x 8 updates (the experts' and one round's centre steps).
PRESETS: dict[str, dict] = {
    "paper": {},
    "tiny": {
        "env.episode_steps": 10,
        "env.warp_contacts": cheetah_env.CONTACTS_PER_GEOM * 8 * 16,
        "experts.tasks": (0.5, 2.0),
        "experts.updates_per_chunk": 1,
        "experts.keep_checkpoints": 2,
        "experts.ppo.num_envs": 4,
        "experts.ppo.num_minibatches": 2,
        "experts.ppo.num_epochs": 2,
        "experts.ppo.total_env_steps": 4 * 10 * 2,
        "experts.family.centre_updates": 3,
        "experts.family.ramp_updates": 1,
        "experts.family.candidates": 2,
        "experts.family.choose_after": 1,  # the candidates' 1 update, then the chosen one's 2
        "experts.family.rounds": 2,  # a second round of candidates where the first all run flipped
        "experts.ppo.policy_hidden": (32, 32),
        "experts.ppo.value_hidden": (32, 32),
        "experts.eval.repetitions": 2,
        "meta.dataset.repetitions": 2,
        "meta.train.epochs": 20,
        "meta.train.chunk": 10,
        "meta.train.decay_every": 10,
        "meta.train.batch_size": 40,  # every pair of its dataset (2 experts x 2 episodes x 10 steps) in one batch
        "meta.eval.tasks": (1.2,),
        "meta.eval.repetitions": 2,
        "filter.tasks": (1.2,),
        "filter.context_step": 0.5,
        "filter.high_context_step": 0.25,
        "filter.width": 0.5,
        "filter.selection": "fixed",
        "filter.selection_repetitions": 2,
        "filter.halving_rungs": (1, 2),
        "filter.eval_repetitions": 2,
        "filter.block": 16,
        "baseline.seeds": 2,
        "baseline.updates_per_chunk": 2,
        "baseline.keep_checkpoints": 2,
        "baseline.eval_tasks": TEST_TASKS[:2],
        "baseline.eval_repetitions": 2,
        "baseline.ppo.sample_task_range": (0.5, 2.0),  # the tiny experts' velocities
        "baseline.ppo.num_envs": 4,
        "baseline.ppo.num_minibatches": 2,
        "baseline.ppo.num_epochs": 2,
        "baseline.ppo.policy_hidden": (32, 32),
        "baseline.ppo.value_hidden": (32, 32),
    },
}
