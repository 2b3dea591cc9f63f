"""Range checks of the stages' config sections, run before anything compiles (`config.validate` runs them all).

Each raises ValueError naming the dotted key, the bad value and what is allowed.
"""

from __future__ import annotations

import math

import numpy as np

from bumps_jax.algo import ppo_config

SELECTIONS = ("fixed", "halving")  # filter.selection


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


def targets(values, task_range, key: str, unit: str = "m", size: int = 1) -> None:
    """ValueError naming `key` unless `values` is a non-empty list of contexts in the task range
    (size > 1: vectors of `size` numbers, a bad one named whole)."""
    from bumps_jax.envs import base as task_env  # noqa: PLC0415

    if len(values) == 0:
        raise ValueError(f"{key} is empty: give at least one target ({unit})")
    if size > 1 and np.ndim(values) != 2:
        raise ValueError(f"{key} must be a list of contexts of {size} numbers each ({unit}), got {values!r}")
    try:
        task_env.check_targets(values, task_range, unit, size)
    except ValueError as err:
        raise ValueError(f"{key}: {err}") from None


def ppo_section(c, prefix: str, n_steps: int, task_range) -> None:
    ppo_config.validate_config(c, n_steps, prefix)
    if c.sample_task_range is not None:
        targets(c.sample_task_range, task_range, f"{prefix}sample_task_range")


def experts(e, task_range, n_steps: int, unit: str = "m", size: int = 1) -> None:
    targets(e.tasks, task_range, "experts.tasks", unit, size)
    positive_ints(e, "experts.", ("updates_per_chunk", "keep_checkpoints"))
    positive_ints(e.eval, "experts.eval.", ("repetitions",))
    ppo_section(e.ppo, "experts.ppo.", n_steps, task_range)
    chunk_divides(e, "experts.", int(e.ppo.total_env_steps // (e.ppo.num_envs * n_steps)))
    if "family" in e:
        for key in ("centre_updates", "ramp_updates"):
            value = e.family[key]
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 0:
                raise ValueError(f"experts.family.{key} must be an integer >= 0, got {value!r}")
        for key in ("candidates", "rounds"):
            value = e.family.get(key, 1)
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
                raise ValueError(f"experts.family.{key} must be an integer >= 1, got {value!r}")
        if e.family.centre_updates % e.updates_per_chunk:
            raise ValueError(
                f"experts.family.centre_updates {e.family.centre_updates} must be a multiple of "
                f"experts.updates_per_chunk {e.updates_per_chunk} (one compiled chunk size)"
            )
        if e.family.centre_updates:  # a centre phase: when its candidates are compared
            choose_after(e)


def choose_after(e) -> None:
    """`experts.family.choose_after`: within the centre's updates, on a chunk's boundary."""
    m, n = e.family.get("choose_after", 0), e.family.centre_updates
    if isinstance(m, bool) or not isinstance(m, int | np.integer) or not 0 <= m <= n:
        raise ValueError(
            f"experts.family.choose_after must be an integer in [0, experts.family.centre_updates {n}], got {m!r}"
        )
    if m % e.updates_per_chunk:
        raise ValueError(
            f"experts.family.choose_after {m} must be a multiple of experts.updates_per_chunk "
            f"{e.updates_per_chunk} (one compiled chunk size)"
        )


def chunk_divides(section, prefix: str, total: int) -> None:
    """`updates_per_chunk` must divide the updates that `ppo.total_env_steps` buys: one compiled chunk size."""
    if total % section.updates_per_chunk:
        raise ValueError(
            f"{prefix}updates_per_chunk {section.updates_per_chunk} must divide the {total} updates that "
            f"{prefix}ppo.total_env_steps {section.ppo.total_env_steps} buys (one compiled chunk size)"
        )


def meta(m, task_range, unit: str = "m", size: int = 1) -> None:
    p = "meta."
    positive_ints(m.train, f"{p}train.", ("batch_size", "epochs", "chunk", "n_seeds", "decay_every"))
    if m.train.epochs % m.train.chunk:
        raise ValueError(f"{p}train.epochs {m.train.epochs} must be a multiple of {p}train.chunk {m.train.chunk}")
    positive_floats(m.train, f"{p}train.", ("learning_rate",))
    if not 0 < m.train.decay_rate <= 1:
        raise ValueError(f"{p}train.decay_rate must be in (0, 1], got {m.train.decay_rate!r}")
    positive_ints(m.dataset, f"{p}dataset.", ("repetitions",))
    noise = m.dataset.action_noise
    if isinstance(noise, bool) or not isinstance(noise, int | float) or not math.isfinite(noise) or noise < 0:
        raise ValueError(f"{p}dataset.action_noise must be a finite std >= 0, got {noise!r}")
    positive_ints(m.eval, f"{p}eval.", ("repetitions",))
    targets(m.eval.tasks, task_range, f"{p}eval.tasks", unit, size)
    for name, arch in m.nets.items():
        if len(arch) != 2 or min(arch) < 1:
            raise ValueError(f"{p}nets.{name} must be (hidden layers >= 1, width >= 1), got {tuple(arch)!r}")


def filtering(f, task_range, unit: str = "m", size: int = 1) -> None:
    p = "filter."
    targets(f.tasks, task_range, f"{p}tasks", unit, size)
    targets(f.context_range, task_range, f"{p}context_range", unit)
    low, high = (tuple(f.context_range) + (None, None))[:2]
    if len(f.context_range) != 2 or not low < high:
        raise ValueError(f"{p}context_range must be (low, high) with low < high, got {tuple(f.context_range)}")
    positive_floats(f, p, ("width", "context_step", "high_context_step"))
    for key in ("context_step", "high_context_step"):
        if f[key] > high - low:
            raise ValueError(f"{p}{key} {f[key]!r} {unit} exceeds {p}context_range's width {high - low:g} {unit}: "
                             "its grid would hold one context")  # fmt: skip
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


def baseline(b, task_range, n_steps: int, unit: str = "m", size: int = 1) -> None:
    """The multi-task baseline's section."""
    p = "baseline."
    positive_ints(b, p, ("seeds", "eval_repetitions", "updates_per_chunk", "keep_checkpoints"))
    targets(b.eval_tasks, task_range, f"{p}eval_tasks", unit, size)
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


def heldout(h, task_range, name: str = "heldout") -> None:
    """The held-out section, or another of its layout (the kick's `dev`) under `name`."""
    targets(h.targets, task_range, f"{name}.targets")
    positive_ints(h, f"{name}.", ("repetitions", "selection_repetitions"))
    if isinstance(h.seed, bool) or not isinstance(h.seed, int) or h.seed < 0:
        raise ValueError(f"{name}.seed must be an integer >= 0, got {h.seed!r}")
