"""Are a run's experts one family? Their kicks replayed between their tasks.

A meta-policy asked for a context between two training tasks answers, at best, something like
the two neighbouring experts' joint trajectories mixed in proportion. This replays exactly that
mix, without any net: each expert's noise-free joint trajectory (the meta stage's dataset.npz),
interpolated linearly in the target between the two experts around it ("interpolated"), and the
nearer expert's trajectory alone ("nearest"). Where the mix misses and the nearest does not,
neighbouring experts are different kicks and no net trained on them can be trusted between them.
With `--kicks` (a run's starting_kicks.json) the same is done with the experts' starting kicks
before behaviour cloning and PPO, so a miss can be placed before or after PPO. Scored on the
development targets and noise (the config's `dev` section), never on the meta-test or held-out
ones. Writes <out-dir>/interpolation[_<name>]_<cpu|gpu>.json.

    python experiments/interpolation.py --run-dir runs/paper --repetitions 16
    python experiments/interpolation.py --run-dir runs/paper --kicks runs/paper/experts/starting_kicks.json
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from bumps_jax import config, runio
from bumps_jax.algo import rollout
from bumps_jax.pipeline.stages import meta as meta_stage
from bumps_jax.report import publish
from bumps_jax.tasks import registry as tasks
from bumps_jax.tasks.kick import keyframes as kick_model

RULES = ("interpolated", "nearest")


def expert_tables(data, n_steps: int) -> tuple[np.ndarray, np.ndarray]:
    """(normalised contexts (E,) ascending, joint trajectories (E, T, 22)) of a meta dataset
    (E experts x K repetitions x T = `n_steps` steps; the first repetition of each expert)."""
    tasks_ = np.unique(data.task)
    n_per_expert = len(data.task) // len(tasks_)
    obs = data.obs.reshape(len(tasks_), n_per_expert, -1)[:, :n_steps]
    actions = data.actions.reshape(len(tasks_), n_per_expert, -1)[:, :n_steps]
    order = np.argsort(obs[:, 0, 1])
    return obs[order, 0, 1], actions[order]


def kick_tables(path, env) -> tuple[np.ndarray, np.ndarray]:
    """`expert_tables` of the starting kicks in a run's starting_kicks.json, played in `env`."""
    record = runio.read_json(path, "starting kicks of an experts run")
    targets = np.asarray(record["tasks_m"], np.float32)
    table = kick_model.action_tables(np.asarray(record["params"], np.float32), env.n_steps, env.dt)
    order = np.argsort(targets)
    return np.asarray(env.normalise_context(targets))[order], np.asarray(table)[order]


def mixed_policy(params, obs):
    """The interpolated (params["nearest"] 0) or nearest-expert (1) open-loop policy over the
    experts' trajectories params["table"] (E, T, 22) at contexts params["contexts"] (E,)."""
    contexts, table = params["contexts"], params["table"]
    i = jnp.clip(jnp.searchsorted(contexts, obs[1]) - 1, 0, contexts.shape[0] - 2)
    w = jnp.clip((obs[1] - contexts[i]) / (contexts[i + 1] - contexts[i]), 0.0, 1.0)
    w = jnp.where(params["nearest"] > 0, jnp.round(w), w)
    return (1 - w) * rollout.table_policy(table[i], obs) + w * rollout.table_policy(table[i + 1], obs)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-dir", default="runs/paper", help="a run whose meta stage recorded its dataset")
    parser.add_argument("--repetitions", type=int, default=16, help="noisy kicks per target and rule")
    parser.add_argument("--kicks", default=None, help="a run's starting_kicks.json: its kicks instead of the experts")
    parser.add_argument("--name", default="", help="a suffix of the record's name (e.g. the run's)")
    parser.add_argument("--out-dir", default="experiments/results")
    args = parser.parse_args(argv)
    dataset = Path(args.run_dir) / "meta" / "dataset.npz"
    if args.repetitions < 1:
        parser.error(f"--repetitions must be at least 1, got {args.repetitions}")
    if args.kicks is None and not dataset.exists():
        parser.error(f"{dataset} does not exist: run the meta stage of {args.run_dir} first")
    if args.kicks is not None and not Path(args.kicks).exists():
        parser.error(f"--kicks {args.kicks} does not exist")
    try:
        cfg = publish.run_config(args.run_dir, config.make_config("paper"))
    except ValueError as err:
        parser.error(str(err))

    start = time.perf_counter()
    env = tasks.make_env(cfg.task, cfg.env)
    if args.kicks is None:
        contexts, table = expert_tables(meta_stage.load_dataset(dataset), env.n_steps)
    else:
        contexts, table = kick_tables(args.kicks, env)
    targets = np.asarray(cfg.dev.targets, np.float32)
    params = {
        "contexts": jnp.stack([jnp.asarray(contexts)] * 2),
        "table": jnp.stack([jnp.asarray(table)] * 2),
        "nearest": jnp.array([0, 1]),
    }
    keys = rollout.repetition_keys(int(cfg.dev.seed), len(targets), args.repetitions)
    metrics = rollout.grid_fn(env, mixed_policy)(params, targets, targets, keys)
    error = np.asarray(metrics["final_error"]).mean(-1)  # (2, targets)
    rows = {}
    for rule, e in zip(RULES, error, strict=True):
        rows[rule] = {
            "error_mean_m": float(e.mean()),
            "targets_above_2m": int((e > 2.0).sum()),
            "error_max_m": float(e.max()),
            "per_target_error_m": e.tolist(),
        }
        print(f"{rule:12s} error {e.mean():.2f} m, {rows[rule]['targets_above_2m']} targets above 2 m, "
              f"worst {e.max():.2f} m at {targets[e.argmax()]:.2f} m")  # fmt: skip
    payload = {
        "run": runio.shown(args.run_dir),
        "replayed": "experts" if args.kicks is None else f"starting kicks ({runio.shown(args.kicks)})",
        "experts_tasks_m": [float(t) for t in cfg.experts.tasks],
        "targets_m": targets.tolist(),
        "seed": int(cfg.dev.seed),
        "repetitions": args.repetitions,
        "rows": rows,
    }
    name = "interpolation" + (f"_{args.name}" if args.name else "")
    print(runio.write_experiment(args.out_dir, name, payload, cfg, time.perf_counter() - start))


if __name__ == "__main__":
    main()
