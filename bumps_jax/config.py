"""The pipeline's one config tree, its presets, and `--set` overrides checked against it.

    cfg = make_config("tiny", {"env.physics_dt": 0.005, "experts.tasks": (9.0,)})

The tree has one section per stage plus the env every stage builds its simulation from:

    preset                       "tiny" | "paper"
    task                         "kick" (the paper's, the default) | "cheetah_vel"
    env       kick_env.default_config(): physics, task, noise, reward
    prior     the keyframe kick prior (CMA-ES)
    experts   one PPO expert per task: starting kicks, cloning, PPO, evaluation
    meta      behaviour cloning into the contextual meta-policies, and their evaluation
    filter    policy filtering over sampled contexts (Table 2)
    baseline  the multi-task PPO baseline (the paper's Figure 1)
    heldout   the held-out evaluation (`evaluate --heldout`): targets and noise no other stage uses
    dev       the same evaluation on development targets and noise (`evaluate --dev`), for design choices
    cheetah_vel  HalfCheetah-Vel's own env, experts, meta and filter sections (`task: cheetah_vel`;
                 built in `cheetah_config`)

The sections at the top are the kick's. Another task's sections live under its name and have the
same layout where the stages share code; `task_view` puts the selected task's at the top, and a
task's stages read only that view.

Defaults are the `paper` preset (the paper's budgets, for a GPU); `tiny` overrides the
sizes so that the whole pipeline runs on a CPU in minutes. Every value a user can set is a
leaf here; `docs/decisions.md` says how the numbers were chosen.
"""

from __future__ import annotations

import copy
import json
import math

import ml_collections
from ml_collections import FieldReference

from bumps_jax.algo import ppo_config
from bumps_jax.pipeline.records import differing_keys, jsonable
from bumps_jax.tasks import registry as tasks
from bumps_jax.tasks.cheetah_vel import config as cheetah_config
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick.targets import DEV_TARGETS, HELDOUT_TARGETS
from bumps_jax.tasks.point_goal import config as point_goal_config


def _prior() -> ml_collections.ConfigDict:
    cfg = ml_collections.ConfigDict()
    cfg.target = 12.0  # m: the main kick is tuned for the middle of the task range
    # Targets allowed while tuning: wide enough for the short and long ends of the kick family.
    cfg.task_range = (5.0, 25.0)
    cfg.extremes = ml_collections.ConfigDict({"short": 6.0, "long": 21.0})  # m: the family's ends
    cfg.population_size = 64  # CMA-ES candidates per generation
    cfg.generations = 80
    cfg.repetitions = 16  # noisy episodes per candidate per generation
    cfg.eval_repetitions = 100  # fresh noisy episodes scoring the best kick
    cfg.sigma_init = 1.0  # CMA-ES step, in units of the kick model's PARAM_SCALE
    cfg.seed = 0
    # Kick record the main search starts from ("": the committed assets/kick_prior.json). A run
    # copies it into its directory first, so a rerun starts from the same kick.
    cfg.start = ""
    cfg.start_strength = 0.75  # the main kick's swing speed cap, leaving headroom for longer kicks
    # Parameters the main search moves (the extremes move all); strength stays at start_strength.
    cfg.free_params = (
        "lean", "support_hip", "support_ankle", "t_shift", "t_lift", "back_hip", "back_knee",
        "back_ankle", "t_back", "swing_hip", "swing_knee", "swing_ankle", "t_swing",
    )  # fmt: skip
    cfg.sweep_strengths = tuple(i / 8 for i in range(9))  # along short (0) -> main (0.5) -> long (1)
    cfg.fitness = ml_collections.ConfigDict()
    cfg.fitness.distance = 1.0  # cost per metre of resting error along the kick line
    cfg.fitness.lateral = 2.0  # cost per metre sideways
    cfg.fitness.invalid = 20.0  # cost of a fall, a miss or a blow-up
    return cfg


def _experts() -> ml_collections.ConfigDict:
    cfg = ml_collections.ConfigDict()
    cfg.tasks = kick_env.meta_train_tasks()  # m, one expert each
    cfg.seed = 0
    cfg.updates_per_chunk = 25  # PPO updates per compiled chunk; progress and a checkpoint between
    cfg.keep_checkpoints = 3
    cfg.bc = ml_collections.ConfigDict()
    cfg.bc.steps = 20000  # full-batch Adam steps cloning the starting kick (cosine decay)
    cfg.bc.learning_rate = 1e-2
    # Where each task's starting kick begins, before tuning: True, the prior's family at the
    # task's calibrated strength (with `tune.anchor_starts`, the best of that and the prior's
    # anchors); False, one kick (`common_start`) for every task, so that the tuned kicks are one family.
    cfg.bc.per_task_strength = False
    # With per_task_strength False: the prior's anchor every task starts from (`kick_model.ANCHORS`).
    cfg.bc.common_start = "long"
    # With per_task_strength False: True sets each task's copy of that kick to the strength at
    # which it rests nearest the task's target (read from a noisy sweep of its strength,
    # `tune.eval_repetitions` episodes per strength), so that the tasks start spread over their
    # targets as one kick; False keeps the kick's own strength for every task.
    cfg.bc.common_start_strength = True
    cfg.tune = ml_collections.ConfigDict()  # CMA-ES on every task's starting kick, all at once
    cfg.tune.generations = 60  # 0: clone the (blended or anchor) kick as it is
    cfg.tune.sigma_init = 2.0  # in PARAM_SCALE units around each task's start
    cfg.tune.population_size = 32
    cfg.tune.repetitions = 8  # noisy kicks per candidate per generation
    cfg.tune.eval_repetitions = 32  # fresh kicks choosing between start and tuned
    cfg.tune.seed = 0
    # "per_task" only: independent runs of the whole tuning (different CMA-ES keys); the one whose
    # kicks cost least over all tasks on fresh episodes is kept whole. Each run costs a tuning.
    cfg.tune.restarts = 1
    # restarts > 1 only: True plays the runs as one batch (each physics call holds every run's
    # episodes; the tuning's env gets a contact pool restarts x env.warp_contacts), each run from
    # its own key as it would alone: the same runs, sooner where the device has room to spare.
    cfg.tune.batch_restarts = False
    # With restarts > 1, what is kept: "run", the run above whole (one chain); "task", each task
    # the cheapest on those fresh episodes of its start and its kick in every run (runs mixed);
    # "chain", the same kicks chosen together: fresh costs plus the neighbour leash between them.
    cfg.tune.keep = "run"
    # keep "task" or "chain" only: generations of one more tuning from the mixed kicks (the same
    # leashes, its own key), each task again keeping the better of the two; 0: none. It re-joins
    # the chain where neighbouring tasks came from different runs.
    cfg.tune.polish_generations = 0
    # keep "task" or "chain" only: the polish's initial CMA-ES step (PARAM_SCALE units); 2.0 is
    # the tuning's own sigma_init, the step the polish took before this knob existed.
    cfg.tune.polish_sigma = 2.0
    # Start each task from the best of its blended kick and the prior's three anchors.
    cfg.tune.anchor_starts = True
    # "per_task": one CMA-ES per task on its own kick. "family": one CMA-ES over a contextual
    # kick, every parameter linear in the target between `knots` evenly spaced knots over the
    # tasks' range, started from the (blended or anchor) kicks at the knots and scored on every
    # task at once. Which one the paper run uses is open (docs/decisions.md).
    cfg.tune.scheme = "per_task"
    cfg.tune.knots = 5  # knots of the "family" scheme's contextual kick (>= 2)
    # "per_task" only: cost per squared PARAM_SCALE unit of a candidate's mean distance from its
    # task's start, added to its kick cost during the search (0: the kick cost alone). > 0 keeps
    # tuned kicks near their starts, so tasks that start from the same kick stay one family.
    cfg.tune.start_leash = 0.0
    # "per_task" only: cost per squared PARAM_SCALE unit of a candidate's mean distance from the
    # midpoint of its neighbouring tasks' current means, added during the search (0: none). > 0
    # tunes the tasks as a chain, so that a kick between two tasks' kicks is near both.
    cfg.tune.neighbour_leash = 1.0
    # "per_task" only: weight of the mean cost of the kicks halfway between a candidate and its
    # neighbouring tasks' current means (their joint trajectories mixed 50/50, played at the
    # middle target), added during the search (0: none; > 0 triples the tuning's episodes). > 0
    # tunes the tasks so that what a meta-policy plays between two of them still kicks.
    cfg.tune.midpoint_weight = 0.0
    cfg.ppo = ppo_config.default_config()
    cfg.ppo.num_envs = 256  # episodes per update (19,200 steps; the paper: 4,096)
    cfg.ppo.num_minibatches = 16  # 16 episodes = 1,200 steps each (the paper: 1,024)
    cfg.ppo.num_epochs = 30
    cfg.ppo.total_env_steps = 256 * 75 * 625  # 12.0 M per expert, 625 updates
    cfg.ppo.learning_rate = 1e-6
    cfg.ppo.init_log_std = -6.0
    cfg.ppo.reward_scaling = 0.01
    cfg.eval = ml_collections.ConfigDict()
    cfg.eval.repetitions = 100  # noisy kicks per expert on its own task
    cfg.eval.seed = 1
    return cfg


def _meta() -> ml_collections.ConfigDict:
    cfg = ml_collections.ConfigDict()
    # name -> (hidden layers, width): the paper's two meta-policies.
    cfg.nets = ml_collections.ConfigDict({"meta_4x256": (4, 256), "meta_11x128": (11, 128)})
    # How the nets train, the same optimisation each way: "separate", each net its own loop, one
    # after the other; "stacked", every net padded and stacked in one loop (`bc_stacked`: each
    # layer of all nets one batched matmul); "stacked_batched", the same with the hand-written
    # backward pass. Rounding differs between them, so a run made one way is not resumed another.
    cfg.trainer = "separate"
    # What the kick's nets read: "unit", (phase = step / steps, (target - 7) / 11), both in [0, 1];
    # "raw", the paper's unscaled (time step, target in m); "centred", both moved to [-1, 1]. Either
    # way the dataset and the env's observations stay (phase, normalised context): "raw" and
    # "centred" are a fixed affine map in front of the first layer (`bc.kick_raw_inputs`,
    # `bc.kick_centred_inputs`), recorded with the nets. Another task takes only "unit"
    # (its states are normalised by the dataset's statistics).
    cfg.inputs = "unit"
    cfg.dataset = ml_collections.ConfigDict()
    cfg.dataset.repetitions = 1  # rollouts per expert; 1 records them noise-free (the paper)
    cfg.dataset.seed = 0
    cfg.train = ml_collections.ConfigDict()
    cfg.train.learning_rate = 3e-4  # Adam, times decay_rate every decay_every epochs
    cfg.train.decay_rate = 0.8
    cfg.train.decay_every = 5000  # epochs
    cfg.train.batch_size = 128
    cfg.train.epochs = 150_000  # passes over the dataset
    cfg.train.chunk = 2500  # epochs per host sync (progress, CSV, checkpoint)
    # Gradient steps per iteration of the compiled loop (lax.scan's unroll; at most an epoch's):
    # the same steps on the same batches in fewer iterations, a longer compile.
    cfg.train.unroll = 1
    cfg.train.n_seeds = 1  # initialisations trained side by side; seed 0 is the table's row
    cfg.train.seed = 0
    cfg.eval = ml_collections.ConfigDict()
    cfg.eval.tasks = kick_env.meta_test_tasks()
    cfg.eval.repetitions = 100
    cfg.eval.seed = 1
    return cfg


def _filter() -> ml_collections.ConfigDict:
    cfg = ml_collections.ConfigDict()
    cfg.tasks = kick_env.meta_test_tasks()
    cfg.context_range = (7.1, 18.0)  # m: sampled contexts form a grid over this range ...
    cfg.context_step = 0.1  # ... of this step (110 contexts)
    cfg.high_context_step = 0.01  # the "high sample rate" variant (1091 contexts)
    cfg.width = 1.0  # m: a task's candidates are the contexts within +- width of it
    # "fixed": every candidate context gets `selection_repetitions` rollouts. "halving":
    # successive halving: every candidate gets halving_rungs[0] rollouts, each task's best
    # `halving_keep` fraction of its candidates goes on to the next rung's total, and so on; the
    # scores at a rung use all of a context's rollouts so far.
    cfg.selection = "halving"
    cfg.selection_repetitions = 10  # noisy rollouts per sampled context ("fixed")
    cfg.halving_rungs = (2, 8, 32, 100)  # rollouts per surviving context after each rung ("halving")
    cfg.halving_keep = 0.25  # fraction of a task's surviving candidates that goes on to the next rung
    cfg.eval_repetitions = 100  # fresh noisy rollouts of each task's chosen context
    cfg.seed = 0  # split into independent selection and evaluation noise
    cfg.net_seed = 0  # which initialisation of a meta-policy ensemble is filtered
    # Episodes per device per program call: one compiled program serves every batch (None: one
    # call, and one compile, per batch size).
    cfg.block = FieldReference(4096, field_type=int)
    return cfg


def _baseline() -> ml_collections.ConfigDict:
    cfg = ml_collections.ConfigDict()
    cfg.seeds = 6  # independent runs, trained side by side
    cfg.updates_per_chunk = 25  # PPO updates per compiled chunk; progress and a checkpoint between
    cfg.keep_checkpoints = 3
    cfg.bc_steps = 20000  # cloning the main kick at every training context before PPO
    cfg.bc_learning_rate = 1e-3
    cfg.eval_tasks = kick_env.meta_test_tasks()
    cfg.eval_repetitions = 100
    cfg.eval_seed = 7
    cfg.ppo = _experts().ppo  # one expert's PPO settings and budget per seed ...
    cfg.ppo.policy_hidden = (256,) * 11  # ... with the paper's 11 x 256 policy
    cfg.ppo.sample_task_range = (7.0, 18.0)  # each episode draws its target from U[7, 18] m
    # A second arm: the same seeds at this policy learning rate, trained beside the paper's
    # (ppo.learning_rate) in one program; None: the paper's arm only.
    cfg.extra_learning_rate = FieldReference(1e-5, field_type=float)
    return cfg


def _heldout() -> ml_collections.ConfigDict:
    cfg = ml_collections.ConfigDict()
    cfg.targets = HELDOUT_TARGETS  # m, off the 0.1 m grid
    cfg.seed = 2222  # noise of the held-out episodes (selection and fresh); no other section uses it
    cfg.repetitions = 100  # fresh noisy kicks per target and variant
    # Filtering a held-out target: candidates are filter.context_range / context_step's grid and the
    # target itself within +- filter.width, each rolled out this many times on its own episodes.
    cfg.selection_repetitions = 10
    return cfg


def _dev() -> ml_collections.ConfigDict:
    cfg = _heldout()  # the same evaluation, on targets and noise of its own
    cfg.targets = DEV_TARGETS  # m, off the 0.1 m grid and off the held-out targets
    cfg.seed = 3333  # noise of the development episodes; no other section uses it
    return cfg


def default_config() -> ml_collections.ConfigDict:
    """The whole tree at its defaults (unlocked): the paper's values. `PRESETS["paper"]` changes
    the few knobs that only pay on a GPU; the tiny preset, for a CPU, keeps their defaults."""
    cfg = ml_collections.ConfigDict()
    cfg.preset = "paper"
    # The contextual task every stage runs: "kick" (the paper's) or "cheetah_vel" (its sections:
    # `cheetah_vel`).
    cfg.task = "kick"
    cfg.env = kick_env.default_config()
    cfg.prior = _prior()
    cfg.experts = _experts()
    cfg.meta = _meta()
    cfg.filter = _filter()
    cfg.baseline = _baseline()
    cfg.heldout = _heldout()
    cfg.dev = _dev()
    cfg.cheetah_vel = cheetah_config.sections(_meta(), _filter())
    cfg.point_goal = point_goal_config.sections(_meta(), _filter())
    return cfg


# Each preset: dotted overrides of the defaults (the paper's values).
PRESETS: dict[str, dict] = {
    "paper": {
        # Both meta-policies in one stacked loop with the hand-written backward: the same
        # optimisation, 361 s against 404-411 s on one H100 (docs/decisions.md, meta.trainer).
        "meta.trainer": "stacked_batched",
        # An epoch's 14 steps in one iteration of that loop: the two nets' training 310 s against
        # 376 s in the meta stage on one H100 (docs/decisions.md, meta.train.unroll).
        "meta.train.unroll": 14,
        # Four independent tunings of the starting kicks, each task's kick chosen among them with
        # the neighbour leash, then a 20-generation polish at a step of 0.25. On development seeds
        # 102 and 103 at the paper budget: experts 0.33 m, unfiltered 4x256 0.44-0.45 m and 11x128
        # 0.36 m, where seed 102's other tunings gave 0.35-0.43, 0.49-0.65 and 0.42-0.48 m
        # (docs/decisions.md, tune.restarts). The experts stage takes about 935 s instead of 762.
        "experts.tune.restarts": 4,
        "experts.tune.keep": "chain",
        "experts.tune.polish_generations": 20,
        "experts.tune.polish_sigma": 0.25,
        # The four tunings as one batch: the same runs (each from its own key), each physics call
        # four times the episodes; in the paper run of 2026-11-26 (one H100) the four runs took
        # 147 s against 208 s one after another (docs/decisions.md, tune.batch_restarts).
        "experts.tune.batch_restarts": True,
    },
    "tiny": {
        "preset": "tiny",
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
        # One generation cannot carry the main kick to 8 and 16 m: each task starts from its own
        # strength, untied to its neighbours.
        "experts.bc.per_task_strength": True,
        "experts.bc.common_start": "main",
        "experts.bc.common_start_strength": False,
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
        # The tests' and the demo's selection: 2 rollouts per context.
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
        **cheetah_config.TINY,
        **point_goal_config.TINY,
    },
}


def make_config(preset: str = "tiny", overrides: dict | None = None) -> ml_collections.ConfigDict:
    """The locked config of `preset` with dotted `overrides` ({"experts.ppo.learning_rate": 1e-5}).

    ValueError, naming the key and value, for an unknown preset or key, or a value of the wrong
    type; then every section's own checks (`validate`).
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {sorted(PRESETS)}")
    cfg = default_config()
    cfg.lock()
    for key, value in {**PRESETS[preset], **(overrides or {})}.items():
        set_leaf(cfg, key, value)
    validate(cfg)
    return cfg


def set_leaf(cfg: ml_collections.ConfigDict, key: str, value) -> None:
    """cfg[key] = value for a dotted key, the value checked against the leaf's type."""
    *parents, leaf = key.split(".")
    node = cfg
    for i, part in enumerate(parents):
        if not isinstance(node, ml_collections.ConfigDict) or part not in node:
            raise ValueError(f"unknown config key {key!r} (no section {'.'.join(parents[: i + 1])!r})")
        node = node[part]
    if not isinstance(node, ml_collections.ConfigDict) or leaf not in node:
        raise ValueError(f"unknown config key {key!r}")
    if isinstance(node[leaf], ml_collections.ConfigDict):
        raise ValueError(f"config key {key!r} is a section; set one of its keys: {sorted(node[leaf])}")
    optional = isinstance(node._fields.get(leaf), FieldReference)  # declared with a type: may be null
    node[leaf] = coerce(key, value, node.get_type(leaf), node[leaf], optional)


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
    """Every section's range checks; ValueError naming the first bad value."""
    from bumps_jax.pipeline import validation  # noqa: PLC0415 (the checks import the algorithm modules)

    validation.validate(cfg)


def section(cfg: ml_collections.ConfigDict, stage: str) -> dict:
    """What one stage's results depend on, as plain data: its section, the env (its physics step
    resolved, as records carry it) and the preset; for a task other than the kick, the task too
    (the kick's stays as it was, so that its runs resume)."""
    if cfg.task == "kick":
        return {"preset": cfg.preset, "env": kick_env.resolved(cfg.env), stage: jsonable(cfg[stage].to_dict())}
    view = task_view(cfg)
    env = tasks.resolved(cfg.task, view.env)
    return {"preset": cfg.preset, "task": cfg.task, "env": env, stage: jsonable(view[stage].to_dict())}


def task_view(cfg: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
    """The config the selected task's stages read: the kick's is `cfg` itself; another task's is a
    locked copy holding preset, task and that task's sections (env, experts, ...) at the top. A
    view is its own view."""
    if cfg.task == "kick" or cfg.task not in cfg:
        return cfg
    view = ml_collections.ConfigDict()
    view.preset, view.task = cfg.preset, cfg.task
    for key in cfg[cfg.task].keys():
        view[key] = copy.deepcopy(cfg[cfg.task][key])
    view.lock()
    return view


def resolved_env(cfg: ml_collections.ConfigDict) -> dict:
    """The selected task's env config as records carry it (`tasks.resolved`)."""
    return tasks.resolved(cfg.task, task_view(cfg).env)


def overrides_of(cfg: ml_collections.ConfigDict) -> dict:
    """{dotted key: value} of every leaf where `cfg` differs from its preset."""
    base, mine = jsonable(make_config(cfg.preset).to_dict()), jsonable(cfg.to_dict())
    out = {}
    for key in differing_keys(base, mine):
        value = mine
        for part in key.split("."):
            value = value[part]
        out[key] = value
    return out
