"""Our vmappable PPO against Brax's `ppo.train` on one kick task, matched hyperparameters.

Both start from the same behaviour-cloned policy (Brax via `restore_params`), see the same
number of env steps in batches of whole 75-step episodes, and are scored on the same fixed
noisy episodes with the deterministic (mean) policy. Brax runs through
`bumps_jax.brax_compat`. Writes <out-dir>/compare_brax_ppo_<device>.json.

    python experiments/compare_brax_ppo.py --out-dir experiments/results
"""

from __future__ import annotations

import argparse
import functools
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax import brax_compat, cli, config, kick_env, kick_model, ppo, rollout, runio
from bumps_jax.stages import experts


def comparison_config(target: float, n_updates: int, num_envs: int, overrides: dict | None = None):
    """The tiny pipeline config with its experts cut to one task and `n_updates` updates of
    `num_envs` episodes; the env draws only that task (Brax resets through `reset(rng)`)."""
    return config.make_config(
        "tiny",
        {
            "env.tasks": (target,),
            "experts.tasks": (target,),
            "experts.bc.steps": 20000,
            "experts.bc.learning_rate": 1e-2,
            # The one 12 m prior kick: it overshoots 16 m by ~4 m, so there is room to improve.
            "experts.bc.per_task_strength": False,
            "experts.tune.generations": 0,  # the one 12 m kick as it is, as in the runs compared
            "experts.ppo.num_envs": num_envs,
            "experts.ppo.num_minibatches": 4,
            "experts.ppo.num_epochs": 4,
            "experts.ppo.total_env_steps": num_envs * 75 * n_updates,
            "experts.ppo.learning_rate": 3e-5,
            "experts.ppo.init_log_std": -4.0,
            "experts.updates_per_chunk": n_updates,
            **(overrides or {}),
        },
    )


def run_brax(cfg, env, init_state: ppo.TrainState, seed: int):
    """Brax's ppo.train with our hyperparameters, from our cloned params. Returns (ExpertParams, wall_s)."""
    params = jax.tree_util.tree_map(lambda x: x[0], init_state.params)
    normalizer = jax.tree_util.tree_map(lambda x: x[0], init_state.normalizer)
    start = time.perf_counter()
    _, (norm, policy, _value), _ = brax_compat.train(
        cfg.experts.ppo,
        env,
        num_timesteps=int(cfg.experts.ppo.total_env_steps),
        restore_params=(normalizer, params.policy, params.value),
        seed=seed,
        num_evals=1,
        run_evals=False,
    )
    jax.block_until_ready(policy)
    return experts.ExpertParams(norm, policy), time.perf_counter() - start


def score(env, networks, params: experts.ExpertParams, target: float, n_episodes: int, seed: int) -> dict:
    """Deterministic policy on fixed noisy episodes: mean return, final error, valid fraction."""
    episodes = jax.jit(rollout.over_reps(rollout.episode_fn(env, experts.expert_policy(networks), record="return")))
    keys = jax.random.split(jax.random.key(seed), n_episodes)
    metrics, ret = episodes(params, jnp.float32(target), jnp.float32(target), keys)
    return {
        "return_mean": float(np.mean(ret)),
        "return_std": float(np.std(ret)),
        "final_error_mean_m": float(np.mean(metrics["final_error"])),
        "valid_fraction": float(np.mean(metrics["valid"])),
    }


def compare(target: float = 16.0, n_updates: int = 8, num_envs: int = 16, eval_episodes: int = 32, seed: int = 0,
            overrides: dict | None = None) -> dict:  # fmt: skip
    """Train both from the same clone, score both on the same episodes: the record (see the module doc)."""
    start = time.perf_counter()
    cfg = comparison_config(target, n_updates, num_envs, overrides)
    env = kick_env.KickEnv(cfg.env)
    programs = experts.compile_programs(cfg, env)
    targets = jnp.asarray([target], jnp.float32)
    record = kick_model.load_record(kick_model.ASSET, env_cfg=cfg.env)
    kicks, _ = experts.starting_kicks(cfg, record)
    state0, _ = experts.run_init(programs, experts.task_rngs(seed, 1), targets, kicks)
    t0 = time.perf_counter()
    ours, metrics = experts.run_chunk(programs, state0, targets)
    jax.block_until_ready(ours)
    ours_wall = time.perf_counter() - t0

    brax_params, brax_wall = run_brax(cfg, env, state0, seed)

    def first(tree):
        return jax.tree_util.tree_map(lambda x: x[0], tree)

    networks = programs.trainer.networks
    out = {
        "target_m": target,
        "env_steps": int(cfg.experts.ppo.total_env_steps),
        "eval_episodes": eval_episodes,
        "ppo": {k: (list(v) if isinstance(v, tuple) else v) for k, v in cfg.experts.ppo.items()},
        "bc_start": score(env, networks, first(experts.expert_params(state0)), target, eval_episodes, seed + 1),
        "ours": score(env, networks, first(experts.expert_params(ours)), target, eval_episodes, seed + 1),
        "brax": score(env, networks, brax_params, target, eval_episodes, seed + 1),
        "ours_training_return_curve": [float(r) for r in np.asarray(metrics.episode_return[0])],
        # Both walls include compiling: on a CPU that is most of it.
        "ours_wall_s": round(ours_wall, 2),
        "brax_wall_s": round(brax_wall, 2),
    }
    out["return_gap"] = out["ours"]["return_mean"] - out["brax"]["return_mean"]
    out.update(runio.provenance(cfg.preset, time.perf_counter() - start, cfg.env))
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out-dir", default="runs/compare_brax_ppo")
    parser.add_argument("--target", type=float, default=16.0)
    parser.add_argument("--updates", type=int, default=8)
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--set", action="append", nargs="+", default=[], metavar="KEY=VALUE",
                        help="config overrides on top of the comparison's, e.g. env.physics_dt=0.005")  # fmt: skip
    args = parser.parse_args(argv)
    try:
        overrides = cli.parse_overrides(args.set)
        comparison_config(args.target, args.updates, args.num_envs, overrides)  # every value checked up front
    except ValueError as err:
        parser.error(str(err))
    out = compare(args.target, args.updates, args.num_envs, overrides=overrides)
    device = "cpu" if out["device"] == "cpu" else "gpu"
    path = runio.write_json(Path(args.out_dir) / f"compare_brax_ppo_{device}.json", out)
    print(functools.reduce(lambda s, k: s + f"{k}: {out[k]}\n", ("bc_start", "ours", "brax"), ""), path)
    return out


if __name__ == "__main__":
    main()
