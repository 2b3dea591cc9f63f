"""One family of experts for a task without an expert start of its own (`experts.family`): the
expert at the contexts' centre first, several candidates side by side, the upright one of least
error going on (another round of fresh candidates while every one runs flipped), then every
expert continued from it, its target moved out from the centre's over the ramp's updates."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax import resumable, runio
from bumps_jax.algo import evaluate, ppo, rollout
from bumps_jax.envs import base as task_env
from bumps_jax.pipeline.expert_programs import (
    Compiled,
    chunked_loop,
    expert_params,
    own_context_rollouts,
    run_init,
    task_expert_policy,
    task_rngs,
)
from bumps_jax.schema import sections as stage_sections


def family_updates(cfg) -> tuple[int, int]:
    """(centre_updates, ramp_updates) of `experts.family` ((0, 0): every expert starts fresh)."""
    fam = cfg.experts.get("family")
    return (0, 0) if fam is None else (int(fam.centre_updates), int(fam.ramp_updates))


def centre_candidates(cfg) -> int:
    """How many centre experts are trained side by side before one is chosen (`experts.family`)."""
    fam = cfg.experts.get("family")
    return 1 if fam is None else int(fam.get("candidates", 1))


def choice_update(cfg) -> int:
    """After how many updates the centre candidates are compared (`sections.choice_update`)."""
    return stage_sections.choice_update(cfg.experts.family)


def family_centre(tasks) -> int:
    """The family's centre: the index of the training context nearest the contexts' mean."""
    t = np.asarray(tasks, np.float64).reshape(len(tasks), -1)
    return int(np.argmin(np.linalg.norm(t - t.mean(axis=0), axis=1)))


def ramped_targets(tasks: np.ndarray, centre: int, update: int, chunk: int, ramp: int) -> np.ndarray:
    """Every expert's training target for the chunk after `update` updates: its own context, or
    while the ramp lasts, the point (update + chunk) / ramp of the way from the centre's to it."""
    frac = 1.0 if ramp <= 0 else min(1.0, (update + chunk) / ramp)
    return tasks[centre] + (tasks - tasks[centre]) * frac


def family_state(centre: ppo.TrainState, rngs) -> ppo.TrainState:
    """The centre expert's TrainState (1, ...) copied to every expert (N = len(rngs)): the same
    policy, value net, optimiser and observation statistics; each its own rng, no updates yet."""
    n = len(rngs)
    state = jax.tree.map(lambda x: jnp.repeat(x, n, axis=0), centre)
    zeros = jnp.zeros((n,), state.update.dtype)
    return state._replace(
        rng=jnp.asarray(rngs, state.rng.dtype), update=zeros, env_steps=zeros.astype(state.env_steps.dtype)
    )


def centre_rounds(cfg) -> int:
    """At most how many rounds of fresh centre candidates are drawn (`experts.family.rounds`)."""
    fam = cfg.experts.get("family")
    return 1 if fam is None else int(fam.get("rounds", 1))


def round_dir(run_dir: Path, r: int) -> Path:
    """Round r's centre candidates (0: the first): run_dir/experts/centre, then centre_round2, ..."""
    return Path(run_dir) / "experts" / ("centre" if r == 0 else f"centre_round{r + 1}")


def round_rngs(own, k: int, r: int):
    """Round r's K candidates' rngs: round 0's first is the centre task's own, every other one
    folded from it, none twice over the rounds."""
    first = [own] if r == 0 else [jax.random.fold_in(own, 10_000 + r * k)]
    return jnp.stack([*first, *(jax.random.fold_in(own, 10_000 + r * k + c) for c in range(1, k))])


def train_centre(cfg, run_dir: Path, programs: Compiled, say=print, stop_after_chunks: int | None = None, r=0) -> dict:
    """Round r of the family's centre experts alone: `experts.family.candidates` of them side by
    side, each PPO updates up to the choice (`choice_update`) from a fresh policy of its own seed
    (`round_rngs`) on the centre context, under `round_dir` (resumable as the experts are).
    Returns `resumable.train_in_chunks`'s dict, its state (K, ...)."""
    tasks = task_env.as_contexts(cfg.experts.tasks, programs.env.CONTEXT_SIZE)
    i, k = family_centre(tasks), centre_candidates(cfg)
    (total, _), n = family_updates(cfg), choice_update(cfg)
    each = "" if k == 1 else f", {k} candidates side by side" + ("" if n == total else f" for the first {n}")
    where = f"{task_env.format_context(tasks[i])} {programs.env.UNIT}"
    rounds = centre_rounds(cfg)
    which = "" if rounds == 1 else f" (round {r + 1} of at most {rounds})"
    say(f"family: the centre expert at {where} first, {total} updates{each}{which}")
    rngs = round_rngs(task_rngs(cfg.experts.seed, len(tasks))[i], k, r)
    centre = np.repeat(tasks[i : i + 1], k, axis=0)
    start = np.zeros((k, programs.start_size))
    loop = chunked_loop(programs, centre, lambda: run_init(programs, rngs, centre, start)[0], lambda _: centre, n)
    return resumable.train_in_chunks(
        round_dir(run_dir, r), loop, n, cfg.experts.keep_checkpoints, say, stop_after_chunks
    )


def upright(candidate: dict) -> bool:
    """A candidate of a choice record stands upright (or its env reports no posture)."""
    return candidate.get("flipped_fraction", 0.0) <= evaluate.FLIPPED


def train_rounds(cfg, run_dir: Path, programs: Compiled, say=print, stop_after_chunks=None) -> dict:
    """The centre candidates' rounds (`train_centre`, `choose_centre`): another round only while
    every candidate of the last one runs flipped, at most `experts.family.rounds`. Returns
    {"state": the chosen candidate (1, ...), "finished", "wall_s"} (its state, unfinished)."""
    wall, rounds = 0.0, centre_rounds(cfg)
    for r in range(rounds):
        out = train_centre(cfg, run_dir, programs, say, stop_after_chunks, r)
        wall += out["wall_s"]
        if not out["finished"]:
            return {**out, "wall_s": wall}
        choice = choose_centre(cfg, run_dir, programs, out["state"], say, r)
        if upright(choice["candidates"][choice["chosen"]]) or r + 1 == rounds:
            break
        say(f"family: every candidate of round {r + 1} runs flipped: {centre_candidates(cfg)} fresh ones")
    c = choice["chosen"]
    return {"state": jax.tree.map(lambda x: x[c : c + 1], out["state"]), "finished": True, "wall_s": wall}


def train_chosen(cfg, run_dir: Path, programs: Compiled, chosen: ppo.TrainState, say=print, stop_after_chunks=None):
    """The chosen centre candidate (1, ...) alone from the choice to `experts.family.centre_updates`,
    under run_dir/experts/centre_chosen (resumable). Returns `resumable.train_in_chunks`'s dict."""
    tasks = task_env.as_contexts(cfg.experts.tasks, programs.env.CONTEXT_SIZE)
    i, (n, _) = family_centre(tasks), family_updates(cfg)
    centre = tasks[i : i + 1]
    say(f"family: the chosen centre alone from update {choice_update(cfg)} to {n}")
    loop = chunked_loop(programs, centre, lambda: chosen, lambda _: centre, n)
    stage_dir = run_dir / "experts" / "centre_chosen"
    return resumable.train_in_chunks(stage_dir, loop, n, cfg.experts.keep_checkpoints, say, stop_after_chunks)


def choose_centre(cfg, run_dir: Path, programs: Compiled, state: ppo.TrainState, say=print, r: int = 0) -> dict:
    """Which of round r's centre candidates the family continues from: each runs
    `experts.eval.repetitions` noisy episodes on the centre context (the same keys for all); the
    upright ones (where the env reports a posture: most steps not flipped) first, then the lowest
    error. Written to choice.json in `round_dir` on the first call and read back on the next, so a
    resumed run continues from the same one. Returns that record ({"chosen", "candidates": [...]})."""
    path = round_dir(run_dir, r) / "choice.json"
    runio.sync("centre choice")  # every process sees the same: the choice made, or not yet
    if not path.exists():
        runio.write_json(path, centre_choice(cfg, programs, state, say))
        runio.sync("centre chosen")
    return runio.read_json(path)  # every process continues from the first one's choice


def centre_choice(cfg, programs: Compiled, state: ppo.TrainState, say=print) -> dict:
    """`choose_centre`'s record, measured now."""
    env, e = programs.env, cfg.experts
    tasks = task_env.as_contexts(e.tasks, env.CONTEXT_SIZE)
    k = len(np.asarray(state.update))
    targets = np.repeat(np.asarray(env.check_targets(tasks), np.float32)[family_centre(tasks)][None], k, axis=0)
    keys = jnp.repeat(rollout.repetition_keys(e.eval.seed, 1, e.eval.repetitions), k, axis=0)  # the same for all
    apply = task_expert_policy(cfg, programs)
    metrics, posture = own_context_rollouts(env, apply, expert_params(state), targets, keys)
    errors = np.asarray(metrics["final_error"], np.float64).mean(axis=1)
    candidates = [{"error_m": float(errors[c]), **{n: float(v[c]) for n, v in posture.items()}} for c in range(k)]
    chosen = min(range(k), key=lambda c: (not upright(candidates[c]), candidates[c]["error_m"]))
    steps = k * int(e.eval.repetitions) * env.n_steps  # the choice's episodes
    record = {"chosen": chosen, "candidates": candidates, "repetitions": int(e.eval.repetitions), "env_steps": steps}
    if k > 1:
        shown = ", ".join(f"{c['error_m']:.3f}" + ("" if upright(c) else " (flipped)") for c in candidates)
        say(f"family: centre candidates' errors {shown} {env.UNIT}: continuing from candidate {chosen}")
    return record
