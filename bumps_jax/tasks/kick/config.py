"""The kick's config: its env and stage sections, its plug-ins' own (the keyframe prior, the
experts' starting kicks, the baseline's cloned start), its presets and its checks.

What the `paper` preset runs that the paper did not (its hyperparameter tables; the original
code's keyframe kick):
  - the physics: MuJoCo (Warp) at a 2.5 ms step with `env.noise`, not SimSpark;
  - PPO (`experts.ppo`): 256 episodes (19,200 steps) per update in 16 minibatches of 1,200
    steps, where the paper has 4,096-step batches and minibatches of 1,024 (the same 12 M
    steps per expert and 30 epochs); a separate value-net rate (`value_learning_rate` 1e-3,
    the paper one Adam at 1e-6), gradient clipping, reward scaling 0.01 on top of the env's
    0.1 (`ppo_config` names the paper's value beside each);
  - the experts' start: every task's keyframe kick from the prior's long kick at its own
    strength, then tuned by CMA-ES as one chain (`experts.bc`, `experts.tune`): four tuning
    runs (`tune.restarts` 4) whose kicks are chosen together with the neighbour leash, then a
    20-generation polish (`tune.polish_generations`); the paper cloned no tuned kicks;
  - the meta-policies read (phase, normalised target) in [0, 1], not (time step, target m);
    the paper's BC learning rate is printed as 3^-6, ours is 3e-4 (the original code's);
  - filtering by successive halving (`filter.selection`), not a fixed number of rollouts per
    context, and the 6 baseline seeds trained at a second learning rate besides the paper's
    (`baseline.extra_learning_rate`).
"""

from __future__ import annotations

import math

import ml_collections
import numpy as np

from bumps_jax.schema import sections as stage_sections
from bumps_jax.schema import validation
from bumps_jax.schema.validation import positive_floats, positive_ints, targets
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model
from bumps_jax.tasks.kick.targets import DEV_TARGETS, HELDOUT_TARGETS

# The paper preset's held-out set must hold at least this many targets.
HELDOUT_MIN_TARGETS = 50


def prior() -> ml_collections.ConfigDict:
    cfg = ml_collections.ConfigDict()
    cfg.target = 12.0  # m: the distance the main kick is searched for
    cfg.task_range = (5.0, 25.0)  # m: targets the prior's searches may kick for
    cfg.extremes = ml_collections.ConfigDict({"short": 6.0, "long": 21.0})  # m: the family's ends
    cfg.population_size = 64  # CMA-ES candidates per generation
    cfg.generations = 80  # CMA-ES generations of each search
    cfg.repetitions = 16  # noisy episodes per candidate per generation
    cfg.eval_repetitions = 100  # fresh noisy episodes scoring the best kick
    cfg.sigma_init = 1.0  # CMA-ES step, in units of the kick model's PARAM_SCALE
    cfg.seed = 0  # CMA-ES and noise seed of the prior's searches
    # Kick record the main search starts from ("": the committed assets/kick_prior.json); a run
    # copies it into its directory first.
    cfg.start = ""
    cfg.start_strength = 0.75  # the main kick's swing speed cap (strength is not searched)
    # Parameters the main search moves (the extremes move all); strength stays at start_strength.
    cfg.free_params = (
        "lean", "support_hip", "support_ankle", "t_shift", "t_lift", "back_hip", "back_knee",
        "back_ankle", "t_back", "swing_hip", "swing_knee", "swing_ankle", "t_swing",
    )  # fmt: skip
    # Strengths at which the family is swept to calibrate distance: short (0) -> main (0.5) -> long (1).
    cfg.sweep_strengths = tuple(i / 8 for i in range(9))
    cfg.fitness = ml_collections.ConfigDict()  # a kick's cost in every CMA-ES search
    cfg.fitness.distance = 1.0  # cost per metre of resting error along the kick line
    cfg.fitness.lateral = 2.0  # cost per metre sideways
    cfg.fitness.invalid = 20.0  # cost of a fall, a miss or a blow-up
    return cfg


def experts() -> ml_collections.ConfigDict:
    """One PPO expert per target, each cloned from its own tuned keyframe kick first."""
    cfg = stage_sections.experts(kick_env.meta_train_tasks())  # m, one expert each
    cfg.bc = ml_collections.ConfigDict()  # cloning each task's starting kick into its expert
    cfg.bc.steps = 20000  # full-batch Adam steps cloning the starting kick (cosine decay)
    cfg.bc.learning_rate = 1e-2  # peak Adam rate of that cloning
    # Where each task's starting kick begins, before tuning: True, the prior's family at the
    # task's calibrated strength (with `tune.anchor_starts`, the best of that and the prior's
    # anchors); False, the prior's long kick for every task, each copy at the strength at which it
    # rests nearest the task's target (read from a noisy sweep of its strength,
    # `tune.eval_repetitions` episodes per strength), so that the tuned kicks are one family.
    cfg.bc.per_task_strength = False
    cfg.tune = ml_collections.ConfigDict()  # CMA-ES on every task's starting kick, all at once
    cfg.tune.generations = 60  # 0: clone the (blended or anchor) kick as it is
    cfg.tune.sigma_init = 2.0  # in PARAM_SCALE units around each task's start
    cfg.tune.population_size = 32  # CMA-ES candidates per task per generation
    cfg.tune.repetitions = 8  # noisy kicks per candidate per generation
    cfg.tune.eval_repetitions = 32  # fresh kicks choosing between start and tuned
    cfg.tune.seed = 0  # CMA-ES seed of the tuning
    # Independent runs of the whole tuning (different CMA-ES keys), played as one batch (each
    # physics call holds every run's episodes; the tuning's env gets a contact pool restarts x
    # env.warp_contacts), each run from its own key as it would alone. 1: that run is kept, each
    # task the better of its start and its kick; > 1: each task's kick is chosen among its start
    # and its kicks in every run together with its neighbours' (fresh costs plus the neighbour
    # leash, `cmaes.chain_choice`). Each run costs a tuning.
    cfg.tune.restarts = 1
    # restarts > 1 only: generations of one more tuning from the kicks chosen among the runs (the
    # same leash, its own key, initial step `POLISH_SIGMA` of starting_kicks), each task again
    # keeping the better of the two; 0: none. It re-joins the chain where neighbouring tasks came
    # from different runs.
    cfg.tune.polish_generations = 0
    # Start each task from the best of its blended kick and the prior's three anchors.
    cfg.tune.anchor_starts = True
    # Cost per squared PARAM_SCALE unit of a candidate's mean distance from the midpoint of its
    # neighbouring tasks' current means, added during the search (0: none). > 0 tunes the tasks as
    # a chain, so that a kick between two tasks' kicks is near both.
    cfg.tune.neighbour_leash = 1.0
    cfg.ppo.num_envs = 256  # episodes per update (19,200 steps; the paper: 4,096)
    cfg.ppo.num_minibatches = 16  # 16 episodes = 1,200 steps each (the paper: 1,024)
    cfg.ppo.num_epochs = 30  # passes over each update's batch
    cfg.ppo.total_env_steps = 256 * 75 * 625  # 12.0 M per expert, 625 updates
    cfg.ppo.learning_rate = 1e-6  # the policy's Adam rate
    cfg.ppo.init_log_std = -6.0  # the policy's log-std at the start
    cfg.ppo.reward_scaling = 0.01  # factor on the env's reward
    return cfg


def sections() -> ml_collections.ConfigDict:
    """The kick's whole tree but `preset` and `task`, at the `paper` preset's defaults."""
    cfg = ml_collections.ConfigDict()
    cfg.env = kick_env.default_config()  # the kick's physics, noise and reward (`kick_env` comments each leaf)
    cfg.prior = prior()
    cfg.experts = experts()
    cfg.meta = stage_sections.meta(kick_env.meta_test_tasks())
    # Contexts on a 0.1 m grid over 7.1-18 m (110; the high sample rate's 0.01 m: 1091), within +- 1 m.
    cfg.filter = stage_sections.filtering(kick_env.meta_test_tasks(), (7.1, 18.0), 0.1, 0.01, 1.0)
    baseline_ppo = experts().ppo  # one expert's PPO settings and budget per seed ...
    baseline_ppo.policy_hidden = (256,) * 11  # ... with the paper's 11 x 256 policy
    cfg.baseline = stage_sections.baseline(baseline_ppo, kick_env.meta_test_tasks(), (7.0, 18.0))  # targets U[7, 18] m
    cfg.baseline.bc_steps = 20000  # Adam steps cloning the main kick at every training context before PPO
    cfg.baseline.bc_learning_rate = 1e-3  # peak Adam rate of that cloning
    cfg.heldout = stage_sections.heldout(HELDOUT_TARGETS, 2222)  # m, off the 0.1 m grid
    cfg.dev = stage_sections.heldout(DEV_TARGETS, 3333)  # m, off the grid and the held-out targets: for design choices
    return cfg


# Each preset: dotted overrides of the defaults (the paper's values). "tiny" shrinks every budget
# so the whole pipeline runs on a CPU in minutes.
# The kick's own training seeds, set with the stages' by a pipeline seed (`config.seeded`).
TRAINING_SEEDS = ("prior.seed", "experts.tune.seed")

PRESETS: dict[str, dict] = {
    "paper": {
        # The starting kicks tuned four times (independent CMA-ES keys, one batch), each task's
        # kick chosen among the runs together with its neighbours' (the leash), then a
        # 20-generation polish.
        "experts.tune.restarts": 4,
        "experts.tune.polish_generations": 20,
    },
    "tiny": {
        # Warp's contact pool sized to the tiny batches (on a CPU unused slots cost every step).
        "env.warp_contacts": 12 * 128,
        "prior.population_size": 8,
        "prior.generations": 3,
        "prior.repetitions": 2,
        "prior.eval_repetitions": 8,
        "experts.tasks": (8.0, 12.0, 16.0),
        "experts.updates_per_chunk": 2,
        "experts.keep_checkpoints": 2,
        "experts.tune.generations": 1,
        "experts.tune.sigma_init": 0.5,
        "experts.tune.population_size": 4,
        "experts.tune.repetitions": 2,
        "experts.tune.eval_repetitions": 4,
        "experts.tune.anchor_starts": False,
        # Each task starts from the prior's family at its own strength, untied to its neighbours
        # (one generation cannot carry one kick to 8 and 16 m).
        "experts.bc.per_task_strength": True,
        "experts.tune.neighbour_leash": 0.0,
        "experts.ppo.num_envs": 8,
        "experts.ppo.num_minibatches": 2,
        "experts.ppo.num_epochs": 4,
        "experts.ppo.total_env_steps": 8 * 75 * 4,
        "experts.ppo.learning_rate": 3e-5,
        "experts.ppo.init_log_std": -4.0,
        "experts.eval.repetitions": 8,
        "meta.train.epochs": 2000,
        "meta.train.learning_rate": 3e-3,
        "meta.train.decay_every": 500,
        "meta.train.chunk": 500,
        "meta.eval.tasks": kick_env.meta_test_tasks()[9::10],
        "meta.eval.repetitions": 2,
        "filter.tasks": kick_env.meta_test_tasks()[9::10],
        "filter.context_step": 1.0,
        "filter.high_context_step": 0.5,
        # Every candidate context 2 rollouts (no halving).
        "filter.selection": "fixed",
        "filter.selection_repetitions": 2,
        "filter.halving_rungs": (1, 2),
        "filter.eval_repetitions": 2,
        "filter.block": 24,
        "baseline.seeds": 2,
        "baseline.updates_per_chunk": 1,
        "baseline.keep_checkpoints": 2,
        "baseline.bc_steps": 2000,
        "baseline.bc_learning_rate": 1e-2,
        "baseline.eval_tasks": kick_env.meta_test_tasks()[9::20],
        "baseline.eval_repetitions": 2,
        "baseline.ppo.num_envs": 8,
        "baseline.ppo.num_minibatches": 2,
        "baseline.ppo.num_epochs": 2,
        "baseline.ppo.total_env_steps": 8 * 75 * 3,
        "baseline.ppo.learning_rate": 1e-5,
        "baseline.extra_learning_rate": 1e-4,
        "baseline.ppo.init_log_std": -4.0,
        "baseline.ppo.policy_hidden": (64, 64),
        "heldout.targets": HELDOUT_TARGETS[::10],
        "heldout.repetitions": 2,
        "heldout.selection_repetitions": 2,
        "dev.targets": DEV_TARGETS[::20],
        "dev.repetitions": 2,
        "dev.selection_repetitions": 2,
    },
}


def validate(cfg: ml_collections.ConfigDict) -> None:
    """The kick's own checks: the prior, the experts' starting kicks, Warp's capacity for
    the tuning, the held-out and development targets."""
    prior_section(cfg.prior)
    experts_section(cfg.experts)
    positive_ints(cfg.baseline, "baseline.", ("bc_steps",))
    positive_floats(cfg.baseline, "baseline.", ("bc_learning_rate",))
    validation.heldout(cfg.dev, tuple(cfg.env.task_range), "dev")
    heldout_section(cfg.heldout, cfg.preset)
    heldout_section(cfg.dev, cfg.preset, "dev")
    shared = [t for t in cfg.dev.targets if np.min(np.abs(np.asarray(cfg.heldout.targets) - t)) < 0.005]
    if shared:
        raise ValueError(f"dev.targets: {shared[0]!r} m lies within 0.005 m of a held-out target; keep them apart")
    if cfg.dev.seed == cfg.heldout.seed:
        raise ValueError(f"dev.seed {cfg.dev.seed} is heldout.seed: the development noise must be its own")
    physics_capacity(cfg)


def prior_section(p) -> None:
    positive_ints(p, "prior.", ("population_size", "generations", "repetitions", "eval_repetitions"))
    if p.population_size < 2:
        raise ValueError(f"prior.population_size must be >= 2 for CMA-ES, got {p.population_size}")
    positive_floats(p, "prior.", ("sigma_init",))
    if not 0.0 < p.start_strength <= 1.0:
        raise ValueError(f"prior.start_strength must be in (0, 1], got {p.start_strength!r}")
    unknown = [n for n in p.free_params if n not in kick_model.PARAM_NAMES]
    if unknown or not p.free_params:
        raise ValueError(f"prior.free_params must name parameters of {kick_model.PARAM_NAMES}, got {unknown!r}")
    for name, value in p.fitness.items():
        if not math.isfinite(value) or value < 0:
            raise ValueError(f"prior.fitness.{name} must be >= 0, got {value!r}")
    lo, hi = p.task_range
    if not 0.0 < lo < hi:
        raise ValueError(f"prior.task_range must be 0 < low < high, got {tuple(p.task_range)}")
    targets([p.target, *p.extremes.values()], p.task_range, "prior.target and prior.extremes")
    if not all(0.0 <= s <= 1.0 for s in p.sweep_strengths) or not p.sweep_strengths:
        raise ValueError(f"prior.sweep_strengths must lie in [0, 1], got {tuple(p.sweep_strengths)}")


def physics_capacity(cfg) -> None:
    """Warp's contact pool holds every episode of each training program and of the experts'
    kick tuning (rollouts larger than the pool run in chunks; a PPO or CMA-ES program cannot)."""
    if cfg.env.impl != "warp":
        return
    most = cfg.env.warp_contacts // kick_env.CONTACTS_PER_EPISODE
    tuning = len(cfg.experts.tasks) * cfg.experts.tune.population_size * cfg.experts.tune.repetitions
    scoring = len(cfg.experts.tasks) * (cfg.experts.tune.restarts + 1) * cfg.experts.tune.eval_repetitions
    programs = {
        "experts (len(experts.tasks) x experts.ppo.num_envs)": len(cfg.experts.tasks) * cfg.experts.ppo.num_envs,
        "baseline (baseline.seeds x learning rates x baseline.ppo.num_envs)": validation.baseline_runs(cfg.baseline),
        "experts tuning (len(experts.tasks) x experts.tune.population_size x experts.tune.repetitions)": tuning,
        "experts tuning's fresh scoring (len(experts.tasks) x (experts.tune.restarts + 1) x "
        "experts.tune.eval_repetitions)": scoring,
    }
    for name, n in programs.items():
        if n > most:
            raise ValueError(
                f"env.warp_contacts {cfg.env.warp_contacts} holds {most} episodes, but the {name} program "
                f"runs {n}: set env.warp_contacts to at least {n * kick_env.CONTACTS_PER_EPISODE}"
            )


def experts_section(e) -> None:
    """The experts' starting kicks: their cloning (`experts.bc`) and tuning (`experts.tune`)."""
    positive_ints(e.bc, "experts.bc.", ("steps",))
    positive_floats(e.bc, "experts.bc.", ("learning_rate",))
    positive_ints(e.tune, "experts.tune.", ("repetitions", "eval_repetitions", "population_size", "restarts"))
    polish = e.tune.polish_generations
    if isinstance(polish, bool) or not isinstance(polish, int) or polish < 0:
        raise ValueError(f"experts.tune.polish_generations must be an integer >= 0, got {polish!r}")
    if polish > 0 and e.tune.restarts == 1:
        raise ValueError("experts.tune.polish_generations applies with experts.tune.restarts > 1; set it to 0")
    if isinstance(e.tune.generations, bool) or e.tune.generations < 0:
        raise ValueError(f"experts.tune.generations must be an integer >= 0, got {e.tune.generations!r}")
    if e.tune.population_size < 2:
        raise ValueError(f"experts.tune.population_size must be >= 2 for CMA-ES, got {e.tune.population_size}")
    positive_floats(e.tune, "experts.tune.", ("sigma_init",))
    weight = e.tune.neighbour_leash
    if isinstance(weight, bool) or not isinstance(weight, int | float) or not weight >= 0:
        raise ValueError(f"experts.tune.neighbour_leash must be a number >= 0, got {weight!r}")


def heldout_section(h, preset: str, name: str = "heldout") -> None:
    """The held-out targets, or another section's of its layout (`dev`) under `name`: off the meta-test
    grid, and enough of them for the paper preset (`validation.heldout` checks the rest)."""
    arr = np.asarray(h.targets, np.float64)
    on_grid = np.abs(arr - np.round(arr, 1)) < 0.005 - 1e-9
    if on_grid.any():
        raise ValueError(
            f"{name}.targets: {float(arr[on_grid][0])!r} m lies within 0.005 m of the 0.1 m grid of the "
            f"meta-test tasks; {name} targets must be off it"
        )
    if name == "heldout" and preset == "paper" and len(arr) < HELDOUT_MIN_TARGETS:
        raise ValueError(
            f"{name}.targets holds {len(arr)} targets; the paper preset needs at least {HELDOUT_MIN_TARGETS}"
        )
