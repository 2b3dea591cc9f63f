"""Keyframe kicks scored by replaying them in the env: the cost CMA-ES minimises, its compiled
programs, and the replays the stages report (a kick's evaluation, the family sweep, each task's
best starting kick).

Every episode is `rollout.episode_fn` playing the kick's action table (`rollout.table_policy`);
batches of kicks are split over a device mesh (`sharding.over_batch`). Candidates compared with
each other meet the same noisy episodes (common random numbers), so a ranking compares kicks, not
luck.
"""

from __future__ import annotations

import functools
import json

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from bumps_jax.algo import rollout, sharding
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model

# -- costs -------------------------------------------------------------------------------------


def kick_cost(env: kick_env.KickEnv, fitness):
    """The kick prior's cost: fn(params (P, 14), keys (P, R), target, extra) -> (mean cost (P,),
    metrics of (P, R)), cost = `kick_model.fitness` with weights `fitness`; `extra` is unused."""
    episodes = jax.vmap(rollout.over_reps(rollout.episode_fn(env, rollout.table_policy)), in_axes=(0, None, None, 0))

    def cost_fn(params, keys, target, extra):
        metrics = episodes(kick_model.action_tables(params, env.n_steps, env.dt), target, target, keys)
        return jnp.mean(kick_model.fitness(metrics, target, fitness), axis=1), metrics

    return cost_fn


def weights(fitness_json: str) -> ml_collections.ConfigDict:
    return ml_collections.ConfigDict(json.loads(fitness_json))


def fitness_json_of(fitness) -> str:
    data = fitness.to_dict() if isinstance(fitness, ml_collections.ConfigDict) else dict(fitness)
    return json.dumps({k: float(v) for k, v in sorted(data.items())})


@functools.lru_cache(maxsize=8)
def cost_program(env, mesh, fitness_json: str):
    """Jitted (params (T, C, 14), keys (C, R), targets (T,)) -> mean costs (T, C), tasks split over
    `mesh`; kept per settings so that one process compiles it once."""
    cost_fn = kick_cost(env, weights(fitness_json))

    def costs(params, keys, target):
        return cost_fn(params, keys, target, 0.0)[0]

    return sharding.over_batch(jax.vmap(costs, in_axes=(0, None, 0)), mesh, (True, False, True))


@functools.lru_cache(maxsize=8)
def metrics_program(env, mesh):
    """`rollout.matched_fn` of action tables: (tables (N, n_steps, 22), contexts (N,), targets (N,),
    keys (N, R)) -> metrics of (N, R); kept per env and mesh."""
    return rollout.matched_fn(env, rollout.table_policy, mesh=mesh)


# -- replays --------------------------------------------------------------------------------------


def best_starts(env, targets, candidates, fitness, repetitions: int = 16, seed: int = 3, mesh=None):
    """Each target's best candidate kick: the lowest mean cost over `repetitions` noisy kicks, the
    same episodes for every candidate (common random numbers); tasks split over `mesh`.

    targets: (T,) m; candidates: (T, C, 14). Returns (params (T, 14), index (T,), costs (T, C)).
    """
    targets = np.asarray(targets, np.float32)
    candidates = np.asarray(kick_model.clip_params(jnp.asarray(candidates, jnp.float32)))
    if targets.ndim != 1 or candidates.ndim != 3 or candidates.shape[::2] != (targets.shape[0], kick_model.N_PARAMS):
        raise ValueError(f"need targets (T,) and candidates (T, C, {kick_model.N_PARAMS}), got "
                         f"{targets.shape} and {candidates.shape}")  # fmt: skip
    check_count("repetitions", repetitions)
    kick_env.check_targets(targets.tolist(), env.config.task_range)
    mesh = mesh or sharding.device_mesh(impl=env.config.impl)
    n_tasks, n_candidates = candidates.shape[:2]
    keys = jnp.broadcast_to(jax.random.split(jax.random.key(seed), repetitions), (n_candidates, repetitions))
    padded = sharding.pad((jnp.asarray(candidates), jnp.asarray(targets)), sharding.padded_size(n_tasks, mesh))
    costs = np.asarray(
        sharding.unpad(cost_program(env, mesh, fitness_json_of(fitness))(padded[0], keys, padded[1]), n_tasks)
    )
    index = np.argmin(costs, axis=1)
    return candidates[np.arange(n_tasks), index], index, costs


def replay(env, params, targets, keys, mesh=None) -> dict:
    """Kicks params (N, 14) at targets (N,) m over keys (N, R): the env's final metrics, (N, R) numpy."""
    mesh = mesh or sharding.device_mesh(impl=env.config.impl)
    n = len(targets)
    tables = kick_model.action_tables(kick_model.clip_params(jnp.asarray(params, jnp.float32)), env.n_steps, env.dt)
    targets = jnp.asarray(targets, jnp.float32)
    args = sharding.pad((tables, targets, targets, keys), sharding.padded_size(n, mesh))
    return {k: np.asarray(v) for k, v in sharding.unpad(metrics_program(env, mesh)(*args), n).items()}


def evaluate_kick(env, params, target: float, fitness, repetitions: int, seed: int = 1, mesh=None) -> dict:
    """One kick (14,) replayed over `repetitions` noisy episodes: plain floats of its resting error
    (mean, std), distance, sideways offset, mean cost and valid / struck / fallen fractions."""
    check_count("repetitions", repetitions)
    kick_env.check_targets(target, env.config.task_range)
    keys = jax.random.split(jax.random.key(seed), repetitions)[None]
    out = replay(env, np.asarray(params, np.float32)[None], [target], keys, mesh)
    cost = kick_model.fitness(out, target, weights(fitness_json_of(fitness)))
    summary = {
        "repetitions": int(repetitions),
        "target": float(target),
        "mean_error": float(np.mean(out["final_error"])),
        "std_error": float(np.std(out["final_error"])),
        "mean_distance": float(np.mean(out["distance"])),
        "mean_lateral": float(np.mean(out["lateral"])),
        "mean_fitness": float(np.mean(cost)),
    }
    return summary | {f"{k}_fraction": float(np.mean(out[k])) for k in ("valid", "struck", "fallen")}


def sweep(env, anchors, strengths, target: float, repetitions: int = 8, seed: int = 2, mesh=None) -> list[dict]:
    """The blended kick (`kick_model.blend_params` of anchors (3, 14)) at each strength in [0, 1]:
    rows of its mean and std resting distance, sideways offset, valid and fallen fractions over
    `repetitions` noisy episodes, the same for every strength."""
    strengths = _strengths(strengths)
    batch = jax.vmap(kick_model.blend_params, in_axes=(None, 0))(jnp.asarray(anchors), jnp.asarray(strengths))
    return _sweep_rows(env, batch, strengths, target, repetitions, seed, mesh)


def strength_sweep(env, kick, strengths, target: float, repetitions: int = 8, seed: int = 2, mesh=None) -> list[dict]:
    """`sweep`'s rows for one kick (14,) with its strength set to each of `strengths` in [0, 1]
    and every other parameter kept."""
    strengths = _strengths(strengths)
    batch = np.tile(np.asarray(kick, np.float32), (len(strengths), 1))
    batch[:, kick_model.PARAM_NAMES.index("strength")] = strengths
    return _sweep_rows(env, batch, strengths, target, repetitions, seed, mesh)


def _strengths(strengths) -> np.ndarray:
    strengths = np.asarray(strengths, np.float32)
    if strengths.ndim != 1 or not len(strengths) or not np.all((strengths >= 0) & (strengths <= 1)):
        raise ValueError(f"strengths must be a 1-d list in [0, 1], got {strengths.tolist()!r}")
    return strengths


def _sweep_rows(env, batch, strengths, target, repetitions, seed, mesh) -> list[dict]:
    check_count("repetitions", repetitions)
    kick_env.check_targets(target, env.config.task_range)
    keys = jnp.broadcast_to(jax.random.split(jax.random.key(seed), repetitions), (len(strengths), repetitions))
    out = replay(env, batch, np.full(len(strengths), target, np.float32), keys, mesh)
    return [
        {
            "strength": float(s),
            "distance_m": float(np.mean(out["distance"][i])),
            "distance_std_m": float(np.std(out["distance"][i])),
            "lateral_m": float(np.mean(out["lateral"][i])),
            "valid_fraction": float(np.mean(out["valid"][i])),
            "fallen_fraction": float(np.mean(out["fallen"][i])),
        }
        for i, s in enumerate(strengths)
    ]


def check_count(name: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
