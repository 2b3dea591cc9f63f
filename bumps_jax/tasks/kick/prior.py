"""The kick-prior stage: CMA-ES on the keyframe kick for the main target and for the two ends of
the reachable range, then a sweep of the blended family over strength.

    run_dir/prior/
      start_prior.json        the kick record the search started from, copied on the first call
      progress_<anchor>.csv   one row per CMA-ES generation of each anchor's search
      search_<anchor>.npz     an unfinished search's state after its last generation
      anchor_<anchor>.json    each anchor's kick and evaluation, written when its search ends
      kick_prior.json         the stage's record (OUTPUT)
      kick_prior_timing.json  its wall times
      kick_prior_asset.json   the prior record the later stages start from
      kick_sweep.png          resting distance against strength

A rerun reuses every finished anchor and resumes an unfinished search after its last generation
(its state in search_<anchor>.npz, saved after each one; Ctrl-C stops it there); it starts from
the run's own start_prior.json, whatever assets/ holds by then.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from bumps_jax import runio
from bumps_jax.algo import sharding
from bumps_jax.tasks.kick import cmaes
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model
from bumps_jax.tasks.kick import scoring as kick_scoring

OUTPUT = "kick_prior.json"
START = "start_prior.json"
ASSET = "kick_prior_asset.json"
TIMING = "kick_prior_timing.json"
SWEEP_PLOT = "kick_sweep.png"
EXTREMES = ("short", "long")  # the anchors besides the main kick, searched in this order


def inputs(cfg, run_dir) -> dict:
    """{"start": the kick record the main search starts from}: the run's own copy if it has one,
    else cfg.prior.start, else the committed prior; ValueError naming the path if it does not load."""
    own = Path(run_dir) / "prior" / START
    path = own if own.exists() else Path(cfg.prior.start or kick_model.ASSET)
    kick_model.load_record(path)
    return {"start": path}


def run(cfg, run_dir, say=print) -> dict:
    """Optimise the main kick and the extremes (reusing finished ones), sweep the family, write the
    stage's files under run_dir/prior/; returns the kick_prior.json payload."""
    t0 = time.perf_counter()
    p = cfg.prior
    stage_dir = Path(run_dir) / "prior"
    start_path = inputs(cfg, run_dir)["start"]
    own = stage_dir / START
    if not own.exists():
        runio.write_bytes(own, Path(start_path).read_bytes())
        say(f"prior: starting from {start_path} (kept as {own})")
    runio.sync("prior start copied")  # every process reads the copy the first one wrote
    x0 = np.asarray(kick_model.load_record(own)["params"], np.float32).copy()
    x0[kick_model.PARAM_NAMES.index("strength")] = p.start_strength
    env = kick_env.KickEnv(cfg.env, {"task_range": tuple(p.task_range)})
    mesh = sharding.device_mesh(impl=env.config.impl)
    found = {"main": _anchor(stage_dir, "main", p.target, x0, p.free_params, p, env, mesh, say)}
    for name in EXTREMES:  # from the main kick, every parameter free
        start = found["main"]["params"]
        found[name] = _anchor(stage_dir, name, p.extremes[name], start, kick_model.PARAM_NAMES, p, env, mesh, say)
    anchors = {n: [float(x) for x in found[n]["params"]] for n in kick_model.ANCHORS}
    stacked = np.asarray([anchors[n] for n in kick_model.ANCHORS], np.float32)
    say(f"prior: sweeping the family over {len(p.sweep_strengths)} strengths")
    rows = kick_scoring.sweep(env, stacked, p.sweep_strengths, p.target, repetitions=sweep_repetitions(p), mesh=mesh)
    reused = sum(found[n]["wall_s"] for n in found if found[n]["reused"])  # time spent in earlier calls
    payload = _payload(cfg, time.perf_counter() - t0 + reused, found, anchors, rows)
    evaluation = found["main"]["evaluation"]
    record = kick_model.make_record(anchors["main"], p, env=kick_env.resolved(cfg.env), evaluation=evaluation,
                                    generations_run=p.generations, anchors=anchors, sweep=rows,
                                    episodes=payload["episodes"])  # fmt: skip
    kick_model.save_record(record, stage_dir / ASSET)
    runio.write_json(stage_dir / TIMING, timing_record(payload))
    plot_sweep(payload, stage_dir / SWEEP_PLOT, tuple(cfg.env.task_range))
    runio.write_json(stage_dir / OUTPUT, payload)
    say(f"prior: main kick {p.target:g} m, error {evaluation['mean_error']:.2f} m, valid "
        f"{evaluation['valid_fraction']:.2f}; wrote {stage_dir / OUTPUT}")  # fmt: skip
    return payload


def sweep_repetitions(p) -> int:
    """Noisy kicks per strength of the family's sweep (`prior` config section, or its dict)."""
    return max(4, int(p["eval_repetitions"]) // 4)


def episodes(p, n_sweep: int) -> int:
    """Episodes a prior stage of config section `p` (or its dict) costs: each anchor's CMA-ES
    generations and evaluation, and a sweep of `n_sweep` strengths (anchors reused from an
    earlier call count: they were paid for once)."""
    search = int(p["generations"]) * int(p["population_size"]) * int(p["repetitions"])
    return len(kick_model.ANCHORS) * (search + int(p["eval_repetitions"])) + n_sweep * sweep_repetitions(p)


def episodes_of(record: dict) -> int | None:
    """The episodes that made a kick prior record (`kick_model.load_record`): its own count, else
    counted from its config and sweep; None if it records neither."""
    if "episodes" in record:
        return int(record["episodes"])
    config = record.get("config")
    keys = ("generations", "population_size", "repetitions", "eval_repetitions")
    if not isinstance(config, dict) or not all(k in config for k in keys) or "sweep" not in record:
        return None
    return episodes(
        {**config, "generations": record.get("generations_run", config["generations"])}, len(record["sweep"])
    )


def _anchor(stage_dir: Path, name: str, target: float, start, free, p, env, mesh, say) -> dict:
    """One anchor's kick: reused from anchor_<name>.json if its search finished, else searched
    (from generation 0), evaluated on eval_repetitions fresh episodes and saved there."""
    path = stage_dir / f"anchor_{name}.json"
    start = np.asarray(start, np.float32)
    found = runio.read_json(path, f"the {name} anchor of the kick prior") if path.exists() else None
    if found is not None and np.array_equal(np.asarray(found["start"], np.float32), start):
        say(f"prior: anchor {name} ({target:g} m) reused from the finished search in {path}")
        return {**found, "params": np.asarray(found["params"], np.float32), "reused": True}
    csv_path, state_path = stage_dir / f"progress_{name}.csv", stage_dir / f"search_{name}.npz"
    if found is not None:
        say(f"prior: anchor {name} ({target:g} m) was searched from another start; it restarts from generation 0")
    t0 = time.perf_counter()
    out = cmaes.optimise(env, start, target, tuple(free), p, csv_path=csv_path, mesh=mesh, say=say,
                         label=f"prior {name} {target:g} m", resume_path=state_path)  # fmt: skip
    search_s = time.perf_counter() - t0
    evaluation = kick_scoring.evaluate_kick(env, out["params"], target, p.fitness, p.eval_repetitions, mesh=mesh)
    found = {
        "name": name,
        "target_m": float(target),
        "start": [float(x) for x in start],
        "free_params": list(free),
        "params": [float(x) for x in np.asarray(out["params"])],
        "best_cost": out["best_cost"],
        "evaluation": evaluation,
        "search_wall_s": search_s,
        "wall_s": time.perf_counter() - t0,
    }
    runio.write_json(path, found)
    runio.remove(state_path)  # the finished search's state: its anchor file holds what is read
    say(f"prior: anchor {name} ({target:g} m) done: error {evaluation['mean_error']:.2f} m, valid "
        f"{evaluation['valid_fraction']:.2f} ({path})")  # fmt: skip
    return {**found, "params": np.asarray(found["params"], np.float32), "reused": False}


def _payload(cfg, wall_s: float, found: dict, anchors: dict, rows: list) -> dict:
    """kick_prior.json: provenance, the main kick's evaluation, the extremes, anchors and sweep."""
    p, evaluation = cfg.prior, found["main"]["evaluation"]
    extremes = {
        name: {
            "target_m": float(p.extremes[name]),
            **{f"{k}_m": found[name]["evaluation"][k] for k in ("mean_error", "mean_distance")},
            **{k: found[name]["evaluation"][k] for k in ("valid_fraction", "fallen_fraction")},
        }
        for name in EXTREMES
    }
    return {
        **runio.provenance(cfg.preset, wall_s, kick_env.resolved(cfg.env)),
        "target_m": float(p.target),
        "n_reps": int(p.eval_repetitions),
        "mean_error_m": evaluation["mean_error"],
        "std_error_m": evaluation["std_error"],
        "valid_fraction": evaluation["valid_fraction"],
        "fallen_fraction": evaluation["fallen_fraction"],
        "struck_fraction": evaluation["struck_fraction"],
        "optimise_wall_s": found["main"]["search_wall_s"],
        "anchor_wall_s": {n: found[n]["wall_s"] for n in kick_model.ANCHORS},
        "reused_anchors": [n for n in kick_model.ANCHORS if found[n]["reused"]],
        "generations": int(p.generations),
        "population_size": int(p.population_size),
        "repetitions_per_candidate": int(p.repetitions),
        "sweep": rows,
        "episodes": episodes(p, len(rows)),  # what the stage cost: anchors' searches and evaluations, sweep
        "extremes": extremes,
        "anchors": anchors,
    }


def timing_record(payload: dict) -> dict:
    """The benchmark view of a kick-prior run: its provenance and wall times, nothing else."""
    keys = ("device", "n_devices", "versions", "date", "command", "preset", "wall_s", "env", "optimise_wall_s",
            "anchor_wall_s", "generations", "population_size", "repetitions_per_candidate")  # fmt: skip
    episodes = payload["generations"] * payload["population_size"] * payload["repetitions_per_candidate"]
    return {
        **{k: payload[k] for k in keys},
        "episodes_per_optimisation": episodes,
        "episodes_per_s": episodes / payload["optimise_wall_s"],
    }


def plot_sweep(payload: dict, path, task_range) -> None:
    """Resting distance vs strength along the short -> main -> long family, the task range shaded."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    rows = payload["sweep"]
    strengths, distances = [r["strength"] for r in rows], [r["distance_m"] for r in rows]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.errorbar(strengths, distances, yerr=[r["distance_std_m"] for r in rows], marker="o", capsize=3,
                label="mean +- std over noisy kicks")  # fmt: skip
    for r in rows:
        ax.annotate(f"{r['valid_fraction']:.2f}", (r["strength"], r["distance_m"]), textcoords="offset points",
                    xytext=(4, -12), fontsize=7)  # fmt: skip
    lo, hi = task_range
    ax.axhspan(lo, hi, color="green", alpha=0.1, label=f"task range {lo:g}-{hi:g} m")
    ax.set_xlabel("strength (0 = short kick, 0.5 = main kick, 1 = long kick)")
    ax.set_ylabel("resting distance (m)")
    ax.set_title(f"Reachable range, valid fraction annotated ({payload['device']})", fontsize=9)
    ax.legend(fontsize=8)
    runio.save_figure(fig, path)
