"""Our vmappable PPO against Brax's `ppo.train`, matched hyperparameters, on two grounds.

kick (the default): one kick task, one seed. Both start from the same behaviour-cloned policy
(Brax via `restore_params`), see the same number of env steps in batches of whole 75-step
episodes, and are scored on the same fixed noisy episodes with the deterministic (mean) policy.
Writes <out-dir>/compare_brax_ppo_<cpu|gpu>.json.

    python experiments/compare_brax_ppo.py --out-dir experiments/results

halfcheetah: ground our trainer was not tuned on. Brax's own `halfcheetah` env (plain forward
running, Brax's reward: forward velocity - 0.1 |a|^2; MJX backend, MJX's JAX implementation),
1000-step episodes cut by Brax's `EpisodeWrapper`, whose `info["truncation"]` our trainer reads
(`ppo.truncation_of`): both bootstrap through the time limit the same way. Brax's published
halfcheetah PPO settings (`BRAX_HALFCHEETAH`, source cited there), matched where ours can express
them and the rest listed in the record (`MATCHED_DIFFERENCES`). Both train from scratch, 3 seeds
each, for the same env steps (`PRESETS`); every `--eval-every` updates each saves its (normalizer,
policy), and after training every checkpoint of both is scored in one compiled program on the same
fixed episodes with the deterministic (mean) policy. Writes one record,
<out-dir>/compare_brax_ppo_halfcheetah_<cpu|gpu>.json (both trainers' per-seed curves, final
returns, their spread and the verdict), and a .png beside it with both learning curves.

It runs in parts, each saved when it finishes (ours with every seed, then each Brax seed) in
<out-dir>/compare_brax_ppo_halfcheetah_parts/ (`--parts-dir`), with a manifest of the run's
settings: parts of another setting are refused. A call skips the parts already there and trains
the rest; `--stop-after-s S` stops it between parts (exit 0) rather than start one that would take
it past S seconds. The call that finds every part scores them and writes the record. Brax's
compiled programs are kept for later calls (JAX_COMPILATION_CACHE_DIR, or jax_cache/ in the parts
directory). One H100 takes ~17-18 minutes in all (`GPU_ESTIMATE`): run the same command until it
writes the record, four calls of ~4-5 minutes each:

    python experiments/compare_brax_ppo.py --mode halfcheetah --preset gpu --stop-after-s 420

At the gpu preset's 2.56 M env steps per seed neither trainer's policy has learned to run. The
gpu_10m preset trains both for 10.24 M env steps per seed on 100-step episodes (scored on whole
1000-step episodes, as the gpu preset): <out-dir>/compare_brax_ppo_halfcheetah_gpu_10m_gpu.json.

    python experiments/compare_brax_ppo.py --mode halfcheetah --preset gpu_10m --stop-after-s 540

Brax's AutoResetWrapper restarts each env from its own first state, so Brax trains from num_envs
start states while ours draws fresh resets every update. `--brax-resets fresh` matches that (Brax's
own `num_resets_per_eval`: new keys after every update): <record name>_fresh_resets.json. Seeds
other than 0 1 2 name the record too (`--seeds 0 1 2 3 4 5`: <record name>_seeds0-5.json). Beside
the spread verdict the record gives Welch's t-test of the two mean final returns.

`--preset smoke` runs the same comparison at CPU size (4 episodes of 100 steps per update, 2
updates, 3 seeds each) on Brax's `fast` env, a stand-in without physics: under a minute on 2 CPU
cores, a record and a plot (runs/compare_brax_ppo/compare_brax_ppo_fast_smoke_cpu.json), not a
result. Each MJX program takes ~30 s per reset or step in it to compile on a CPU, so
`--preset smoke --env halfcheetah` (the same sizes on the real env) takes minutes.

    python experiments/compare_brax_ppo.py --mode halfcheetah --preset smoke

Brax runs through `experiments.brax_compat` in both modes.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import functools
import json
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats
from brax import envs as brax_envs
from jax.experimental.compilation_cache import compilation_cache as cc

from bumps_jax import cli, config, resumable, runio
from bumps_jax import records as env_records
from bumps_jax.algo import ppo, ppo_config, rollout
from bumps_jax.pipeline import expert_programs
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model
from experiments import brax_compat


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
    return expert_programs.ExpertParams(norm, policy), time.perf_counter() - start


def score(env, networks, params: expert_programs.ExpertParams, target: float, n_episodes: int, seed: int) -> dict:
    """Deterministic policy on fixed noisy episodes: mean return, final error, valid fraction."""
    episodes = jax.jit(
        rollout.over_reps(rollout.episode_fn(env, expert_programs.expert_policy(networks), record="return"))
    )
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
    programs = expert_programs.compile_programs(cfg, env)
    targets = jnp.asarray([target], jnp.float32)
    record = kick_model.load_record(kick_model.ASSET, env_cfg=cfg.env)
    # The one 12 m prior kick: it overshoots 16 m by ~4 m, so there is room to improve.
    kicks = record["anchors"][None, kick_model.ANCHORS.index("main")]
    state0, _ = expert_programs.run_init(programs, expert_programs.task_rngs(seed, 1), targets, kicks)
    t0 = time.perf_counter()
    ours, metrics = expert_programs.run_chunk(programs, state0, targets)
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
        "bc_start": score(env, networks, first(expert_programs.expert_params(state0)), target, eval_episodes, seed + 1),
        "ours": score(env, networks, first(expert_programs.expert_params(ours)), target, eval_episodes, seed + 1),
        "brax": score(env, networks, brax_params, target, eval_episodes, seed + 1),
        "ours_training_return_curve": [float(r) for r in np.asarray(metrics.episode_return[0])],
        # Both walls include compiling: on a CPU that is most of it.
        "ours_wall_s": round(ours_wall, 2),
        "brax_wall_s": round(brax_wall, 2),
    }
    out["return_gap"] = out["ours"]["return_mean"] - out["brax"]["return_mean"]
    out.update(runio.provenance(cfg.preset, time.perf_counter() - start, config.resolved_env(cfg)))
    return out


# -- halfcheetah ------------------------------------------------------------------------------

# Brax's published PPO settings for `halfcheetah` (BRAX_HALFCHEETAH_SOURCE): the `train_fn` table
# of Brax's training notebook. What it leaves out takes `ppo.train`'s defaults
# at that tag: gae_lambda 0.95, clipping_epsilon 0.3, vf_loss_coefficient 0.5, normalize_advantage
# True, max_grad_norm None; networks `make_ppo_networks`' (policy 4 x 32, value 5 x 256, swish,
# tanh-squashed Gaussian, initial std 1).
BRAX_HALFCHEETAH = {
    "num_timesteps": 50_000_000,
    "num_evals": 20,
    "reward_scaling": 1,
    "episode_length": 1000,
    "normalize_observations": True,
    "action_repeat": 1,
    "unroll_length": 20,
    "num_minibatches": 32,
    "num_updates_per_batch": 8,
    "discounting": 0.95,
    "learning_rate": 3e-4,
    "entropy_cost": 0.001,
    "num_envs": 2048,
    "batch_size": 512,
    "seed": 3,
}
BRAX_HALFCHEETAH_SOURCE = "google/brax notebooks/training.ipynb, tag v0.14.2 (f489566), train_fn['halfcheetah']"
EPISODE_LENGTH = BRAX_HALFCHEETAH["episode_length"]
# Ours must clip the gradient's norm (ppo.max_grad_norm > 0); Brax's settings clip nothing. Both
# clip here at a norm no gradient reaches, which leaves every step as it is.
NO_CLIP = 1e9
MATCHED_DIFFERENCES = (
    "rollouts: ours collects whole episodes from fresh resets every update; Brax is run the same "
    "way (unroll_length = episode_length, the record's env.episode_length: num_envs episodes per "
    "update, one unroll per env), not with its published 2048 envs x 20-step unrolls x 8",
    "budget: env_steps_per_seed, not the published 50M; num_envs whole episodes per update in "
    "num_minibatches minibatches (published: 327,680 steps per update in 32 minibatches of 10,240)",
    "episodes: both train on episodes of env.episode_length steps, cut by Brax's EpisodeWrapper and "
    "bootstrapped through the cut the same way; both are scored on episodes of eval_episode_length "
    "(the published 1000)",
    "networks: both ours (ppo.make_networks, given to Brax as its network factory): tanh MLPs, not "
    "swish; an unsquashed Gaussian with a learned state-independent log-std, not a tanh-squashed one; "
    "the env clips actions to [-1, 1], its control cost is paid on the unclipped action",
    f"gradient clipping at a norm of {NO_CLIP:g} in both (none in effect; Brax's settings: none)",
)
# What each `--brax-resets` mode makes of the one setting the two trainers may start differently.
# first: Brax as it ships (its AutoResetWrapper); fresh: Brax's own `num_resets_per_eval`, one
# reset per update with new keys, so that both start every update's episodes from fresh resets.
BRAX_RESETS = {
    "first": "resets: Brax's AutoResetWrapper restarts each env from its own first state (num_envs start "
    "states for the whole run); ours draws a fresh reset every update",
    "fresh": "resets: matched, both from fresh resets every update (Brax: num_resets_per_eval = eval_every, "
    "a reset with new keys after every update; its AutoResetWrapper's restart is replaced before it steps)",
}


def differences(brax_resets: str) -> list[str]:
    """The record's `differences`: what is not matched, and how the starts of episodes compare."""
    return [*MATCHED_DIFFERENCES, BRAX_RESETS[brax_resets]]


def cheetah_ppo_config(num_envs: int, num_minibatches: int, env_steps: int):
    """Our PPO section set to Brax's halfcheetah settings (`BRAX_HALFCHEETAH`): a locked ConfigDict."""
    b = BRAX_HALFCHEETAH
    return ppo_config.make_config(
        overrides={
            "num_envs": num_envs,
            "num_minibatches": num_minibatches,
            "num_epochs": b["num_updates_per_batch"],
            "total_env_steps": env_steps,
            "learning_rate": b["learning_rate"],
            "value_learning_rate": b["learning_rate"],  # Brax: one Adam for both networks
            "anneal_learning_rate": False,
            "max_grad_norm": NO_CLIP,
            "discount": b["discounting"],
            "gae_lambda": 0.95,
            "clip_epsilon": 0.3,
            "entropy_cost": b["entropy_cost"],
            "vf_coefficient": 0.5,
            "reward_scaling": float(b["reward_scaling"]),
            "normalize_advantage": True,
            "normalize_observations": b["normalize_observations"],
            "policy_hidden": (32,) * 4,
            "value_hidden": (256,) * 5,
            "init_log_std": 0.0,  # Brax's init_noise_std 1
        }
    )


class TimeLimited:
    """Brax's env as our trainer takes it: `reset(rng, target)` (one task: the target is ignored)
    and episodes of `n_steps`, whose last step Brax's `EpisodeWrapper` flags in `info["truncation"]`."""

    def __init__(self, env, episode_length: int):
        self.env = brax_envs.training.EpisodeWrapper(env, episode_length, action_repeat=1)
        self.n_steps = episode_length
        self.observation_size = env.observation_size
        self.action_size = env.action_size

    def reset(self, rng: jax.Array, target=None):
        del target
        return self.env.reset(rng)

    def step(self, state, action: jax.Array):
        return self.env.step(state, action)


ENVS = ("halfcheetah", "fast")


def make_brax_env(name: str):
    """Brax's `halfcheetah` on MJX (MJX's JAX implementation), or Brax's `fast`: a unit-test stand-in
    with no physics (a point pushed along a line) whose programs compile in seconds on a CPU."""
    if name not in ENVS:
        raise ValueError(f"env must be one of {ENVS}, got {name!r}")
    return brax_envs.get_environment(name, backend="mjx") if name == "halfcheetah" else brax_envs.get_environment(name)


def env_record(name: str, env, episode_length: int) -> dict:
    """The env config a record carries: physics step (s), backend and what else fixes the task."""
    if name == "fast":
        # No physics: one explicit Euler step of `env._dt` per control step.
        return {"name": "fast", "impl": "none", "physics_dt": float(env._dt), "episode_length": episode_length}
    return {
        "name": name,
        "backend": "mjx",
        "impl": "jax",  # MJX's JAX implementation
        "physics_dt": float(env.sys.opt.timestep),
        "n_frames": int(env._n_frames),
        "ctrl_dt": float(env.dt),
        "solver_iterations": int(env.sys.opt.iterations),
        "episode_length": episode_length,
        "reward": "forward velocity - 0.1 * sum(action ** 2)",
    }


def _episode_return(env: TimeLimited, networks, normalizer, policy_params, key) -> jax.Array:
    """One whole episode of the mean policy: the sum of its rewards (a scalar)."""

    def step(state, _):
        nxt = env.step(state, ppo.policy_mean(networks, normalizer, policy_params, state.obs))
        return nxt, nxt.reward

    _, rewards = jax.lax.scan(step, env.reset(key), None, env.n_steps)
    return rewards.sum()


def make_evaluator(env: TimeLimited, networks, n_episodes: int, seed: int):
    """(normalizers, policy params), each with a leading axis of P policies -> returns (P, n_episodes)
    of the deterministic policy on the same fixed episodes. Every checkpoint of both trainers is
    scored in one call after training: an episode is 1000 sequential steps, so one call of many
    policies costs about what one call of one policy costs."""
    keys = jax.random.split(jax.random.PRNGKey(seed), n_episodes)
    per_policy = jax.vmap(functools.partial(_episode_return, env, networks), in_axes=(None, None, 0))
    returns = jax.jit(jax.vmap(per_policy, in_axes=(0, 0, None)))

    def evaluate(normalizers, policies):
        return np.asarray(returns(normalizers, policies, keys))

    return evaluate


def _host(tree):
    """A copy on the host with plain dtypes: Brax's params come back from pmap typed otherwise than
    ours from vmap (weak types), and the device's copy is freed for the training that goes on."""
    return jax.tree_util.tree_map(lambda x: np.asarray(x), tree)


def _stack(trees):
    return jax.tree_util.tree_map(lambda *xs: np.stack(xs), *trees)


class Progress:
    """Progress lines with an ETA, counting updates: ours' (every seed in one program) count once,
    Brax's once per seed, so `total` is n_updates x (1 + seeds). Each Brax seed compiles again, so
    the ETA runs long while Brax's seeds remain."""

    def __init__(self, total_updates: int, say=print):
        self.total, self.done, self.say, self.pace = total_updates, 0, say, resumable.Clock(total_updates)

    def __call__(self, updates: int, text: str) -> None:
        self.done += updates
        self.say(f"  {text}  [{self.done}/{self.total} updates, {self.pace.tick(self.done)}]", flush=True)


def run_ours_cheetah(cfg, env: TimeLimited, seeds, eval_every: int, progress: Progress) -> dict:
    """Our trainer, every seed in one vmapped program; a host copy of each seed's (normalizer,
    policy) every `eval_every` updates, scored later (`make_evaluator`)."""
    trainer = ppo.make_train(cfg, env)
    init = jax.jit(jax.vmap(trainer.init))
    chunk = jax.jit(jax.vmap(functools.partial(trainer.run_updates, n=eval_every), in_axes=(0, None)))
    start = time.perf_counter()
    state = init(jnp.stack([jax.random.PRNGKey(s) for s in seeds]))
    steps, checkpoints, collected = [0], [_host((state.normalizer, state.params.policy))], []
    for _ in range(trainer.n_updates // eval_every):
        state, metrics = chunk(state, jnp.float32(0.0))
        collected.append(np.asarray(metrics.episode_return))  # (seeds, eval_every)
        checkpoints.append(_host((state.normalizer, state.params.policy)))
        steps.append(int(state.env_steps[0]))
        train_return = np.round(collected[-1][:, -1].astype(float), 1).tolist()  # the last update's, per seed
        progress(eval_every, f"ours  {steps[-1]:>10,d} steps  training return {train_return}")
    return {
        "env_steps": steps,
        "checkpoints": checkpoints,  # (evals,) of trees with a leading seed axis
        "training_return": np.concatenate(collected, axis=1).tolist(),  # (seeds, updates), stochastic policy
        "wall_s": round(time.perf_counter() - start, 2),
    }


def run_brax_cheetah(
    cfg, env: TimeLimited, raw_env, seed: int, eval_every: int, progress: Progress, brax_resets: str = "first"
) -> dict:
    """Brax's `ppo.train` on the raw env (Brax wraps it with its own EpisodeWrapper and
    AutoResetWrapper), one whole episode per env per update like ours; a host copy of its
    (normalizer, policy) from `policy_params_fn` at the same env steps as ours. Brax's own
    evaluator is off. `brax_resets` (`BRAX_RESETS`): "fresh" resets every env with new keys after
    every update (Brax's `num_resets_per_eval`), as ours starts each update; "first": Brax's default."""
    steps_per_update = int(cfg.num_envs) * env.n_steps
    n_evals = int(cfg.total_env_steps) // (steps_per_update * eval_every)
    steps, checkpoints = [], []

    def on_params(step, make_policy, params):
        del make_policy
        normalizer, policy, _value = params
        checkpoints.append(_host((normalizer, policy)))
        steps.append(int(step))
        if step:
            progress(eval_every, f"brax  {int(step):>10,d} steps  (seed {seed})")

    start = time.perf_counter()
    brax_compat.train(
        cfg,
        env,
        environment=raw_env,
        num_timesteps=n_evals * eval_every * steps_per_update,
        num_evals=n_evals + 1,
        run_evals=False,
        num_eval_envs=1,  # Brax builds its evaluator even when it does not run it
        policy_params_fn=on_params,
        seed=seed,
        num_resets_per_eval=eval_every if brax_resets == "fresh" else 0,
    )
    return {"env_steps": steps, "checkpoints": checkpoints, "wall_s": round(time.perf_counter() - start, 2)}


def score_checkpoints(evaluate, ours_checkpoints, brax_checkpoints) -> tuple[np.ndarray, np.ndarray]:
    """Mean return of every checkpoint, in one call: ((seeds, evals) ours, (seeds, evals) Brax).
    ours_checkpoints: (evals,) of trees with a leading seed axis; brax_checkpoints: (seeds,) of
    (evals,) of trees."""
    ours = [_seed(tree, i) for i in range(len(brax_checkpoints)) for tree in ours_checkpoints]
    brax = [tree for run in brax_checkpoints for tree in run]
    returns = evaluate(*_stack(ours + brax)).mean(axis=1)
    n_seeds, n_evals = len(brax_checkpoints), len(ours_checkpoints)
    return returns[: len(ours)].reshape(n_seeds, n_evals), returns[len(ours) :].reshape(n_seeds, n_evals)


def _seed(tree, i: int):
    return jax.tree_util.tree_map(lambda x: x[i], tree)


def spread_check(ours_final, brax_final) -> dict:
    """Is each trainer's mean final return inside the range (min to max) of the other's seeds? And
    Welch's t-test of the two means (unequal variances; two-sided p; None below 2 seeds an arm,
    NaN, which the record writes as null, where neither arm's returns vary)."""
    ours_final, brax_final = np.asarray(ours_final), np.asarray(brax_final)
    ours_in = bool(brax_final.min() <= ours_final.mean() <= brax_final.max())
    brax_in = bool(ours_final.min() <= brax_final.mean() <= ours_final.max())
    welch_t = welch_p = None
    if min(ours_final.size, brax_final.size) >= 2:
        test = scipy.stats.ttest_ind(ours_final, brax_final, equal_var=False)
        welch_t, welch_p = float(test.statistic), float(test.pvalue)
    return {
        "ours_mean_in_brax_range": ours_in,
        "brax_mean_in_ours_range": brax_in,
        "within_each_others_spread": ours_in and brax_in,
        "welch_t": welch_t,
        "welch_p": welch_p,
    }


def arm_record(env_steps, eval_return) -> dict:
    """One trainer's curves (seeds x evals, at `env_steps`) and its final returns' spread."""
    curves = np.asarray(eval_return, dtype=float)
    final = curves[:, -1]
    return {
        "env_steps": [int(s) for s in env_steps],
        "eval_return": curves.tolist(),  # (seeds, evals)
        "final_return": final.tolist(),
        "final_return_mean": float(final.mean()),
        "final_return_std": float(final.std()),
        "final_return_range": [float(final.min()), float(final.max())],
    }


def comparison_record(env_steps, ours_curves, brax_curves) -> dict:
    """Both trainers' curves, final returns and the verdict: the record's result keys."""
    ours, brax = arm_record(env_steps, ours_curves), arm_record(env_steps, brax_curves)
    return {
        "ours": ours,
        "brax": brax,
        "final_return_gap": ours["final_return_mean"] - brax["final_return_mean"],
        **spread_check(ours["final_return"], brax["final_return"]),
    }


def check_cheetah_run(num_envs: int, num_minibatches: int, env_steps: int, eval_every: int, episode_length: int):
    """Our PPO config of the run (`cheetah_ppo_config`), or ValueError naming the bad setting."""
    cfg = cheetah_ppo_config(num_envs, num_minibatches, env_steps)
    ppo_config.validate_config(cfg, episode_length, prefix="")
    per_eval = num_envs * episode_length * eval_every
    if eval_every < 1 or env_steps % per_eval:
        raise ValueError(
            f"env_steps {env_steps} must be a multiple of num_envs x episode length x eval_every = {per_eval}"
        )
    return cfg


# -- halfcheetah in parts ----------------------------------------------------------------------
# The gpu preset takes longer than one call may run, so the comparison is made of parts, each saved
# when it finishes: ours (every seed in one program) and each Brax seed. A call trains the parts
# not yet in the parts directory, one after another; the call that finds them all scores them.


def part_names(seeds) -> list[str]:
    """The parts of a run, in the order they train: ours, then Brax's seeds."""
    return ["ours", *(f"brax_seed{s}" for s in seeds)]


def run_settings(cfg, env_name: str, episode_length: int, seeds, eval_every: int, brax_resets: str = "first") -> dict:
    """What a part's result depends on: the parts directory's manifest. Scoring settings
    (eval_episodes) are left out: a rerun may score the same parts otherwise."""
    return runio.json_safe(
        {
            "env_name": env_name,
            "episode_length": episode_length,
            "seeds": list(seeds),
            "eval_every": eval_every,
            "backend": jax.default_backend(),
            "versions": {k: v for k, v in runio.versions().items() if k in ("jax", "brax", "mujoco-mjx")},
            "ppo": {k: (list(v) if isinstance(v, tuple) else v) for k, v in cfg.items()},
        }
        # Brax's default resets name no key, so the parts of runs made before the choice existed still match.
        | ({} if brax_resets == "first" else {"brax_resets": brax_resets})
    )


def open_parts(directory: Path, settings: dict) -> Path:
    """The parts directory for a run of `settings` (`run_settings`): created with its manifest,
    or checked against the manifest it has. ValueError, in one line naming every differing
    setting, when it holds parts of another run."""
    manifest = directory / "manifest.json"
    if not manifest.exists():
        runio.write_json(manifest, {"settings": settings})
        return directory
    theirs = runio.read_json(manifest, "the parts' settings").get("settings", {})
    differ = [f"{k} {env_records.lookup(theirs, k)!r} there, {env_records.lookup(settings, k)!r} here"
              for k in env_records.differing_keys(theirs, settings)]  # fmt: skip
    if differ:
        raise ValueError(
            f"{runio.shown(directory)} holds the parts of another run ({'; '.join(differ)}): "
            "use another --parts-dir or delete it"
        )
    return directory


def checkpoint_treedef(cfg, env: TimeLimited):
    """The tree structure of one checkpoint, (normalizer, policy params) of `ppo.make_networks`:
    a part's saved leaves are rebuilt on it, and a part saved with another is refused."""
    networks = ppo.make_networks(cfg, env.observation_size, env.action_size)

    def init():
        return ppo.init_normalizer(env.observation_size), networks.policy_network.init(jax.random.PRNGKey(0))

    return jax.tree_util.tree_structure(jax.eval_shape(init))


def save_part(path: Path, run: dict) -> Path:
    """One finished part as one .npz, written whole or not at all (temp file, then rename): its
    checkpoints stacked over evals (arrays `leaf<i>`, in tree order) and the rest of `run`
    (env_steps, wall_s, ...) as JSON with the checkpoints' tree structure."""
    leaves, treedef = jax.tree_util.tree_flatten(_stack(run["checkpoints"]))
    meta = {k: v for k, v in run.items() if k != "checkpoints"} | {"treedef": str(treedef)}
    arrays = {f"leaf{i}": np.asarray(leaf) for i, leaf in enumerate(leaves)}
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("wb") as f:
        np.savez(f, meta=np.array(json.dumps(runio.json_safe(meta))), **arrays)
    os.replace(tmp, path)
    return path


def part_meta(path: Path) -> dict:
    """A saved part's JSON: env_steps, wall_s, device, date, and what else its trainer recorded."""
    with np.load(path, allow_pickle=False) as data:
        return json.loads(str(data["meta"]))


def load_part(path: Path, treedef) -> dict:
    """A saved part as its trainer returned it: (evals,) host checkpoints on `treedef`, and the rest."""
    with np.load(path, allow_pickle=False) as data:
        run = json.loads(str(data["meta"]))
        if run.pop("treedef") != str(treedef):
            raise ValueError(
                f"{runio.shown(path)}: its checkpoints are not trees of this run's networks: delete it to train it anew"
            )
        stacked = jax.tree_util.tree_unflatten(treedef, [data[f"leaf{i}"] for i in range(treedef.num_leaves)])
    run["checkpoints"] = [_seed(stacked, k) for k in range(len(run["env_steps"]))]
    return run


def stop_before_next(elapsed_s: float, walls_s, stop_after_s: float | None) -> bool:
    """`--stop-after-s`: after a call's first part, is the next one not to start? It is not when the
    call's elapsed time plus the next part's expected duration would pass `stop_after_s`; expected:
    the longest part measured so far (`walls_s`, this call's and earlier calls')."""
    return stop_after_s is not None and elapsed_s + max(walls_s) > stop_after_s


def compare_cheetah(
    env_steps: int,
    num_envs: int,
    num_minibatches: int,
    eval_every: int,
    parts_dir: Path,
    seeds=(0, 1, 2),
    eval_episodes: int = 64,
    episode_length: int = EPISODE_LENGTH,
    eval_episode_length: int | None = None,
    env_name: str = "halfcheetah",
    preset: str = "gpu",
    stop_after_s: float | None = None,
    brax_resets: str = "first",
    say=print,
) -> dict | None:
    """Both trainers from scratch on Brax's `env_name` (`ENVS`), every seed, scored the same way:
    the record. Both train on episodes of `episode_length` steps and are scored on episodes of
    `eval_episode_length` (default: the same); Brax's resets as `brax_resets` says (`BRAX_RESETS`).
    Parts already in `parts_dir` (checked by `open_parts`) are skipped; with `stop_after_s` it may
    stop between parts (`stop_before_next`) and returns None."""
    start = time.perf_counter()
    cfg = check_cheetah_run(num_envs, num_minibatches, env_steps, eval_every, episode_length)
    open_parts(parts_dir, run_settings(cfg, env_name, episode_length, seeds, eval_every, brax_resets))
    raw_env = make_brax_env(env_name)
    env = TimeLimited(raw_env, episode_length)
    treedef = checkpoint_treedef(cfg, env)
    paths = {name: parts_dir / f"{name}.npz" for name in part_names(seeds)}
    walls, earlier_s = [], 0.0
    for name, path in paths.items():
        if path.exists():
            wall = part_meta(path)["wall_s"]
            walls.append(wall)
            earlier_s += wall
            say(f"{name}: done in an earlier call ({wall:.0f} s), skipped", flush=True)
    todo = [name for name, path in paths.items() if not path.exists()]
    brax_seed = dict(zip(part_names(seeds)[1:], seeds, strict=True))
    n_updates = env_steps // (num_envs * episode_length)
    progress = Progress(n_updates * len(todo), say)
    for i, name in enumerate(todo):
        elapsed = time.perf_counter() - start
        if i and stop_before_next(elapsed, walls, stop_after_s):
            say(
                f"stopped after {elapsed:.0f} s (--stop-after-s {stop_after_s:g}; the next part is expected to take "
                f"{max(walls):.0f} s): left {', '.join(todo[i:])} and the scoring. The parts done are in "
                f"{runio.shown(parts_dir)}: rerun the same command to go on",
                flush=True,
            )
            return None
        if name == "ours":
            say(f"ours: {len(seeds)} seeds in one program, {env_steps:,d} env steps each ({n_updates} updates)",
                flush=True)  # fmt: skip
            run = run_ours_cheetah(cfg, env, seeds, eval_every, progress)
        else:
            say(f"brax: seed {brax_seed[name]}", flush=True)
            run = run_brax_cheetah(cfg, env, raw_env, brax_seed[name], eval_every, progress, brax_resets)
        run.update(device=runio.device_name(), date=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"))
        save_part(paths[name], run)
        walls.append(run["wall_s"])
    parts = {name: load_part(path, treedef) for name, path in paths.items()}
    ours, brax_runs = parts["ours"], [parts[name] for name in part_names(seeds)[1:]]
    if any(run["env_steps"] != ours["env_steps"] for run in brax_runs):
        raise RuntimeError(f"Brax saved params at {brax_runs[0]['env_steps']}, ours at {ours['env_steps']}")
    n_policies = 2 * len(seeds) * len(ours["env_steps"])
    say(f"scoring {n_policies} checkpoints x {eval_episodes} episodes, deterministic policy", flush=True)
    t = time.perf_counter()
    networks = ppo.make_networks(cfg, env.observation_size, env.action_size)
    eval_env = TimeLimited(raw_env, eval_episode_length or episode_length)
    evaluate = make_evaluator(eval_env, networks, eval_episodes, seed=1000)
    ours_curves, brax_curves = score_checkpoints(
        evaluate, ours.pop("checkpoints"), [r["checkpoints"] for r in brax_runs]
    )
    eval_wall = time.perf_counter() - t
    result = comparison_record(ours["env_steps"], ours_curves, brax_curves)
    result["ours"].update(training_return=ours["training_return"], wall_s=ours["wall_s"])
    result["brax"]["wall_s"] = [run["wall_s"] for run in brax_runs]
    out = {
        "mode": "halfcheetah",
        "env_name": env_name,
        "seeds": list(seeds),
        "env_steps_per_seed": int(env_steps),
        "steps_per_update": num_envs * episode_length,
        "eval_every_updates": eval_every,
        "eval_episodes": eval_episodes,
        "eval_episode_length": eval_env.n_steps,
        "eval": "deterministic (mean) policy, the same fixed episodes for every checkpoint of both trainers",
        "eval_wall_s": round(eval_wall, 2),
        # Where and when each part trained: a run may take several calls (`--stop-after-s`).
        "parts": {name: {k: part[k] for k in ("device", "date", "wall_s")} for name, part in parts.items()},
        "brax_published": BRAX_HALFCHEETAH,
        "brax_published_source": BRAX_HALFCHEETAH_SOURCE,
        "ppo": {k: (list(v) if isinstance(v, tuple) else v) for k, v in cfg.items()},
        "brax_train_kwargs": {
            k: v for k, v in brax_compat.train_kwargs(cfg, env).items() if k not in ("environment", "network_factory")
        },
        "brax_resets": brax_resets,
        "differences": differences(brax_resets),
        **result,
    }
    record_env = env_record(env_name, raw_env, episode_length)
    # wall_s: this call's and the parts' of earlier calls.
    out.update(runio.provenance(preset, earlier_s + time.perf_counter() - start, record_env))
    out["env"] = record_env  # as it is: provenance's reading of it adds the kick env's keys
    return out


def plot_cheetah(out: dict, path: Path) -> Path:
    """Return against env steps, one thin line per seed and the mean, for both trainers."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, color in (("ours", "tab:blue"), ("brax", "tab:orange")):
        steps = np.asarray(out[name]["env_steps"]) / 1e6
        curves = np.asarray(out[name]["eval_return"])
        for curve in curves:
            ax.plot(steps, curve, color=color, alpha=0.3, lw=1)
        ax.plot(steps, curves.mean(axis=0), color=color, lw=2, label=f"{name} (mean of {len(curves)} seeds)")
    ax.set_xlabel("env steps (millions)")
    ax.set_ylabel("return, deterministic policy")
    ax.set_title(f"{out['env_name']}: our PPO and Brax's, {out['device']}")
    ax.legend()
    return runio.save_figure(fig, path)


# The halfcheetah presets (`--preset`): num_envs (whole episodes per update), num_minibatches,
# eval_every (updates between saved checkpoints), env_steps (per seed), eval_episodes (per checkpoint).
# gpu: 8 updates of 320 whole episodes, 2,560,000 env steps per seed (Brax's published budget is
# 50M). An update is 320,000 steps in 32 minibatches of 10 episodes (10,000 steps), 8 epochs: about
# Brax's published update (2048 envs x 20 steps x 8 unrolls = 327,680 steps in 32 minibatches of 10,240).
# At that budget neither trainer's policy runs (the gpu record of 2026-11-24: final returns near 0),
# so its verdict says little. gpu_10m: 10.24 M env steps per seed, 4x the gpu preset's, in 50
# updates of 2048 training episodes of 100 steps (204,800 steps, 32 minibatches of 6,400): an
# update's cost is its 100 sequential steps, so 50 of them fit one device call per part; scored,
# as the gpu preset, on whole 1000-step episodes.
# smoke: Brax's `fast` stand-in env, 100-step episodes, 2 updates of 4 episodes: a record and a plot, not a result.
PRESETS = {
    "gpu": {"num_envs": 320, "num_minibatches": 32, "eval_every": 2, "env_steps": 320 * 1000 * 8, "eval_episodes": 64},
    "gpu_10m": {
        "num_envs": 2048,
        "num_minibatches": 32,
        "eval_every": 10,
        "env_steps": 2048 * 100 * 50,
        "eval_episodes": 64,
    },
    "smoke": {"num_envs": 4, "num_minibatches": 2, "eval_every": 1, "env_steps": 4 * 100 * 2, "eval_episodes": 2},
}
# Per preset: Brax's env, the training episodes' length and the scored episodes' length (steps).
PRESET_ENV = {
    "gpu": ("halfcheetah", EPISODE_LENGTH, EPISODE_LENGTH),
    "gpu_10m": ("halfcheetah", 100, EPISODE_LENGTH),
    "smoke": ("fast", 100, 100),
}
# The gpu preset on one H100, measured on 2026-11-23 in one call, stopped at 550 s: ours, 3 seeds in
# one program, 8 updates: 231 s, compiling included. Brax, seed 0: 102 s for its first 2 updates,
# compiling included, then ~27 s an update (55.6 and 53.1 s for the next two pairs). Not reached:
# the rest of seed 0, seeds 1 and 2 (their programs load from the compilation cache) and the
# scoring. Projected from these: Brax's seed 0 ~265 s, each later seed 216-265 s; ~16-17 min in
# all. Each part is 231-265 s, so `--stop-after-s 420` makes each call one part (a second would
# take it past 420 s) and the run four calls; the fourth also scores. The whole run, 2026-11-24
# (one H100, four calls): ours 249 s, Brax's seeds 275, 236 and 235 s, 1,050 s with the scoring.
# gpu_10m, measured 2026-11-24 (one H100, fresh resets, 6 seeds, four calls): ours, 6 seeds in one
# program, 256 s; Brax's seeds 175-228 s each (the first compiling); 1,431 s with the scoring.
# The projection made before it, from the gpu preset: an update costs its sequential steps, ~31 ms a step
# for ours' 3 x 320 episodes and ~27 ms for one Brax seed's 320; at 6.4x the episodes per step,
# guessed 2-3x that: ours ~6-8 min, each Brax seed ~4-5 min, ~20 min in all, one part per call.
GPU_ESTIMATE = {
    "gpu": "~17-18 minutes on one H100 in all (measured 2026-11-24: parts of 235-275 s, compiling included): "
    "run it in parts, rerunning the same command with --stop-after-s 420 until it writes the record (four calls)",
    "gpu_10m": "~13 minutes on one H100 for 3 seeds each, ~24 for 6 (measured 2026-11-24): run it in parts, "
    "rerunning the same command with --stop-after-s 540 until it writes the record",
}


def main(argv=None) -> dict | None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--mode", choices=("kick", "halfcheetah"), default="kick", help="the ground (see above)")
    parser.add_argument("--out-dir", help="kick: runs/compare_brax_ppo; halfcheetah: experiments/results (gpu), "
                        "runs/compare_brax_ppo (smoke)")  # fmt: skip
    parser.add_argument("--num-envs", type=int, help="episodes per update (kick: 16; halfcheetah: the preset's)")
    kick = parser.add_argument_group("kick")
    kick.add_argument("--target", type=float, default=16.0)
    kick.add_argument("--updates", type=int, default=8)
    kick.add_argument("--set", action="append", nargs="+", default=[], metavar="KEY=VALUE",
                      help="config overrides on top of the comparison's, e.g. env.physics_dt=0.005")  # fmt: skip
    cheetah = parser.add_argument_group("halfcheetah (defaults: the preset's, PRESETS)")
    cheetah.add_argument("--preset", choices=tuple(PRESETS), default="gpu",
                         help="gpu: the comparison (1000-step episodes); smoke: CPU-sized, not a result")  # fmt: skip
    cheetah.add_argument("--env", choices=ENVS, help="Brax's env (default: halfcheetah; smoke: fast)")
    cheetah.add_argument("--env-steps", type=int, help="per seed, a multiple of num_envs x episode length x eval-every")
    cheetah.add_argument("--num-minibatches", type=int)
    cheetah.add_argument("--eval-every", type=int, help="updates between scored checkpoints")
    cheetah.add_argument("--eval-episodes", type=int)
    cheetah.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    cheetah.add_argument("--brax-resets", choices=tuple(BRAX_RESETS), default="first",
                         help="first: Brax's AutoResetWrapper as it ships (each env restarts from its first state); "
                         "fresh: Brax resets every env with new keys after every update, as ours (record name "
                         "+ _fresh_resets)")  # fmt: skip
    cheetah.add_argument("--parts-dir", help="where finished parts are saved (default <out-dir>/<record name>_parts)")
    cheetah.add_argument("--stop-after-s", type=float, metavar="S",
                         help="after a part, start no other whose expected duration (the longest part measured, "
                         "in this call or an earlier one) would take this call past S seconds; 0: one part a call. "
                         "Rerun the same command to go on")  # fmt: skip
    args = parser.parse_args(argv)
    if args.mode == "halfcheetah":
        # JAX_COMPILATION_CACHE_DIR, where set, holds the compilation cache.
        return main_cheetah(parser, args, os.environ.get("JAX_COMPILATION_CACHE_DIR"))
    try:
        overrides = cli.parse_overrides(args.set)
        num_envs = args.num_envs or 16
        comparison_config(args.target, args.updates, num_envs, overrides)  # every value checked up front
    except ValueError as err:
        parser.error(str(err))
    out = compare(args.target, args.updates, num_envs, overrides=overrides)
    path = runio.write_experiment(args.out_dir or "runs/compare_brax_ppo", "compare_brax_ppo", out)
    print(functools.reduce(lambda s, k: s + f"{k}: {out[k]}\n", ("bc_start", "ours", "brax"), ""), path)
    return out


@contextlib.contextmanager
def compilation_cache(directory):
    """JAX's persistent compilation cache in `directory` (every program, however quick to compile)
    while inside; JAX's own settings again after. Brax's `ppo.train` compiles its programs afresh on
    every call: with the cache its later seeds, in this call or a later one, load the first's."""
    before = (jax.config.jax_compilation_cache_dir, jax.config.jax_persistent_cache_min_compile_time_secs)
    jax.config.update("jax_compilation_cache_dir", str(directory))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    try:
        yield
    finally:
        jax.config.update("jax_compilation_cache_dir", before[0])
        jax.config.update("jax_persistent_cache_min_compile_time_secs", before[1])
        cc.reset_cache()  # JAX opens its cache once, at the first compile; the next one opens anew


def seeds_suffix(seeds) -> str:
    """The record name's mark for seeds other than the default 0 1 2: `_seeds0-5` for a run of
    seeds, `_seeds1_4_7` otherwise; "" for the default."""
    seeds = list(seeds)
    if seeds == [0, 1, 2]:
        return ""
    if len(seeds) > 1 and seeds == list(range(seeds[0], seeds[0] + len(seeds))):
        return f"_seeds{seeds[0]}-{seeds[-1]}"
    return "_seeds" + "_".join(str(s) for s in seeds)


def main_cheetah(parser, args, cache_dir: str | None = None) -> dict | None:
    """The halfcheetah mode of `main`: settings and the parts directory checked before anything
    compiles. `cache_dir`: the compilation cache's (default: in the parts directory)."""
    if args.set:
        parser.error("--set applies to the kick mode only")
    run = {**PRESETS[args.preset]}
    run.update({key: getattr(args, key) for key in run if getattr(args, key) is not None})
    default_env, episode_length, eval_episode_length = PRESET_ENV[args.preset]
    env_name = args.env or default_env
    name = f"compare_brax_ppo_{env_name}" + ("" if args.preset == "gpu" else f"_{args.preset}")
    name += "" if args.brax_resets == "first" else f"_{args.brax_resets}_resets"
    name += seeds_suffix(args.seeds)
    try:
        cfg = check_cheetah_run(run["num_envs"], run["num_minibatches"], run["env_steps"], run["eval_every"],
                                episode_length)  # fmt: skip
        if run["eval_episodes"] < 1 or not args.seeds:
            raise ValueError("--eval-episodes and --seeds must be at least one")
        if len(set(args.seeds)) != len(args.seeds):
            raise ValueError(f"--seeds must differ, got {args.seeds}")
        if args.stop_after_s is not None and args.stop_after_s < 0:
            raise ValueError(f"--stop-after-s must be at least 0, got {args.stop_after_s:g}")
        default_dir = "experiments/results" if args.preset.startswith("gpu") else "runs/compare_brax_ppo"
        out_dir = runio.check_writable(args.out_dir or default_dir)
        parts_dir = runio.check_writable(args.parts_dir or out_dir / f"{name}_parts")
        open_parts(parts_dir, run_settings(cfg, env_name, episode_length, args.seeds, run["eval_every"],
                                           args.brax_resets))  # fmt: skip
    except ValueError as err:
        parser.error(str(err))
    if args.preset in GPU_ESTIMATE:
        print(f"{args.preset} preset: {GPU_ESTIMATE[args.preset]}", flush=True)
    with compilation_cache(cache_dir or parts_dir / "jax_cache"):
        out = compare_cheetah(
            run["env_steps"],
            run["num_envs"],
            run["num_minibatches"],
            run["eval_every"],
            parts_dir,
            seeds=tuple(args.seeds),
            eval_episodes=run["eval_episodes"],
            episode_length=episode_length,
            eval_episode_length=eval_episode_length,
            env_name=env_name,
            preset=args.preset,
            stop_after_s=args.stop_after_s,
            brax_resets=args.brax_resets,
        )
    if out is None:
        return None
    path = runio.write_experiment(out_dir, name, out)
    figure = plot_cheetah(out, path.with_suffix(".png"))
    for arm in ("ours", "brax"):
        rec = out[arm]
        final = f"{rec['final_return_mean']:.1f} +- {rec['final_return_std']:.1f}"
        curve = np.round(np.mean(rec["eval_return"], axis=0), 1).tolist()
        print(f"{arm}: final return {final} {np.round(rec['final_return'], 1).tolist()}  mean curve {curve}")
    welch = "" if out["welch_t"] is None else f"  Welch t {out['welch_t']:.2f}, p {out['welch_p']:.3f}"
    print(f"within each other's seed spread: {out['within_each_others_spread']}{welch}  wall {out['wall_s']:.0f} s")
    print(f"{runio.shown(path)}\n{runio.shown(figure)}")
    return out


if __name__ == "__main__":
    main()
