"""Does splitting the kick's CMA-ES tuning over processes change what it computes?

The kick task tunes its starting kicks by CMA-ES (`cmaes.tune_for_tasks`): K restarts x T targets
searches, each generation one program that `sharding.over_batch` splits over the processes. This
runs one small tuning three ways, from the same starts and seeds:

- `split`: N processes of JAX's multi-process runtime on this host (`launch.process_env`), each
  computing its 1/N of every generation's searches and of the fresh scoring, the rows gathered;
- `part_calls`: one process, each generation (and the fresh scoring) computed as N calls of its
  N parts, joined: what the N processes compute, computed in one process;
- `whole_run`: one process, every generation one call of the whole batch (the plain tuning).

`part_calls` also computes each of its generations, from the same inputs, as one call of the whole
batch: how far one generation moves with the batch's shape alone, before CMA-ES carries it on;
and for generation 1 every candidate's episodes (targets x restarts x population x repetitions)
at the whole batch and in N parts, so that single episodes whose contact physics magnify XLA's
per-shape rounding are counted.

Writes one record: per generation the max abs/rel differences of the searches' stats (best and
mean cost, valid fraction) for split vs part_calls (0 when the split computes exactly what its
parts compute) and split vs whole_run; generation 1's per-episode cost differences (median, count
over 1e-3, max); the final CMA-ES means', fresh-scoring costs' and chosen kicks' differences; the
fresh costs themselves; the settings and provenance.

    JAX_PLATFORMS=cpu python experiments/tuning_split.py --out experiments/results/tuning_split_cpu.json
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

EPISODE_TOLERANCE = 1e-3  # an episode's cost "differs" above this


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="tiny", help="the config preset")
    parser.add_argument("--impl", default="jax", choices=("jax", "warp"), help="env.impl: the physics")
    parser.add_argument("--targets", type=float, nargs="+", default=[8.0, 10.0, 13.0, 16.0], help="tasks (m)")
    parser.add_argument("--generations", type=int, default=3, help="CMA-ES generations")
    parser.add_argument("--population", type=int, default=4, help="experts.tune.population_size")
    parser.add_argument("--repetitions", type=int, default=2, help="experts.tune.repetitions")
    parser.add_argument("--eval-repetitions", type=int, default=4, help="experts.tune.eval_repetitions")
    parser.add_argument("--restarts", type=int, default=2, help="experts.tune.restarts")
    parser.add_argument("--leash", type=float, default=1.0, help="experts.tune.neighbour_leash")
    parser.add_argument("--sigma", type=float, default=0.5, help="experts.tune.sigma_init")
    parser.add_argument("--processes", type=int, default=2, help="N: processes of the split arm")
    parser.add_argument("--limit-s", type=float, default=1800.0, help="seconds the split arm's processes may take")
    parser.add_argument("--out", type=Path, required=True, help="the record to write (.json)")
    parser.add_argument("--worker", type=Path, help=argparse.SUPPRESS)  # a split-arm process's folder
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # what each split-arm process is given
    if args.processes < 2:
        parser.error(f"--processes must be at least 2, got {args.processes}")
    n = len(args.targets)
    if n % args.processes or (n * args.restarts) % args.processes:
        parser.error(f"{n} targets ({n * args.restarts} searches) do not split evenly over {args.processes} processes")
    return args


def make_config(args):
    from bumps_jax import config  # noqa: PLC0415

    return config.make_config(args.preset, {
        "env.impl": args.impl,
        "experts.tasks": tuple(args.targets),
        "experts.tune.generations": args.generations,
        "experts.tune.population_size": args.population,
        "experts.tune.repetitions": args.repetitions,
        "experts.tune.eval_repetitions": args.eval_repetitions,
        "experts.tune.restarts": args.restarts,
        "experts.tune.neighbour_leash": args.leash,
        "experts.tune.sigma_init": args.sigma,
    })  # fmt: skip


def run_tuning(cfg, parts: int = 1, say=print, check_whole: bool = True, prior: dict | None = None) -> dict:
    """One tuning (`cmaes.tune_for_tasks`) with what each generation and the fresh scoring computed,
    its starts from `prior` (its anchors and sweep; default the shipped prior).

    parts > 1: every generation and the fresh scoring computed as `parts` calls of their parts,
    joined (what `parts` processes compute); with `check_whole`, each generation also computed as
    one call of the whole batch from the same inputs (`one_generation`), and generation 1's
    per-episode costs at the whole batch and in parts (`episodes`).
    """
    import jax  # noqa: PLC0415
    import jax.numpy as jnp  # noqa: PLC0415

    from bumps_jax.algo import sharding  # noqa: PLC0415
    from bumps_jax.tasks.kick import cmaes, starting_kicks  # noqa: PLC0415
    from bumps_jax.tasks.kick import keyframes as kick_model  # noqa: PLC0415
    from bumps_jax.tasks.kick import scoring as kick_scoring  # noqa: PLC0415

    tune = cfg.experts.tune
    targets = np.asarray(cfg.experts.tasks, np.float32)
    env = starting_kicks.tune_env(cfg, int(tune.restarts))
    record = kick_model.load_record(kick_model.ASSET) if prior is None else prior
    starts, _, _ = starting_kicks.prior_kicks(cfg, record, targets, env, say=lambda *a, **k: None)
    fitness_json = kick_scoring.fitness_json_of(cfg.prior.fitness)
    out = {"generations": [], "final_mean": [], "best_cost": [], "fresh_costs": [], "one_generation": [],
           "episodes": None}  # fmt: skip
    real_search, real_run, real_score = cmaes.kick_search, cmaes.run_search, kick_scoring.cost_program

    def host(tree):
        return jax.tree.map(lambda x: np.asarray(x).tolist(), tree)

    def cut(tree, i, k):
        return jax.tree.map(lambda x: x[i * k : (i + 1) * k], tree)

    def join(pieces):
        return jax.tree.map(lambda *xs: jnp.concatenate(xs), *pieces)

    def in_parts(fn, batched, *whole):
        """fn over `batched` (rows on the leading axis) as `parts` calls of equal parts, the rows
        padded to a multiple of `parts` as processes pad them (`sharding.pad`), joined and unpadded;
        `whole`: arguments every call takes whole."""
        n = len(jax.tree.leaves(batched)[0])
        k = -(-n // parts)
        padded = sharding.pad(batched, k * parts)
        return sharding.unpad(join([fn(*cut(padded, i, k), *whole) for i in range(parts)]), n)

    def gen1_episodes(search, args):
        """Generation 1's candidates, each one's R episodes' costs at the whole batch and in parts."""
        carry, key, x0, target, scale = args[:5]
        weights = kick_scoring.weights(fitness_json)
        per_search = jax.jit(jax.vmap(kick_scoring.kick_cost(env, weights)))
        ks = jax.vmap(lambda k: jax.random.split(k, 3))(key)
        z = jax.vmap(lambda k, st: search.es.ask(k, st, search.es_params)[0])(ks[:, 0], carry.es)
        P, R = z.shape[1], int(tune.repetitions)
        keys = jax.vmap(lambda k: jnp.broadcast_to(jax.random.split(k, R), (P, R) + k.shape))(ks[:, 1])
        params = kick_model.clip_params(x0[:, None] + scale[:, None] * z)
        zero = jnp.zeros(len(target))

        def episodes(*batch):  # (params, keys, targets, extra) -> each episode's cost and distance
            metrics, tgt = per_search(*batch)[1], batch[2]
            return {"cost": kick_model.fitness(metrics, tgt[:, None, None], weights), "distance": metrics["distance"]}

        batch = (params, keys, target, zero)
        return {"whole": host(episodes(*batch)), "parts": host(in_parts(episodes, batch))}

    def kick_search(*a, **kw):
        search = real_search(*a, **kw)
        if parts == 1:
            return search

        def step(*args):
            carry, stats = in_parts(lambda *part: search.step(*sharding.place(part, search.mesh)), args)
            if not check_whole:
                return carry, stats
            whole_carry, whole_stats = search.step(*args)
            leaves = zip(jax.tree.leaves(carry), jax.tree.leaves(whole_carry), strict=True)
            out["one_generation"].append({
                "whole_call": host(whole_stats._asdict()),
                "carry_max_abs": max(float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64))))
                                     for x, y in leaves),
            })  # fmt: skip
            if out["episodes"] is None:
                out["episodes"] = gen1_episodes(search, args)
            return carry, stats

        return search._replace(step=step)

    def run_search(*a, **kw):
        kw["on_generation"] = lambda g, s: out["generations"].append(host(s._asdict()))
        result = real_run(*a, **kw)
        out["final_mean"].append(host(result.mean))
        out["best_cost"].append(host(result.best_cost))
        return result

    def cost_program(*a):
        program = real_score(*a)

        def score(params, keys, tgt):
            if parts == 1:
                costs = program(params, keys, tgt)
            else:
                costs = in_parts(lambda p, t, k: program(p, k, t), (params, tgt), keys)
            out["fresh_costs"].append(host(costs))
            return costs

        return score

    patches = ((cmaes, "kick_search", kick_search), (cmaes, "run_search", run_search),
               (kick_scoring, "cost_program", cost_program))  # fmt: skip
    t0 = time.perf_counter()
    with contextlib.ExitStack() as stack:
        for module, name, fn in patches:
            stack.enter_context(_patched(module, name, fn))
        tuned = cmaes.tune_for_tasks(env, targets, starts, tune, int(tune.generations), float(tune.sigma_init),
                                     fitness=cfg.prior.fitness, say=say)  # fmt: skip
    out.update(
        seconds=time.perf_counter() - t0,
        processes=jax.process_count(),
        devices_per_process=len(jax.local_devices()),
        parts=parts,
        starts=host(starts),
        **{k: host(tuned[k]) for k in ("params", "start_cost", "tuned_cost", "restart_costs", "runs_kept")},
    )
    return out


@contextlib.contextmanager
def _patched(module, name, fn):
    real = getattr(module, name)
    setattr(module, name, fn)
    try:
        yield
    finally:
        setattr(module, name, real)


# -- comparing ----------------------------------------------------------------------------------


def differences(a, b) -> dict:
    """How far `b` lies from `a` (the reference): max abs and max rel difference (|b - a| / |a|,
    0 where both are 0, null where only a is 0), and whether they are identical bit for bit."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"cannot compare arrays of shapes {a.shape} and {b.shape}")
    diff = np.abs(a - b)
    rel = np.divide(diff, np.abs(a), out=np.where(diff > 0, np.inf, 0.0), where=np.abs(a) > 0)
    max_rel = float(rel.max()) if rel.size else 0.0
    return {
        "max_abs": float(diff.max()) if diff.size else 0.0,
        "max_rel": max_rel if np.isfinite(max_rel) else None,
        "identical": bool(np.array_equal(a, b)),
    }


def episode_differences(whole, parts, tolerance: float = EPISODE_TOLERANCE) -> dict:
    """Per-episode |parts - whole|: how many episodes, the median and max difference, how many
    differ by more than `tolerance` and how many differ at all."""
    diff = np.abs(np.asarray(parts, np.float64) - np.asarray(whole, np.float64)).reshape(-1)
    return {
        "episodes": int(diff.size),
        "median_abs": float(np.median(diff)),
        "max_abs": float(diff.max()),
        "over_tolerance": int(np.sum(diff > tolerance)),
        "tolerance": tolerance,
        "differing": int(np.sum(diff > 0)),
    }


STATS = ("best", "mean", "valid")


def compare(split: dict, part_calls: dict, whole_run: dict) -> dict:
    """The record's comparisons of the three arms' payloads (`run_tuning`)."""
    if not (np.array_equal(split["starts"], part_calls["starts"]) and np.array_equal(split["starts"],
                                                                                  whole_run["starts"])):  # fmt: skip
        raise ValueError("the arms started from different kicks")
    per_generation = []
    for g, (s, p, w) in enumerate(zip(split["generations"], part_calls["generations"], whole_run["generations"],
                                      strict=True)):  # fmt: skip
        row = {
            "generation": g + 1,
            "split_vs_part_calls": {k: differences(p[k], s[k]) for k in STATS},
            "split_vs_whole_run": {k: differences(w[k], s[k]) for k in STATS},
        }
        if part_calls["one_generation"]:
            one = part_calls["one_generation"][g]
            row["one_generation_whole_call_vs_part_calls"] = {
                **{k: differences(one["whole_call"][k], p[k]) for k in STATS},
                "carry_max_abs": one["carry_max_abs"],
            }
        per_generation.append(row)

    def pair(key):
        return {"split_vs_part_calls": differences(part_calls[key], split[key]),
                "split_vs_whole_run": differences(whole_run[key], split[key])}  # fmt: skip

    record = {
        "per_generation": per_generation,
        "final_mean": pair("final_mean"),
        "best_cost": pair("best_cost"),
        "fresh_costs": {
            **pair("fresh_costs"),
            "split": split["fresh_costs"],
            "part_calls": part_calls["fresh_costs"],
            "whole_run": whole_run["fresh_costs"],
        },  # fmt: skip
        "chosen_kicks": pair("params"),
        "runs_kept": {
            name: arm["runs_kept"]
            for name, arm in (("split", split), ("part_calls", part_calls), ("whole_run", whole_run))
        },  # fmt: skip
        "tuned_cost": {name: arm["tuned_cost"] for name, arm in (("split", split), ("whole_run", whole_run))},
        "start_cost": split["start_cost"],
    }
    if part_calls["episodes"] is not None:
        ep = part_calls["episodes"]
        record["gen1_episodes"] = {
            "cost": episode_differences(ep["whole"]["cost"], ep["parts"]["cost"]),
            "distance_m": episode_differences(ep["whole"]["distance"], ep["parts"]["distance"]),
        }
    same = [row["split_vs_part_calls"][k]["identical"] for row in per_generation for k in STATS]
    same += [record[k]["split_vs_part_calls"]["identical"] for k in ("final_mean", "best_cost", "fresh_costs",
                                                                      "chosen_kicks")]  # fmt: skip
    record["split_equals_part_calls"] = all(same)
    return record


# -- running ------------------------------------------------------------------------------------


def worker(args) -> None:
    """One process of the split arm: join the others, tune, the first process writes the payload."""
    import jax  # noqa: PLC0415

    from bumps_jax.algo import sharding  # noqa: PLC0415

    sharding.initialize_distributed()
    payload = run_tuning(make_config(args), say=lambda m: print(f"[process {jax.process_index()}] {m}", flush=True))
    if sharding.is_writer():
        (args.worker / "split.json").write_text(json.dumps(payload))


def run_split(args) -> dict:
    """The split arm: `args.processes` processes of this script (`--worker`) on this host."""
    from bumps_jax import launch  # noqa: PLC0415

    with tempfile.TemporaryDirectory(prefix="tuning-split-") as tmp:
        port, procs, logs = launch.free_port(), [], []
        own = [*args.argv, "--worker", tmp]
        for i in range(args.processes):
            log = open(Path(tmp) / f"log.{i}", "w")  # noqa: SIM115 (closed with its process)
            # each its own hash seed: nothing the processes agree on may follow Python's hash order
            env = {**launch.process_env(i, args.processes, port, launch.visible_gpus()), "PYTHONHASHSEED": str(1 + i)}
            procs.append(
                subprocess.Popen([sys.executable, __file__, *own], env=env, stdout=log, stderr=subprocess.STDOUT)
            )
            logs.append(log)
        print(f"[tuning_split] split arm: {args.processes} processes", flush=True)
        deadline, failed = time.monotonic() + args.limit_s, None
        while any(p.poll() is None for p in procs):
            failed = failed or next((i for i, p in enumerate(procs) if p.poll() not in (None, 0)), None)
            if failed is not None or time.monotonic() > deadline:
                time.sleep(5.0)  # the others' last words, then stop them
                for p in procs:
                    if p.poll() is None:
                        p.kill()
                        p.wait()
                break
            time.sleep(0.5)
        for log in logs:
            log.close()
        result = Path(tmp) / "split.json"
        if any(p.returncode for p in procs) or not result.exists():
            i = failed if failed is not None else 0
            lines = (Path(tmp) / f"log.{i}").read_text().strip().splitlines()
            raise SystemExit(f"error: split arm, process {i} ended ({procs[i].returncode}): "
                             f"{lines[-1] if lines else '(no output)'}")  # fmt: skip
        return json.loads(result.read_text())


def main(argv=None) -> None:
    args = parse_args(argv)
    if args.worker is not None:
        return worker(args)
    from bumps_jax import config, runio  # noqa: PLC0415

    try:
        cfg = make_config(args)
        runio.check_writable(args.out.parent, "the record's folder")
    except ValueError as err:
        raise SystemExit(f"error: {err}") from None
    start = time.perf_counter()
    split = run_split(args)
    print(f"[tuning_split] split arm done in {split['seconds']:.0f} s; one process, the parts' calls", flush=True)
    part_calls = run_tuning(cfg, parts=args.processes, say=lambda m: print(f"[part_calls] {m}", flush=True))
    print("[tuning_split] one process, the whole batch", flush=True)
    whole_run = run_tuning(cfg, parts=1, say=lambda m: print(f"[whole_run] {m}", flush=True))
    record = {
        "task": cfg.task,
        "settings": {
            k: getattr(args, k)
            for k in (
                "targets",
                "generations",
                "population",
                "repetitions",
                "eval_repetitions",
                "restarts",
                "leash",
                "sigma",
            )
        },  # fmt: skip
        "processes": args.processes,
        "arms": {
            name: {
                "processes": arm["processes"],
                "devices_per_process": arm["devices_per_process"],
                "calls_per_generation": arm["parts"] if arm["processes"] == 1 else 1,
                "seconds": arm["seconds"],
            }
            for name, arm in (("split", split), ("part_calls", part_calls), ("whole_run", whole_run))
        },  # fmt: skip
        **compare(split, part_calls, whole_run),
    }
    record.update(runio.provenance(cfg.preset, time.perf_counter() - start, config.resolved_env(cfg)),
                  date=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"))  # fmt: skip
    # the split arm's processes, one device each (the arms say how each arm ran)
    record.update(n_processes=args.processes, n_devices=args.processes * split["devices_per_process"])
    runio.write_json(args.out, runio.json_safe(record))
    for row in record["per_generation"]:
        print(f"gen {row['generation']}: split vs part calls max abs "
              f"{max(d['max_abs'] for d in row['split_vs_part_calls'].values()):.3g}; split vs whole run "
              f"{max(d['max_abs'] for d in row['split_vs_whole_run'].values()):.3g}")  # fmt: skip
    if "gen1_episodes" in record:
        e = record["gen1_episodes"]["cost"]
        print(f"gen 1 episodes: {e['over_tolerance']} of {e['episodes']} differ by > {e['tolerance']:g} "
              f"(median {e['median_abs']:.2g}, max {e['max_abs']:.3g})")  # fmt: skip
    print(f"final means: split vs whole run max abs {record['final_mean']['split_vs_whole_run']['max_abs']:.3g}; "
          f"split equals part calls: {record['split_equals_part_calls']}; wrote {args.out}")  # fmt: skip


if __name__ == "__main__":
    main()
