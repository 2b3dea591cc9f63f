"""Our vmappable PPO against Brax's `ppo.train` on one kick task, matched hyperparameters.

Both start from the same behaviour-cloned policy (Brax via `restore_params`), see the same
number of env steps in batches of whole 75-step episodes, and are scored on the same fixed
noisy episodes with the deterministic (mean) policy. Writes <out-dir>/compare_brax_ppo_<device>.json.

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
from brax.training.agents.ppo import train as brax_ppo

from bumps_jax import evaluate, experts, kick_env, ppo, results

if not hasattr(jax, "device_put_replicated"):
    # Removed in newer jax; Brax's train still calls it once to replicate its state over devices.
    jax.device_put_replicated = lambda x, devices: jax.tree_util.tree_map(
        lambda a: jnp.broadcast_to(a, (len(devices), *jnp.shape(a))), x
    )


def comparison_config(target: float, n_updates: int, num_envs: int):
    """The expert preset cut to one task and `n_updates` updates of `num_envs` episodes."""
    return experts.make_config(
        overrides={
            "preset": "compare",
            "tasks": (target,),
            "bc.steps": 20000,
            "bc.learning_rate": 1e-2,
            # The one 12 m prior kick: it overshoots 16 m by ~4 m, so there is room to improve.
            "bc.per_task_strength": False,
            "tune.generations": 0,  # the one 12 m kick as it is, as in the runs compared
            "ppo.num_envs": num_envs,
            "ppo.num_minibatches": 4,
            "ppo.num_epochs": 4,
            "ppo.total_env_steps": num_envs * 75 * n_updates,
            "ppo.learning_rate": 3e-5,
            "ppo.init_log_std": -4.0,
            "updates_per_chunk": n_updates,
        }
    )


def brax_network_factory(cfg):
    """Brax's factory signature over our network settings (same policy and value nets)."""

    def factory(obs_size, action_size, preprocess_observations_fn):
        del preprocess_observations_fn  # ours is fixed by cfg.normalize_observations (off)
        return ppo.make_networks(cfg, obs_size, action_size)

    return factory


def brax_settings(p, env) -> dict:
    """Our PPO config `p` as the keyword arguments of Brax's ppo.train (budget and logging aside)."""
    return {
        "environment": env,
        "num_envs": int(p.num_envs),
        "episode_length": env.n_steps,
        "unroll_length": env.n_steps,  # one rollout = one whole episode per env, as ours
        "batch_size": int(p.num_envs // p.num_minibatches),
        "num_minibatches": int(p.num_minibatches),
        "num_updates_per_batch": int(p.num_epochs),
        "learning_rate": float(p.learning_rate),
        "entropy_cost": float(p.entropy_cost),
        "discounting": float(p.discount),
        "gae_lambda": float(p.gae_lambda),
        "clipping_epsilon": float(p.clip_epsilon),
        "reward_scaling": float(p.reward_scaling),
        "max_grad_norm": float(p.max_grad_norm),
        "vf_loss_coefficient": float(p.vf_coefficient),
        "normalize_observations": bool(p.normalize_observations),
        "network_factory": brax_network_factory(p),
    }


def run_brax(cfg, env, init_state: ppo.TrainState, seed: int):
    """Brax's ppo.train with our hyperparameters, from our BC'd params. Returns (ExpertParams, wall_s)."""
    params = jax.tree_util.tree_map(lambda x: x[0], init_state.params)
    normalizer = jax.tree_util.tree_map(lambda x: x[0], init_state.normalizer)
    start = time.perf_counter()
    _, (norm, policy, _value), _ = brax_ppo.train(
        **brax_settings(cfg.ppo, env),
        num_timesteps=int(cfg.ppo.total_env_steps),
        restore_params=(normalizer, params.policy, params.value),
        seed=seed,
        num_evals=1,
        run_evals=False,
    )
    jax.block_until_ready(policy)
    return experts.ExpertParams(norm, policy), time.perf_counter() - start


def score(env, networks, params: experts.ExpertParams, target: float, n_episodes: int, seed: int) -> dict:
    """Deterministic policy on fixed noisy episodes: mean return, final error, valid fraction."""
    episode = jax.jit(jax.vmap(evaluate.return_fn(env, experts.expert_policy(networks)), in_axes=(None, None, 0)))
    ret, metrics = episode(params, target, jax.random.split(jax.random.PRNGKey(seed), n_episodes))
    return {
        "return_mean": float(np.mean(ret)),
        "return_std": float(np.std(ret)),
        "final_error_mean_m": float(np.mean(metrics["final_error"])),
        "valid_fraction": float(np.mean(metrics["valid"])),
    }


def compare(
    target: float = 16.0, n_updates: int = 8, num_envs: int = 16, eval_episodes: int = 32, seed: int = 0
) -> dict:
    start = time.perf_counter()
    cfg = comparison_config(target, n_updates, num_envs)
    # Brax resets through `reset(rng)`, which draws the target from `tasks`: one task only.
    env = kick_env.KickEnv(config_overrides={"tasks": (target,)})
    programs = experts.compile_programs(cfg, env)
    targets = jnp.asarray([target], jnp.float32)
    kicks, _ = experts.starting_kicks(cfg, verbose=False)
    state0, _ = experts.run_init(programs, experts.task_rngs(seed, 1), targets, kicks)
    t0 = time.perf_counter()
    ours, metrics = experts.run_chunk(programs, state0, targets)
    jax.block_until_ready(ours)
    ours_wall = time.perf_counter() - t0

    brax_params, brax_wall = run_brax(cfg, env, state0, seed)

    def squeeze(tree):
        return jax.tree_util.tree_map(lambda x: x[0], tree)

    networks = programs.trainer.networks
    out = {
        "target_m": target,
        "env_steps": int(cfg.ppo.total_env_steps),
        "eval_episodes": eval_episodes,
        "ppo": {k: (list(v) if isinstance(v, tuple) else v) for k, v in cfg.ppo.items()},
        "bc_start": score(env, networks, squeeze(experts.expert_params(state0)), target, eval_episodes, seed + 1),
        "ours": score(env, networks, squeeze(experts.expert_params(ours)), target, eval_episodes, seed + 1),
        "brax": score(env, networks, brax_params, target, eval_episodes, seed + 1),
        "ours_training_return_curve": [float(r) for r in np.asarray(metrics.episode_return[0])],
        # Both walls include compiling: on a CPU that is most of it.
        "ours_wall_s": round(ours_wall, 2),
        "brax_wall_s": round(brax_wall, 2),
    }
    out["return_gap"] = out["ours"]["return_mean"] - out["brax"]["return_mean"]
    out.update(results.provenance("compare", time.perf_counter() - start, physics_dt_s=env.physics_dt))
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out-dir", default="runs/compare_brax_ppo")
    parser.add_argument("--target", type=float, default=16.0)
    parser.add_argument("--updates", type=int, default=8)
    parser.add_argument("--num-envs", type=int, default=16)
    args = parser.parse_args(argv)
    out = compare(args.target, args.updates, args.num_envs)
    device = "cpu" if out["device"] == "cpu" else "gpu"
    path = results.write_json(Path(args.out_dir) / f"compare_brax_ppo_{device}.json", out)
    print(functools.reduce(lambda s, k: s + f"{k}: {out[k]}\n", ("bc_start", "ours", "brax"), ""), path)
    return out


if __name__ == "__main__":
    main()
