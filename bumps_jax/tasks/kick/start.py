"""How the kick's experts start (its `protocol.ExpertStart`): each clones its own keyframe kick.

The kicks come from the keyframe prior (the prior stage's record, else the committed asset),
chosen and tuned by CMA-ES for every task at once (`starting_kicks`); each expert's Gaussian
policy is fitted to its kick's joint targets (`bc.clone_policy`) before PPO. The multi-task
baseline starts from the prior's main kick, cloned at every meta-training context.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bumps_jax import runio
from bumps_jax.algo import bc
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes, starting_kicks
from bumps_jax.tasks.kick import prior as prior_stage

PRIOR = prior_stage.ASSET  # the record a prior stage writes, and the copy an experts run keeps
TUNING = "tuning"  # the starting kicks' starts and finished tuning runs, until the record is written
STARTING_KICKS = "starting_kicks.json"


def prior_path(run_dir: Path) -> Path:
    """The kick prior record this run's experts start from: the run's own prior stage's record,
    else the copy the experts stage keeps of the one it started from, else the committed asset."""
    for path in (run_dir / "prior" / PRIOR, run_dir / "experts" / PRIOR):
        if path.is_file():
            return path
    return keyframes.ASSET


def kick_dataset(env: kick_env.KickEnv, target, kick_params) -> tuple[jax.Array, jax.Array]:
    """A keyframe kick (14,) as (obs (T, 2), actions (T, 22)) for an expert of `target` m.

    obs[k] is what the env shows before step k: (k / T, normalised target); actions[k] the
    kick's joint targets for step k.
    """
    phase = jnp.arange(env.n_steps, dtype=jnp.float32) / env.n_steps
    context = jnp.full_like(phase, env.normalise_context(jnp.asarray(target, jnp.float32)))
    actions = keyframes.keyframes_to_actions(kick_params, env.n_steps, env.dt)
    return jnp.stack([phase, context], axis=-1), actions


class KeyframeStart:
    """The kick's experts start from their own tuned keyframe kicks, cloned."""

    size = keyframes.N_PARAMS  # a keyframe kick's parameters

    def inputs(self, cfg, run_dir: Path) -> dict:
        path = prior_path(Path(run_dir))
        keyframes.load_record(path, env_cfg=cfg.env)  # exists, parses, and was made under this env config
        return {"prior": path}

    def starts(self, cfg, run_dir: Path, stage_dir: Path, say=print) -> np.ndarray:
        """Each task's starting kick (E, 14), with starting_kicks.json beside it."""
        path = prior_path(Path(run_dir))
        record = keyframes.load_record(path, env_cfg=cfg.env)
        if path == keyframes.ASSET:  # keep the prior this run started from: a rerun must not read a newer asset
            runio.write_text(stage_dir / PRIOR, path.read_text())
        kicks, info = starting_kicks.starting_kicks(cfg, record, say, keep_dir=stage_dir / TUNING)
        runio.write_json(stage_dir / STARTING_KICKS, {**info, "prior": runio.shown(path)})
        return kicks

    def make_init(self, cfg, env, trainer):
        """A pure fn (rng, target, kick (14,)) -> (TrainState after cloning that kick, BC losses (steps,))."""
        e = cfg.experts

        def init(rng, target, kick):
            rng_state, rng_policy = jax.random.split(rng)
            policy = trainer.networks.policy_network.init(rng_policy)
            obs, actions = kick_dataset(env, target, kick)
            policy, losses = bc.clone_policy(trainer.networks, policy, obs, actions, e.bc.steps, e.bc.learning_rate)
            return trainer.init(rng_state, policy), losses

        return init

    def describe(self, cfg, run_dir: Path, stage_dir: Path, env, record: dict) -> dict:
        """The starting kicks scored as the experts are, their smoothness and tuning runs, and the
        env steps one expert cost (its share of the prior's and the tuning's episodes, its PPO)."""
        e = cfg.experts
        kicks = runio.read_json(stage_dir / STARTING_KICKS)
        out = {}
        out["starting_kicks"], out["starting_kicks_midpoints"] = starting_kicks.evaluate_starting_kicks(
            cfg, env, kicks["params"]
        )
        out["starting_kicks_smoothness"] = starting_kicks.smoothness(kicks["params"], e.tasks)
        if len(kicks.get("restart_costs", [])) > 1:  # `tune.restarts`: every run's fresh cost, and what was kept
            runs = {"kept": kicks["restart"], "fresh_costs": kicks["restart_costs"]}
            if "run_seconds" in kicks:  # each run's time, also of runs a resumed tuning read back
                runs["run_seconds"] = kicks["run_seconds"]
            if kicks.get("keep") in ("task", "chain"):  # each task's run (0: its start), the polish's tasks improved
                runs["runs_kept"] = kicks["runs_kept"]
                runs["keep"] = kicks["keep"]
                if "polish" in kicks:
                    runs["polish_improved"] = int(sum(kicks["polish"]["improved"]))
            out["starting_kicks_tuning_runs"] = runs
        n = len(e.tasks)
        prior_episodes = prior_stage.episodes_of(keyframes.load_record(prior_path(Path(run_dir))))
        out["env_steps_breakdown"] = {
            "prior": None if prior_episodes is None else int(prior_episodes * env.n_steps / n),
            "tuning": int(kicks.get("episodes", 0) * env.n_steps / n),
            "ppo": int(record["env_steps"]),
        }
        return out

    def scratch(self) -> tuple[str, ...]:
        return (TUNING,)

    def baseline_start(self, cfg, env, trainer, run_dir: Path, say=print) -> tuple:
        """The prior's main kick cloned at every meta-training context: (policy params, BC losses)."""
        b = cfg.baseline
        record = keyframes.load_record(prior_path(Path(run_dir)), env_cfg=cfg.env)
        say(f"cloning the main kick into the {len(b.ppo.policy_hidden)}-layer policy ({b.bc_steps} steps)", flush=True)
        return clone_start(cfg, env, trainer, jnp.asarray(record["params"]))


def clone_start(cfg, env: kick_env.KickEnv, trainer, kick) -> tuple:
    """The policy every baseline seed starts from: `kick` cloned at every meta-training context.
    (params, BC losses)."""
    b = cfg.baseline
    pairs = [kick_dataset(env, t, kick) for t in kick_env.meta_train_tasks()]
    obs, actions = (jnp.concatenate(parts) for parts in zip(*pairs, strict=True))
    policy0 = trainer.networks.policy_network.init(jax.random.key(0))
    clone = jax.jit(lambda p: bc.clone_policy(trainer.networks, p, obs, actions, b.bc_steps, b.bc_learning_rate))
    return clone(policy0)
