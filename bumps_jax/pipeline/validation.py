"""Range checks of the whole config tree, run before anything compiles.

Each raises ValueError naming the dotted key, the bad value and what is allowed.
"""

from __future__ import annotations

import math

import ml_collections
import numpy as np

from bumps_jax.algo import ppo_config
from bumps_jax.pipeline.added_knobs import ADDED_KNOBS
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model

# The paper preset's held-out set must hold at least this many targets.
HELDOUT_MIN_TARGETS = 50

TUNE_SCHEMES = ("per_task", "family")  # experts.tune.scheme
TUNE_KEEPS = ("run", "task", "chain")  # experts.tune.keep
SELECTIONS = ("fixed", "halving")  # filter.selection
META_TRAINERS = ("separate", "stacked", "stacked_batched")  # meta.trainer
META_INPUTS = ("unit", "raw", "centred")  # meta.inputs


def validate(cfg: ml_collections.ConfigDict) -> None:
    """Every section of a pipeline config (`config.make_config`): the kick's always, another
    task's (`task`) when it is the one selected."""
    from bumps_jax.tasks import registry as tasks  # noqa: PLC0415

    tasks.check_task(cfg.task)
    kick_env.validate_config(cfg.env)
    n_steps = int(round(cfg.env.horizon_s / cfg.env.ctrl_dt))
    task_range = tuple(cfg.env.task_range)
    prior(cfg.prior)
    experts(cfg.experts, task_range, n_steps)
    meta(cfg.meta, task_range)
    filtering(cfg.filter, task_range)
    baseline(cfg.baseline, task_range, n_steps)
    heldout(cfg.heldout, task_range, cfg.preset)
    heldout(cfg.dev, task_range, cfg.preset, "dev")
    shared = [t for t in cfg.dev.targets if np.min(np.abs(np.asarray(cfg.heldout.targets) - t)) < 0.005]
    if shared:
        raise ValueError(f"dev.targets: {shared[0]!r} m lies within 0.005 m of a held-out target; keep them apart")
    if cfg.dev.seed == cfg.heldout.seed:
        raise ValueError(f"dev.seed {cfg.dev.seed} is heldout.seed: the development noise must be its own")
    physics_capacity(cfg)
    if cfg.filter.net_seed >= cfg.meta.train.n_seeds:
        raise ValueError(
            f"filter.net_seed {cfg.filter.net_seed} names no network: meta.train.n_seeds is {cfg.meta.train.n_seeds}"
        )
    if cfg.task == "cheetah_vel":
        cheetah_vel(cfg.cheetah_vel, "cheetah_vel.")
    if cfg.task == "point_goal":
        from bumps_jax.tasks.point_goal import config as point_goal_config  # noqa: PLC0415

        point_goal_config.validate(cfg.point_goal, "point_goal.")


def cheetah_vel(c, prefix: str) -> None:
    """HalfCheetah-Vel's sections (`cheetah_config.sections`); keys named with `prefix`."""
    from bumps_jax.tasks.cheetah_vel import env as cheetah_env  # noqa: PLC0415

    try:
        cheetah_env.validate_config(c.env)
    except ValueError as err:
        raise ValueError(f"{prefix}{err}") from None
    n_steps, task_range, unit = int(c.env.episode_steps), tuple(c.env.task_range), "m/s"
    e = c.experts
    targets(e.tasks, task_range, f"{prefix}experts.tasks", unit)
    positive_ints(e, f"{prefix}experts.", ("updates_per_chunk", "keep_checkpoints"))
    positive_ints(e.eval, f"{prefix}experts.eval.", ("repetitions",))
    ppo_section(e.ppo, f"{prefix}experts.ppo.", n_steps, task_range)
    chunk_divides(e, f"{prefix}experts.", int(e.ppo.total_env_steps // (e.ppo.num_envs * n_steps)))
    meta(c.meta, task_range, prefix, unit, task="cheetah_vel")
    filtering(c.filter, task_range, prefix, unit)
    if c.filter.net_seed >= c.meta.train.n_seeds:
        raise ValueError(f"{prefix}filter.net_seed {c.filter.net_seed} names no network: "
                         f"{prefix}meta.train.n_seeds is {c.meta.train.n_seeds}")  # fmt: skip
    baseline(c.baseline, task_range, n_steps, prefix, unit)
    if c.env.impl == "warp":
        per_episode = cheetah_env.contacts_per_episode(bool(c.env.all_contacts))
        for name, n in (("experts", len(e.tasks) * e.ppo.num_envs), ("baseline", baseline_runs(c.baseline))):
            if n > c.env.warp_contacts // per_episode:
                raise ValueError(
                    f"{prefix}env.warp_contacts {c.env.warp_contacts} holds {c.env.warp_contacts // per_episode} "
                    f"episodes, but the {name} program runs {n}: set it to at least {n * per_episode}"
                )


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
        "baseline (baseline.seeds x learning rates x baseline.ppo.num_envs)": baseline_runs(cfg.baseline),
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


def positive_ints(node, prefix: str, keys) -> None:
    for key in keys:
        value = node[key]
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
            raise ValueError(f"{prefix}{key} must be a positive integer, got {value!r}")


def positive_floats(node, prefix: str, keys) -> None:
    for key in keys:
        value = node[key]
        if not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
            raise ValueError(f"{prefix}{key} must be > 0, got {value!r}")


def targets(values, task_range, key: str, unit: str = "m") -> None:
    from bumps_jax.envs import base as task_env  # noqa: PLC0415

    if len(values) == 0:
        raise ValueError(f"{key} is empty: give at least one target ({unit})")
    try:
        task_env.check_targets(values, task_range, unit)
    except ValueError as err:
        raise ValueError(f"{key}: {err}") from None


def prior(p) -> None:
    from bumps_jax.tasks.kick import keyframes as kick_model  # noqa: PLC0415

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


def ppo_section(c, prefix: str, n_steps: int, task_range) -> None:
    ppo_config.validate_config(c, n_steps, prefix)
    if c.sample_task_range is not None:
        targets(c.sample_task_range, task_range, f"{prefix}sample_task_range")


def experts(e, task_range, n_steps: int) -> None:
    targets(e.tasks, task_range, "experts.tasks")
    positive_ints(e, "experts.", ("updates_per_chunk", "keep_checkpoints"))
    positive_ints(e.bc, "experts.bc.", ("steps",))
    positive_floats(e.bc, "experts.bc.", ("learning_rate",))
    if e.bc.common_start not in kick_model.ANCHORS:
        raise ValueError(f"experts.bc.common_start must be one of {kick_model.ANCHORS}, got {e.bc.common_start!r}")
    if e.bc.per_task_strength and (e.bc.common_start != "main" or e.bc.common_start_strength):
        raise ValueError(
            "experts.bc.common_start and common_start_strength apply when every task starts from one kick: "
            "set experts.bc.per_task_strength to false"
        )
    positive_ints(e.tune, "experts.tune.", ("repetitions", "eval_repetitions", "population_size", "restarts"))
    if e.tune.keep not in TUNE_KEEPS:
        raise ValueError(f"experts.tune.keep must be one of {TUNE_KEEPS}, got {e.tune.keep!r}")
    if not isinstance(e.tune.batch_restarts, bool):
        raise ValueError(f"experts.tune.batch_restarts must be true or false, got {e.tune.batch_restarts!r}")
    polish = e.tune.polish_generations
    if isinstance(polish, bool) or not isinstance(polish, int) or polish < 0:
        raise ValueError(f"experts.tune.polish_generations must be an integer >= 0, got {polish!r}")
    if polish > 0 and e.tune.keep == "run":
        raise ValueError(
            "experts.tune.polish_generations applies with experts.tune.keep 'task' or 'chain'; set it to 0"
        )
    if isinstance(e.tune.generations, bool) or e.tune.generations < 0:
        raise ValueError(f"experts.tune.generations must be an integer >= 0, got {e.tune.generations!r}")
    if e.tune.population_size < 2:
        raise ValueError(f"experts.tune.population_size must be >= 2 for CMA-ES, got {e.tune.population_size}")
    positive_floats(e.tune, "experts.tune.", ("sigma_init", "polish_sigma"))
    if e.tune.scheme not in TUNE_SCHEMES:
        raise ValueError(f"experts.tune.scheme must be one of {TUNE_SCHEMES}, got {e.tune.scheme!r}")
    for name in ("start_leash", "neighbour_leash", "midpoint_weight"):
        weight = e.tune[name]
        if isinstance(weight, bool) or not isinstance(weight, int | float) or not weight >= 0:
            raise ValueError(f"experts.tune.{name} must be a number >= 0, got {weight!r}")
    if e.tune.scheme == "family":
        # The per-task knobs that are on, each named with the value that turns it off (the value
        # the code behaved as before the knob existed): all in one line, so that switching a
        # preset that uses several of them (the paper's) takes one try.
        per_task = ("restarts", "polish_generations", "start_leash", "neighbour_leash", "midpoint_weight")
        off = {k: ADDED_KNOBS[f"experts.tune.{k}"] for k in per_task}
        on = [f"experts.tune.{k}={v:g}" for k, v in off.items() if e.tune[k] != v]
        if on:
            raise ValueError(f"experts.tune.scheme 'family' has no per-task tuning knobs: set {', '.join(on)}")
    if isinstance(e.tune.knots, bool) or e.tune.knots < 2:
        raise ValueError(f"experts.tune.knots must be an integer >= 2, got {e.tune.knots!r}")
    if e.tune.scheme == "family" and len(set(e.tasks)) < 2:
        raise ValueError(
            f"experts.tune.scheme 'family' needs at least two distinct experts.tasks, got {tuple(e.tasks)}"
        )
    positive_ints(e.eval, "experts.eval.", ("repetitions",))
    ppo_section(e.ppo, "experts.ppo.", n_steps, task_range)
    total = int(e.ppo.total_env_steps // (e.ppo.num_envs * n_steps))
    chunk_divides(e, "experts.", total)


def chunk_divides(section, prefix: str, total: int) -> None:
    """`updates_per_chunk` must divide the updates that `ppo.total_env_steps` buys: one compiled chunk size."""
    if total % section.updates_per_chunk:
        raise ValueError(
            f"{prefix}updates_per_chunk {section.updates_per_chunk} must divide the {total} updates that "
            f"{prefix}ppo.total_env_steps {section.ppo.total_env_steps} buys (one compiled chunk size)"
        )


def meta(m, task_range, prefix: str = "", unit: str = "m", task: str = "kick") -> None:
    p = f"{prefix}meta."
    positive_ints(m.train, f"{p}train.", ("batch_size", "epochs", "chunk", "n_seeds", "decay_every", "unroll"))
    if m.train.epochs % m.train.chunk:
        raise ValueError(f"{p}train.epochs {m.train.epochs} must be a multiple of {p}train.chunk {m.train.chunk}")
    positive_floats(m.train, f"{p}train.", ("learning_rate",))
    if not 0 < m.train.decay_rate <= 1:
        raise ValueError(f"{p}train.decay_rate must be in (0, 1], got {m.train.decay_rate!r}")
    if m.trainer not in META_TRAINERS:
        raise ValueError(f"{p}trainer must be one of {META_TRAINERS}, got {m.trainer!r}")
    if m.inputs not in META_INPUTS:
        raise ValueError(f"{p}inputs must be one of {META_INPUTS}, got {m.inputs!r}")
    if task != "kick" and m.inputs != "unit":  # another task's nets read its states normalised by the dataset
        raise ValueError(f"{p}inputs {m.inputs!r} is for the kick's (time step, target); this task's nets read "
                         "its states normalised by the dataset: leave it at 'unit'")  # fmt: skip
    positive_ints(m.dataset, f"{p}dataset.", ("repetitions",))
    positive_ints(m.eval, f"{p}eval.", ("repetitions",))
    targets(m.eval.tasks, task_range, f"{p}eval.tasks", unit)
    for name, arch in m.nets.items():
        if len(arch) != 2 or min(arch) < 1:
            raise ValueError(f"{p}nets.{name} must be (hidden layers >= 1, width >= 1), got {tuple(arch)!r}")


def filtering(f, task_range, prefix: str = "", unit: str = "m") -> None:
    p = f"{prefix}filter."
    targets(f.tasks, task_range, f"{p}tasks", unit)
    targets(f.context_range, task_range, f"{p}context_range", unit)
    positive_floats(f, p, ("width", "context_step", "high_context_step"))
    positive_ints(f, p, ("selection_repetitions", "eval_repetitions"))
    if f.selection not in SELECTIONS:
        raise ValueError(f"{p}selection must be one of {SELECTIONS}, got {f.selection!r}")
    rungs = tuple(f.halving_rungs)
    if (
        not rungs
        or any(isinstance(r, bool) or not isinstance(r, int) or r < 1 for r in rungs)
        or any(b <= a for a, b in zip(rungs, rungs[1:], strict=False))
    ):
        raise ValueError(f"{p}halving_rungs must be increasing positive integers, got {rungs}")
    if not 0.0 < f.halving_keep < 1.0:
        raise ValueError(f"{p}halving_keep must be in (0, 1), got {f.halving_keep!r}")
    if isinstance(f.net_seed, bool) or f.net_seed < 0:
        raise ValueError(f"{p}net_seed must be an integer >= 0, got {f.net_seed!r}")
    if f.block is not None:
        positive_ints(f, p, ("block",))


def baseline(b, task_range, n_steps: int, prefix: str = "", unit: str = "m") -> None:
    """The multi-task baseline's section (the kick's, or another task's under `prefix`, which has no clone)."""
    p = f"{prefix}baseline."
    cloned = ("bc_steps",) if "bc_steps" in b else ()
    positive_ints(b, p, ("seeds", *cloned, "eval_repetitions", "updates_per_chunk", "keep_checkpoints"))
    if cloned:
        positive_floats(b, p, ("bc_learning_rate",))
    targets(b.eval_tasks, task_range, f"{p}eval_tasks", unit)
    ppo_section(b.ppo, f"{p}ppo.", n_steps, task_range)
    chunk_divides(b, p, int(b.ppo.total_env_steps // (b.ppo.num_envs * n_steps)))
    if b.ppo.sample_task_range is None:
        raise ValueError(f"{p}ppo.sample_task_range must be (low, high): the baseline is multi-task")
    if b.extra_learning_rate is not None:
        positive_floats(b, p, ("extra_learning_rate",))
        if b.extra_learning_rate == b.ppo.learning_rate:
            raise ValueError(f"{p}extra_learning_rate {b.extra_learning_rate!r} is the paper arm's own rate")
    if b.ppo.anneal_learning_rate:
        raise ValueError(f"{p}ppo.anneal_learning_rate must be false: the baseline's arms keep a constant rate")


def baseline_runs(b) -> int:
    """Episodes of one baseline update: seeds x learning rates x ppo.num_envs."""
    return b.seeds * (1 if b.extra_learning_rate is None else 2) * b.ppo.num_envs


def heldout(h, task_range, preset: str, name: str = "heldout") -> None:
    """The held-out section, or another of its layout (`dev`) under `name`."""
    targets(h.targets, task_range, f"{name}.targets")
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
    positive_ints(h, f"{name}.", ("repetitions", "selection_repetitions"))
    if isinstance(h.seed, bool) or not isinstance(h.seed, int) or h.seed < 0:
        raise ValueError(f"{name}.seed must be an integer >= 0, got {h.seed!r}")
