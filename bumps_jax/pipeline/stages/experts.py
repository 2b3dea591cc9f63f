"""Stage 2: one PPO expert per task, all tasks in one compiled program.

Each expert starts as its task says (`Task.expert_start`: the kick clones its own tuned keyframe
kick; a task without one starts from a fresh policy), and PPO refines it on its own target. The
host loop runs jitted chunks of `updates_per_chunk` updates; between chunks it prints progress
with an ETA, appends progress.csv and saves an orbax checkpoint. A killed run resumes from the
newest readable checkpoint and ends exactly where an uninterrupted one would: every random number
comes from the carried `TrainState.rng`.

Writes run_dir/experts/: what the task's start keeps (the kick: starting_kicks.json, tuning/),
checkpoints/ (while training; removed with the start's scratch once the record is written),
progress.csv, wall_time.json, final_params/, experts.json, experts.md.
"""

from __future__ import annotations

import functools
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import ml_collections
import numpy as np

from bumps_jax import config, resumable, runio
from bumps_jax.algo import evaluate, ppo, rollout
from bumps_jax.envs import base as task_env
from bumps_jax.pipeline.expert_programs import (
    Compiled,
    ExpertParams,
    chunked_loop,
    compile_programs,
    csv_fields,
    expert_params,
    expert_policy,
    own_context_rollouts,
    run_init,
    task_expert_policy,
    task_rngs,
)
from bumps_jax.pipeline.family import (
    centre_rounds,
    choice_update,
    family_centre,
    family_state,
    family_updates,
    ramped_targets,
    round_dir,
    train_chosen,
    train_rounds,
)
from bumps_jax.pipeline.programs import stage_env
from bumps_jax.records import jsonable
from bumps_jax.schema import sections as stage_sections
from bumps_jax.tasks import registry as tasks

OUTPUT = "experts.json"


def inputs(cfg, run_dir: Path) -> dict:
    """What the task's expert start reads (nothing for a fresh policy)."""
    start = tasks.get(cfg.task).expert_start
    return {} if start is None else start.inputs(cfg, run_dir)


class Family(NamedTuple):
    """Deterministic policies stacked over experts: params leaves have a leading axis (E,)."""

    apply_fn: Any  # (params of one expert, contextual obs) -> action: `expert_policy`
    params: Any
    tasks: np.ndarray  # (E,) targets (the task's unit); (E, K) for a vector context


# -- training -----------------------------------------------------------------------------------


def initial_state(cfg, run_dir: Path, programs: Compiled, say=print):
    """The experts' TrainState (N, ...) before PPO, from the task's expert start (fresh policies
    without one): written as checkpoint 0."""
    targets = np.asarray(cfg.experts.tasks, np.float32)  # (E,), or (E, K) for a vector context
    start = tasks.get(cfg.task).expert_start
    if start is None:
        starts = np.zeros((len(targets), 0))
    else:
        starts = start.starts(cfg, run_dir, run_dir / "experts", say)
    state, losses = run_init(programs, task_rngs(cfg.experts.seed, len(targets)), targets, starts)
    if start is not None:
        say(f"behaviour cloning: final mse per task {np.asarray(losses[:, -1]).round(6).tolist()}")
    return state


def train(cfg, run_dir: Path, programs: Compiled, say=print, stop_after_chunks: int | None = None) -> dict:
    """Train every task's expert under run_dir/experts, resuming from its newest readable checkpoint;
    with `experts.family`, the centre expert first (`train_centre`) and every expert from it.

    Returns {"state": TrainState (N, ...), "finished": bool, "wall_s": training seconds over every call}.
    """
    import orbax.checkpoint as ocp  # noqa: PLC0415

    stage_dir = run_dir / "experts"
    tasks = task_env.as_contexts(cfg.experts.tasks, programs.env.CONTEXT_SIZE)  # (E,) or (E, K)
    total = programs.trainer.n_updates
    centre_updates, ramp = family_updates(cfg)
    centre_s = 0.0
    if centre_updates:
        centre = train_rounds(cfg, run_dir, programs, say, stop_after_chunks)
        if not centre["finished"]:
            return centre
        centre_s, chosen = centre["wall_s"], centre["state"]
        if choice_update(cfg) < centre_updates:  # the chosen one goes on alone
            alone = train_chosen(cfg, run_dir, programs, chosen, say, stop_after_chunks)
            centre_s += alone["wall_s"]
            if not alone["finished"]:
                return {**alone, "wall_s": centre_s, "finished": False}
            chosen = alone["state"]
        rngs = jax.vmap(lambda k: jax.random.fold_in(k, 1))(task_rngs(cfg.experts.seed, len(tasks)))
        init = functools.partial(family_state, chosen, rngs)
    else:
        init = functools.partial(initial_state, cfg, run_dir, programs, say)
    i, chunk = family_centre(tasks), int(cfg.experts.updates_per_chunk)
    loop = chunked_loop(programs, tasks, init, lambda u: ramped_targets(tasks, i, u, chunk, ramp), total)
    out = resumable.train_in_chunks(stage_dir, loop, total, cfg.experts.keep_checkpoints, say, stop_after_chunks)
    out["wall_s"] += centre_s
    if out["finished"]:
        with ocp.StandardCheckpointer() as checkpointer:  # leaving the context waits for the write
            params = resumable.savable(expert_params(out["state"]))
            checkpointer.save((stage_dir / "final_params").resolve(), params, force=True)
        runio.write_checksums(stage_dir / "final_params")
        runio.sync("final_params")
    return out


# What rebuilds an expert's policy besides the env's sizes: its PPO networks' keys.
POLICY_KEYS = ("policy_hidden", "value_hidden", "normalize_observations", "init_log_std")


def policy_record(ppo_cfg, env) -> dict:
    """The experts' policy as their record describes it: observation and action sizes and the PPO
    networks' architecture (`POLICY_KEYS`), all a reader needs to rebuild it."""
    shape = {"obs_size": int(env.observation_size), "action_size": int(env.action_size)}
    return {**shape, **{k: jsonable(ppo_cfg[k]) for k in POLICY_KEYS}}


def policy_networks(policy: dict):
    """The PPO networks of a `policy_record`."""
    arch = ml_collections.ConfigDict({k: tuple(v) if isinstance(v, list) else v for k, v in policy.items()})
    return ppo.make_networks(arch, policy["obs_size"], policy["action_size"])


def abstract_params(policy: dict, n_tasks: int) -> ExpertParams:
    """The ExpertParams (N, ...) shapes and dtypes of `n_tasks` experts of a `policy_record`."""
    networks = policy_networks(policy)
    one = jax.eval_shape(
        lambda: ExpertParams(ppo.init_normalizer(policy["obs_size"]), networks.policy_network.init(jax.random.key(0)))
    )
    return jax.tree.map(lambda a: jax.ShapeDtypeStruct((n_tasks, *a.shape), a.dtype), one)


def load_final_params(stage_dir: Path, policy: dict, n_tasks: int) -> ExpertParams:
    """The ExpertParams (N, ...) saved under stage_dir/final_params, of experts of a `policy_record`;
    ValueError naming it if unreadable."""
    import orbax.checkpoint as ocp  # noqa: PLC0415

    final = (Path(stage_dir) / "final_params").resolve()
    runio.verify_checksums(final)  # CorruptError (a ValueError) naming a changed file
    try:
        with ocp.StandardCheckpointer() as checkpointer:  # closed on leaving: no thread outlives the read
            return checkpointer.restore(final, abstract_params(policy, n_tasks))
    except Exception as err:  # noqa: BLE001 (orbax and tensorstore raise many kinds)
        reason = type(err).__name__
        raise ValueError(f"{final}: cannot read the trained experts ({reason}); rerun train-experts") from None


def load_family(cfg, run_dir: Path) -> Family:
    """The trained experts of a run, for behaviour cloning and replays: rebuilt from their record
    (`policy_record`) and final_params, not from the trainer that made them; `cfg` gives the env."""
    stage_dir = Path(run_dir) / "experts"
    record = runio.read_json(stage_dir / OUTPUT, "the experts' record: run train-experts first")
    env = stage_env(cfg.env, cfg.task)
    policy = record.get("policy") or policy_record(cfg.experts.ppo, env)  # a record from before it was kept
    params = load_final_params(stage_dir, policy, len(cfg.experts.tasks))
    return Family(expert_policy(policy_networks(policy), env), params, np.asarray(cfg.experts.tasks, np.float64))


def evaluate_on_own(cfg, programs: Compiled, params: ExpertParams) -> tuple[dict, dict]:
    """Every expert on its own context, `eval.repetitions` noisy episodes (`own_context_rollouts`)."""
    env, e = programs.env, cfg.experts
    targets = np.asarray(env.check_targets(e.tasks), np.float32)
    keys = rollout.repetition_keys(e.eval.seed, len(targets), e.eval.repetitions)  # evaluate_experts' keys
    return own_context_rollouts(env, task_expert_policy(cfg, programs), params, targets, keys)


# An expert whose training error fell by more than this fraction from one tenth of its updates to
# the last tenth, and by more than STILL_FALLING_FLOOR, was still learning when its budget ended.
STILL_FALLING = 0.05
# In the task's unit (1 cm; 1 cm/s): the last digit the stages print errors to (two decimals), so
# that an expert solved to millimetres, whose error still wobbles by a millimetre, is not learning.
STILL_FALLING_FLOOR = 0.01


def training_tail(progress: Path, unit: str = "m") -> dict | None:
    """Whether each expert was still learning at the end: from progress.csv (targets in `unit`),
    every expert's mean training `final_error` over its last tenth of updates (at least one) against
    the tenth before: learning where it fell by more than `STILL_FALLING` of it and more than
    `STILL_FALLING_FLOOR` (an absolute floor: a relative drop of a millimetre-sized error is noise).
    None where there are fewer than two updates (or no log)."""
    import csv  # noqa: PLC0415

    if not progress.exists():
        return None
    target = csv_fields(unit)[2]
    curves: dict[str, list[float]] = {}
    with progress.open() as f:
        for row in csv.DictReader(f):
            curves.setdefault(row[target], []).append(float(row["final_error"]))
    n = min((len(c) for c in curves.values()), default=0)
    if n < 2:
        return None
    k = max(1, n // 10)
    before = np.array([np.mean(c[n - 2 * k : n - k]) for c in curves.values()])
    last = np.array([np.mean(c[n - k : n]) for c in curves.values()])
    falling = before - last > np.maximum(STILL_FALLING * np.abs(before), STILL_FALLING_FLOOR)
    return {
        "updates_compared": k,
        "threshold": STILL_FALLING,
        "floor": STILL_FALLING_FLOOR,
        "still_falling": int(falling.sum()),
        "n_experts": len(curves),
        "per_task_drop": (before - last).tolist(),  # in the order of progress.csv's first appearance
    }


def tail_line(tail: dict | None, unit: str) -> str:
    """The training tail in words, or "" without one."""
    if not tail:
        return ""
    k, pct = tail["updates_compared"], f"{tail['threshold']:.0%}"
    floor = f" and {tail['floor']:g} {unit}" if "floor" in tail else ""  # a record from before the floor has none
    return (f"{tail['still_falling']} of {tail['n_experts']} experts were still learning when their budget ended "
            f"(training error over their last {k} updates below the {k} before by more than {pct}{floor}; "
            f"largest drop {max(tail['per_task_drop']):.3g} {unit}).\n")  # fmt: skip


def evaluate_experts(cfg, stage_dir: Path, params: ExpertParams, programs: Compiled, wall_s: float, say=print) -> dict:
    """Every expert on its own task (`eval.repetitions` noisy episodes each): experts.json and experts.md."""
    start = time.perf_counter()
    e = cfg.experts
    say(f"evaluating {len(e.tasks)} experts x {e.eval.repetitions} noisy episodes (compiling first)", flush=True)
    metrics, posture = evaluate_on_own(cfg, programs, params)
    record = evaluate.experts_record(e.tasks, metrics, programs.trainer.n_updates * programs.trainer.steps_per_update)
    task = tasks.get(cfg.task)
    centre_updates, _ = family_updates(cfg)
    if task.expert_start is None:  # every env step an expert cost is PPO's (its share of the centre's)
        made = (round_dir(stage_dir.parent, r) / "choice.json" for r in range(centre_rounds(cfg)))
        choices = [runio.read_json(path) for path in made if path.exists()]
        used = max(1, len(choices))  # rounds of candidates the run drew
        centre_steps = (
            stage_sections.centre_env_updates(e.family, used) * programs.trainer.steps_per_update
            if centre_updates
            else 0
        )
        record["env_steps_breakdown"] = {"ppo": record["env_steps"]}
        if centre_steps:
            record["env_steps_breakdown"]["family_centre_share"] = centre_steps // len(e.tasks)
            record["family_centre"] = {"context": task_env.context_json(e.tasks[family_centre(e.tasks)]),
                                       "updates": centre_updates, "choose_after": choice_update(cfg),
                                       "env_steps": centre_steps}  # fmt: skip
            if choices:  # every round's candidates and the one the family continued from (their episodes' steps)
                offset = sum(len(c["candidates"]) for c in choices[:-1])
                record["family_centre"].update(
                    chosen=offset + choices[-1]["chosen"],
                    candidates=[{**c, "round": r + 1} for r, ch in enumerate(choices) for c in ch["candidates"]],
                    repetitions=choices[-1]["repetitions"],
                    rounds=used,
                    choice_env_steps=sum(ch["env_steps"] for ch in choices),
                )
    else:
        record.update(task.expert_start.describe(cfg, stage_dir.parent, stage_dir, programs.env, record))
    known = [v for v in record["env_steps_breakdown"].values() if v is not None]
    record["env_steps_total"] = int(sum(known))  # per expert, the parts that are known
    record["family_check"] = evaluate.family_check(programs.env, e.tasks, metrics, posture)
    record["training_tail"] = training_tail(stage_dir / "progress.csv", programs.env.UNIT)
    record.update(runio.provenance(cfg.preset, wall_s + time.perf_counter() - start, config.resolved_env(cfg)))
    record.update(task=cfg.task, unit=task.unit, eval_repetitions=int(e.eval.repetitions))
    record["policy"] = policy_record(e.ppo, programs.env)  # what rebuilds the experts from final_params
    family = evaluate.family_table(record["family_check"], programs.env.UNIT)
    say(family)
    tail = tail_line(record["training_tail"], task.unit)
    if tail:
        say(tail)
    runio.write_text(stage_dir / "experts.md", task.report.experts(record) + "\n" + tail + "\n" + family)
    runio.write_json(stage_dir / OUTPUT, record)
    return record


def run(cfg, run_dir: Path, say=print) -> dict:
    """The stage: train (or resume) every expert, then evaluate them; returns experts.json's record."""
    stage_dir = Path(run_dir) / "experts"
    programs = compile_programs(cfg)
    n = len(cfg.experts.tasks)
    if (stage_dir / "final_params").exists():  # trained; a previous call stopped before its evaluation
        say(f"experts already trained ({stage_dir / 'final_params'}): evaluating them")
        params = load_final_params(stage_dir, policy_record(cfg.experts.ppo, programs.env), n)
        wall = 0.0
        rounds = [round_dir(run_dir, r).name for r in range(centre_rounds(cfg))]
        for clock_path in (stage_dir / part / "wall_time.json" for part in ("", *rounds, "centre_chosen")):
            clock = runio.read_json(clock_path) if clock_path.exists() else {}
            wall += max([0.0, *map(float, clock.values())])
    else:
        out = train(cfg, run_dir, programs, say)
        params, wall = expert_params(out["state"]), out["wall_s"]
    record = evaluate_experts(cfg, stage_dir, params, programs, wall, say)
    # The record and final_params hold everything later stages read: the training checkpoints
    # (most of a paper run directory's size) go, once final_params is verified.
    runio.verify_checksums(stage_dir / "final_params")
    start = tasks.get(cfg.task).expert_start
    for scratch in (
        "checkpoints",
        *(f"{round_dir(run_dir, r).name}/checkpoints" for r in range(centre_rounds(cfg))),
        "centre_chosen/checkpoints",
        *(() if start is None else start.scratch()),
    ):
        runio.remove(stage_dir / scratch)
    say(tasks.get(cfg.task).report.experts(record))
    return record
