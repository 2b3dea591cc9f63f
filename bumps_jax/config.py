"""The pipeline's one config tree, its presets, and `--set` overrides checked against it.

    cfg = make_config("tiny", {"env.physics_dt": 0.005, "experts.tasks": (9.0,)})
    cfg = make_config("tiny", {"task": "cheetah_vel", "experts.seed": 3})

The tree is the selected task's (`Task.sections`, in its folder's `config.py`): one section per
stage it runs plus the env every stage builds its simulation from:

    preset    "tiny" (a CPU, minutes) | "paper" (the paper's budgets, a GPU)
    task      the contextual task every stage runs (`tasks.registry`; the kick by default)
    env       the task's physics, noise and reward
    experts   one PPO expert per training context (`schema.sections.experts`)
    meta      behaviour cloning into the contextual meta-policies, and their evaluation
    filter    policy filtering over sampled contexts (Table 2)
    baseline  the multi-task PPO baseline (the paper's Figure 1)
    heldout   the held-out evaluation (`evaluate --heldout`), where the task has one

and the sections its plug-ins read (the kick's `prior` and `dev`). Defaults are the `paper`
preset; a preset is dotted overrides of them (`Task.presets`); a task's derived keys (the
baseline's budget from its experts') follow both (`derive`). Every value a user can set is a
leaf with a comment saying what it does; `docs/decisions.md` says how the numbers were chosen
and which settings lost; the kick's `config.py` says which of its paper values are not the paper's.
"""

from __future__ import annotations

import json
import math

import ml_collections
from ml_collections import FieldReference

from bumps_jax.records import differing_keys, jsonable
from bumps_jax.tasks import registry as tasks

PRESETS = ("tiny", "paper")


def default_config(task: str = tasks.DEFAULT) -> ml_collections.ConfigDict:
    """`task`'s whole tree at its defaults (unlocked): the `paper` preset."""
    cfg = ml_collections.ConfigDict()
    cfg.preset = "paper"  # the preset this tree was made from (recorded; set by `make_config`)
    cfg.task = tasks.check_task(task)  # the contextual task every stage runs (set by `make_config`)
    for name, section in tasks.get(task).sections().items():
        cfg[name] = section
    derive(cfg)
    return cfg


def derive(cfg: ml_collections.ConfigDict, given=frozenset()) -> None:
    """Set the task's derived keys (its config module's `DERIVED`: (key, function of the tree)
    pairs, in order, each seeing those before it), but the keys in `given` (set by the preset or
    the user): a value computed from others follows them after every override."""
    for key, compute in getattr(tasks.get(cfg.task).config, "DERIVED", ()):
        if key not in given:
            set_leaf(cfg, key, compute(cfg))


def make_config(preset: str = "tiny", overrides: dict | None = None) -> ml_collections.ConfigDict:
    """The locked config of `preset` with dotted `overrides` ({"experts.ppo.learning_rate": 1e-5});
    the task is `overrides["task"]` (default: the kick).

    ValueError, naming the key and value, for an unknown preset, task or key, or a value of the
    wrong type; then every section's own checks (`validate`).
    """
    overrides = dict(overrides or {})
    task = tasks.check_task(overrides.pop("task", tasks.DEFAULT))
    presets = tasks.get(task).presets
    if preset not in presets:
        raise ValueError(f"unknown preset {preset!r}; choose one of {sorted(presets)}")
    cfg = default_config(task)
    cfg.preset = preset
    cfg.lock()
    given = {**presets[preset], **overrides}
    for key, value in given.items():
        set_leaf(cfg, key, value)
    tasks.get(task).env_class.validate_config(cfg.env)  # before the derived keys, which may divide by its values
    derive(cfg, frozenset(given))
    validate(cfg)
    return cfg


def set_leaf(cfg: ml_collections.ConfigDict, key: str, value) -> None:
    """cfg[key] = value for a dotted key, the value checked against the leaf's type."""
    *parents, leaf = key.split(".")
    node = cfg
    for i, part in enumerate(parents):
        if not isinstance(node, ml_collections.ConfigDict) or part not in node:
            raise ValueError(
                f"unknown config key {key!r} (no section {'.'.join(parents[: i + 1])!r}){_nearest(cfg, key)}"
            )
        node = node[part]
    if not isinstance(node, ml_collections.ConfigDict) or leaf not in node:
        raise ValueError(f"unknown config key {key!r}{_nearest(cfg, key)}")
    if isinstance(node[leaf], ml_collections.ConfigDict):
        raise ValueError(f"config key {key!r} is a section; set one of its keys: {sorted(node[leaf])}")
    optional = isinstance(node._fields.get(leaf), FieldReference)  # declared with a type: may be null
    node[leaf] = coerce(key, value, node.get_type(leaf), node[leaf], optional)


def _nearest(cfg: ml_collections.ConfigDict, key: str) -> str:
    """'; did you mean ...' naming the valid dotted keys nearest `key` (or its last part), else ''."""
    import difflib  # noqa: PLC0415

    def leaves(node, prefix=""):
        for k, v in node.items():
            yield from leaves(v, f"{prefix}{k}.") if isinstance(v, ml_collections.ConfigDict) else [f"{prefix}{k}"]

    keys = list(leaves(cfg))
    near = difflib.get_close_matches(key, keys, n=3, cutoff=0.6)
    near += [k for k in keys if k.rsplit(".", 1)[-1] == key.rsplit(".", 1)[-1] and k not in near][: 3 - len(near)]
    return f"; did you mean {', '.join(near)}?" if near else "; python -m bumps_jax config lists every key"


def coerce(key: str, value, kind: type, current, optional: bool = False):
    """`value` as the type of a leaf (kind; current: its value now; optional: null allowed), or
    ValueError naming the key, the value and what the leaf takes."""

    def bad(expected: str):
        return ValueError(f"--set {key}={json.dumps(value, default=str)}: expected {expected}")

    if value is None:
        if optional or current is None:
            return value
        raise bad(f"a value of type {kind.__name__}, not null")
    if kind is bool:
        if isinstance(value, bool):
            return value
        raise bad("true or false")
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad("an integer")
        return value
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise bad("a finite number")
        return float(value)
    if kind is str:
        if not isinstance(value, str):
            raise bad("a string")
        return value
    if kind is tuple:
        if not isinstance(value, list | tuple):
            example = json.dumps(list(current)[:3])[:-1] + (", ...]" if len(current) > 3 else "]")
            raise bad(f"a list like {example}")
        items = list(value)
        if current and all(isinstance(c, str) for c in current):
            if not all(isinstance(v, str) for v in items):
                raise bad("a list of strings")
            return tuple(items)
        if current and all(isinstance(c, list | tuple) for c in current):
            return tuple(tuple(v) if isinstance(v, list) else v for v in items)
        if not all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in items):
            raise bad("a list of numbers")
        ints = current and all(isinstance(c, int) for c in current)
        if ints and not all(isinstance(v, int) for v in items):
            raise bad("a list of integers")
        return tuple(items if ints else [float(v) for v in items])
    return value


def validate(cfg: ml_collections.ConfigDict) -> None:
    """Every section's range checks, then the task's own (`Task.validate`: its plug-ins' sections,
    its capacities); ValueError naming the first bad value. The env's own checks (its class's
    `validate_config`) ran first, in `make_config`, before the derived keys read the env."""
    from bumps_jax.envs import base as task_env  # noqa: PLC0415
    from bumps_jax.schema import validation  # noqa: PLC0415 (the checks import the algorithm modules)

    task = tasks.get(cfg.task)
    task_env.validate_task_range(cfg.env.task_range)  # every context is checked against it
    n_steps, task_range, unit = task.env_class.n_steps_of(cfg.env), tuple(cfg.env.task_range), task.unit
    size = task.env_class.CONTEXT_SIZE  # numbers in one context
    checks = {"experts": lambda: validation.experts(cfg.experts, task_range, n_steps, unit, size),
              "meta": lambda: validation.meta(cfg.meta, task_range, unit, size),
              "filter": lambda: validation.filtering(cfg.filter, task_range, unit, size),
              "baseline": lambda: validation.baseline(cfg.baseline, task_range, n_steps, unit, size),
              "heldout": lambda: validation.heldout(cfg.heldout, task_range)}  # fmt: skip
    for name, check in checks.items():
        if name in cfg:  # a section per stage the task runs
            check()
    if "meta" in cfg and "experts" in cfg:  # the pairs the meta stage records (`meta.collect_dataset`)
        from bumps_jax.algo import bc  # noqa: PLC0415

        e, k = len(cfg.experts.tasks), cfg.meta.dataset.repetitions
        how = f" ({e} experts x {k} episode(s) x {n_steps} steps)"
        bc.check_batch_size(cfg.meta.train, e * k * n_steps, "meta.train.batch_size", how)
    if "meta" in cfg and cfg.meta.dataset.clip_labels and task.env_class.ACTION_BOUND is None:
        raise ValueError(f"meta.dataset.clip_labels: the {cfg.task} env clips no action (its ACTION_BOUND is None), "
                         "so there is no bound to clip the labels to: set it false")  # fmt: skip
    if "filter" in cfg and "meta" in cfg and cfg.filter.net_seed >= cfg.meta.train.n_seeds:
        raise ValueError(
            f"filter.net_seed {cfg.filter.net_seed} names no network: meta.train.n_seeds is {cfg.meta.train.n_seeds}"
        )
    task.validate(cfg)


# Keys that joined a stage's section after runs were made, with the value that changes nothing:
# a section leaves such a key out at that value, so runs made before it still resume.
ADDED_KEYS = {"potential_shaping": 0.0}  # under any PPO section


def section(cfg: ml_collections.ConfigDict, stage: str) -> dict:
    """What one stage's results depend on, as plain data: its section, the task, its env (as
    records carry it) and the preset; keys of `ADDED_KEYS` at their value that changes nothing left out."""
    body = without_added(jsonable(cfg[stage].to_dict()))
    return {"preset": cfg.preset, "task": cfg.task, "env": resolved_env(cfg), stage: body}


# Sections deleted from the tree (their experiment lost; docs/decisions.md), each with the key and
# value at which an older record's result is one made without them: such a record still matches.
REMOVED_SECTIONS = {"meta.dagger": ("rounds", 0)}  # DAgger: 0 rounds was plain cloning


def without_removed(tree: dict) -> dict:
    """An older record's stage section (`section`'s layout) less every `REMOVED_SECTIONS` section
    that holds its value that changes nothing; one that did something is kept, and so differs."""
    out = json.loads(json.dumps(tree))
    for dotted, (key, inert) in REMOVED_SECTIONS.items():
        *parents, leaf = dotted.split(".")
        node = out
        for part in parents:
            node = node.get(part) if isinstance(node, dict) else None
        if isinstance(node, dict) and isinstance(node.get(leaf), dict) and node[leaf].get(key) == inert:
            del node[leaf]
    return out


def without_added(tree):
    """A nested dict less every `ADDED_KEYS` key holding its value that changes nothing."""
    if not isinstance(tree, dict):
        return tree
    return {k: without_added(v) for k, v in tree.items() if not (k in ADDED_KEYS and v == ADDED_KEYS[k])}


def resolved_env(cfg: ml_collections.ConfigDict) -> dict:
    """The task's env config as records carry it (`Task.resolved_env`)."""
    return tasks.resolved(cfg.task, cfg.env)


def overrides_of(cfg: ml_collections.ConfigDict) -> dict:
    """{dotted key: value} of every leaf where `cfg` differs from its preset, but a derived key
    (`derive`) that holds what the rest of the tree gives it: it followed an override, none itself."""
    base, mine = jsonable(make_config(cfg.preset, {"task": cfg.task}).to_dict()), jsonable(cfg.to_dict())
    derived = dict(getattr(tasks.get(cfg.task).config, "DERIVED", ()))
    out = {}
    for key in differing_keys(base, mine):
        value = mine
        for part in key.split("."):
            value = value[part]
        if key not in derived or value != jsonable(derived[key](cfg)):
            out[key] = value
    return out


# The keys a pipeline seed sets: every stage's training randomness, not the evaluations' noise
# (the same episodes score every seed). A task's config module adds its own (`TRAINING_SEEDS`).
TRAINING_SEEDS = ("experts.seed", "meta.dataset.seed", "meta.train.seed", "filter.seed")


def training_seed_keys(task: str) -> tuple[str, ...]:
    """The keys a pipeline seed sets for `task`: the stages' and its config module's own."""
    return TRAINING_SEEDS + tuple(getattr(tasks.get(task).config, "TRAINING_SEEDS", ()))


def seeded(cfg: ml_collections.ConfigDict, seed: int) -> ml_collections.ConfigDict:
    """`cfg` with every training seed set to `seed` (its preset and other overrides kept)."""
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"--seeds: a seed must be an integer >= 0, got {seed!r}")
    kept = {k: tuple(v) if isinstance(v, list) else v for k, v in overrides_of(cfg).items()}
    return make_config(cfg.preset, {"task": cfg.task, **kept, **dict.fromkeys(training_seed_keys(cfg.task), seed)})
