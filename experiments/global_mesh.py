"""Past one GPU, two ways: per-process programs (the pipeline's) or one global mesh.

N processes joined by JAX's multi-process runtime, one device each, roll out the same batch of
episodes (a fixed random linear policy on the task's test contexts, Warp physics by default)
two ways, each timed after a compiling call:

- `per_process`: the pipeline's `sharding.over_batch`: every process runs its own program on its
  rows of the batch, and the rows are gathered to every process;
- `global_mesh`: one program over a mesh of every process's device (`shard_map`), the env's
  arrays (its MJX model, Warp's blank episode) passed to it as replicated global arrays instead
  of being closed over, the batch placed as one global array, the output gathered the same way.

Writes one record: each way's episodes per second (every process's work over the slowest
process's time), whether both gave the same final metrics, or the line that stopped a way.

    python experiments/global_mesh.py --processes 4 --out runs/global_mesh_4gpu.json
    JAX_PLATFORMS=cpu python experiments/global_mesh.py --processes 2 --preset tiny --episodes 16 --out runs/gm.json
"""

from __future__ import annotations

import argparse
import copy
import datetime
import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

WAYS = ("per_process", "global_mesh")


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="cheetah_vel", help="the task whose env steps the episodes")
    parser.add_argument("--preset", default="paper", help="the config preset (its env)")
    parser.add_argument("--processes", type=int, default=2, help="N: processes, one device (GPU) each")
    parser.add_argument("--episodes", type=int, default=4096, help="episodes per process in one call")
    parser.add_argument("--out", type=Path, required=True, help="the record to write (.json)")
    parser.add_argument("--limit-s", type=float, default=900.0,
                        help="seconds the processes may take; then stopped, the ways not done named")  # fmt: skip
    parser.add_argument("--worker", type=Path, help=argparse.SUPPRESS)  # a measuring process's folder
    args = parser.parse_args(argv)
    if args.processes < 2:
        parser.error(f"--processes must be at least 2 (one process has no mesh of processes), got {args.processes}")
    if not args.limit_s > 0:
        parser.error(f"--limit-s must be > 0, got {args.limit_s}")
    if args.episodes < 1:
        parser.error(f"--episodes must be a positive integer, got {args.episodes}")
    return args


def env_arrays(env) -> dict:
    """The env's attributes that hold device arrays (its MJX model, Warp's blank episode): what a
    program over a global mesh must take as arguments rather than close over."""
    import jax  # noqa: PLC0415

    return {k: v for k, v in vars(env).items() if any(isinstance(x, jax.Array) for x in jax.tree.leaves(v))}


def with_arrays(env, arrays: dict):
    """A shallow copy of `env` whose array attributes are `arrays` (traced values in a program)."""
    clone = copy.copy(env)
    clone.__dict__.update(arrays)
    return clone


def worker(args) -> None:
    """One process: build the env, run each way once to compile and once timed, write its share."""
    import jax  # noqa: PLC0415
    import jax.numpy as jnp  # noqa: PLC0415
    import numpy as np  # noqa: PLC0415
    from jax.experimental import multihost_utils  # noqa: PLC0415
    from jax.sharding import Mesh  # noqa: PLC0415
    from jax.sharding import PartitionSpec as P  # noqa: PLC0415

    from bumps_jax import config  # noqa: PLC0415
    from bumps_jax.algo import rollout, sharding  # noqa: PLC0415
    from bumps_jax.tasks import registry  # noqa: PLC0415

    sharding.initialize_distributed()
    cfg = config.make_config(args.preset, {"task": args.task})
    env = registry.make_env(args.task, cfg.env)
    n = args.episodes * jax.process_count()
    contexts = np.resize(np.asarray(cfg.filter.tasks, np.float32), (n, *np.shape(cfg.filter.tasks)[1:]))
    keys = rollout.repetition_keys(0, n, 1)
    obs_size = env.context_observation_size
    params = 0.1 * jax.random.normal(jax.random.key(1), (env.action_size, obs_size))

    def policy(w, obs):
        return jnp.tanh(w @ obs)

    def batch(e):
        return jax.vmap(rollout.over_reps(rollout.episode_fn(e, policy)), in_axes=(None, 0, 0, 0))

    out: dict = {"process": jax.process_index(), "device": str(jax.local_devices()[0].device_kind)}
    # per_process: the pipeline's way
    local = sharding.device_mesh(impl=cfg.env.impl)
    per_process = sharding.over_batch(batch(env), local, (False, True, True, True))

    def per_process_way():
        return lambda: per_process(params, contexts, contexts, keys)

    # global_mesh: one program over every process's device, the env's arrays as arguments
    mesh = Mesh(np.asarray(jax.devices()), (sharding.AXIS,))
    arrays = env_arrays(env)

    def program(arrays, w, c, t, k):
        return batch(with_arrays(env, arrays))(w, c, t, k)

    specs = (P(), P(), P(sharding.AXIS), P(sharding.AXIS), P(sharding.AXIS))
    mapped = jax.jit(jax.shard_map(program, mesh=mesh, in_specs=specs, out_specs=P(sharding.AXIS), check_vma=False))

    def global_mesh_way():
        # The replicated arguments are placed once, as the per-process way's env arrays sit on its
        # device already; each call places only the batch's rows, as `over_batch` does.
        host = multihost_utils.host_local_array_to_global_array
        placed = [host(x, mesh, P()) for x in (jax.tree.map(np.asarray, arrays), np.asarray(params))]

        def run():
            rows = sharding.own_rows((contexts, contexts, np.asarray(jax.random.key_data(keys))))
            rows = [host(x, mesh, P(sharding.AXIS)) for x in rows[:2]] + [
                jax.random.wrap_key_data(host(rows[2], mesh, P(sharding.AXIS)))
            ]
            return multihost_utils.process_allgather(mapped(*placed, *rows), tiled=True)

        return run

    finals = {}
    for name, way in (("per_process", per_process_way), ("global_mesh", global_mesh_way)):
        try:
            run = way()
            t0 = time.perf_counter()
            jax.block_until_ready(run())
            first = time.perf_counter() - t0
            sharding.barrier(f"{name}-compiled")
            t0 = time.perf_counter()
            metrics = jax.block_until_ready(run())
            wall = time.perf_counter() - t0
            finals[name] = np.asarray(metrics[env.ACHIEVED], np.float64)
            out[name] = {"wall_s": wall, "compile_s": first - wall, "episodes": n}
        except Exception as err:  # noqa: BLE001 (the record says what stopped this way)
            out[name] = {"error": f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"}
        # after each way: what is done survives a crash in the next (Warp's physics can take the process down)
        (args.worker / f"result.{jax.process_index()}.json").write_text(json.dumps(out))
    if len(finals) == 2:
        a, b = finals["per_process"], finals["global_mesh"]
        out["same_metrics"] = bool(np.array_equal(a, b))
        out["max_difference"] = float(np.max(np.abs(a - b)))
    (args.worker / f"result.{jax.process_index()}.json").write_text(json.dumps(out))


def main(argv=None) -> None:
    args = parse_args(argv)
    if args.worker is not None:
        return worker(args)
    from bumps_jax import config, launch, runio  # noqa: PLC0415

    try:
        cfg = config.make_config(args.preset, {"task": args.task})
        runio.check_writable(args.out.parent, "the record's folder")
    except ValueError as err:
        raise SystemExit(f"error: {err}") from None
    gpus = launch.visible_gpus()
    if gpus is not None and len(gpus) < args.processes:
        raise SystemExit(f"error: --processes {args.processes} needs as many GPUs; this host shows {len(gpus)}")
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="global-mesh-") as tmp:
        port, procs = launch.free_port(), []
        for i in range(args.processes):
            own = ["--processes", str(args.processes), "--episodes", str(args.episodes), "--worker", tmp]
            cmd = [sys.executable, __file__, "--task", args.task, "--preset", args.preset, "--out", str(args.out), *own]
            log = open(Path(tmp) / f"log.{i}", "w")  # noqa: SIM115 (closed with its process)
            env = launch.process_env(i, args.processes, port, gpus)
            env["PYTHONFAULTHANDLER"] = "1"  # a crash prints its Python frames
            procs.append((subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT), log))
        print(f"[global_mesh] {args.processes} processes x {args.episodes} episodes, both ways", flush=True)
        failed = wait_all([proc for proc, _ in procs], limit_s=args.limit_s)
        for _, log in procs:
            log.close()
        results = []
        for i in range(args.processes):
            path = Path(tmp) / f"result.{i}.json"
            if not path.exists():
                raise SystemExit(f"error: process {i} failed before either way ran: {last_line(Path(tmp), i)}")
            result = json.loads(path.read_text())
            for way in WAYS:  # a way the process did not live to finish: how it ended
                if way not in result and failed is not None:
                    ended = f"process {failed[0]} exited ({failed[1]}): {last_line(Path(tmp), failed[0])}"
                    result[way] = {"error": ended}
            results.append(result)
    record = {"task": args.task, "processes": args.processes, "episodes_per_process": args.episodes,
              "episode_steps": int(env_steps(cfg)), "ways": {}, "per_process_results": results}  # fmt: skip
    for way in WAYS:
        parts = [r[way] for r in results]
        errors = [p["error"] for p in parts if "error" in p]
        if errors:
            record["ways"][way] = {"error": errors[0]}
            continue
        wall = max(p["wall_s"] for p in parts)
        record["ways"][way] = {"episodes_per_s": parts[0]["episodes"] / wall, "wall_s": wall,
                               "compile_s": max(p["compile_s"] for p in parts)}  # fmt: skip
    if all("same_metrics" in r for r in results):
        record["same_metrics"] = all(r["same_metrics"] for r in results)
        record["max_difference"] = max(r["max_difference"] for r in results)
    prov = runio.provenance(cfg.preset, round(time.perf_counter() - start, 3), config.resolved_env(cfg))
    record.update(prov, device=results[0]["device"], n_devices=args.processes, n_processes=args.processes,
                  date=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"))  # fmt: skip
    runio.write_json(args.out, record)
    for way, r in record["ways"].items():
        said = r["error"] if "error" in r else f"{r['episodes_per_s']:,.0f} episodes/s ({r['wall_s']:.2f} s)"
        print(f"{way}: {said}")
    print(f"same final metrics: {record.get('same_metrics')}; wrote {args.out}")


def wait_all(procs, grace_s: float = 10.0, limit_s: float = float("inf")):
    """Wait for every process; once one fails, stop the others after `grace_s` (a peer of a
    crashed process can wait forever in a collective), and all of them after `limit_s`.
    (index, exit code) of the first failure, or None."""
    failed, limit = None, time.monotonic() + limit_s
    while any(p.poll() is None for p in procs):
        if time.monotonic() > limit:
            running = [i for i, p in enumerate(procs) if p.poll() is None]
            for i in running:
                procs[i].kill()
                procs[i].wait()
            return failed or (running[0], f"stopped after --limit-s {limit_s:g}")
        if failed is None:
            failed = next(((i, p.returncode) for i, p in enumerate(procs) if p.poll() not in (None, 0)), None)
            if failed is not None:
                deadline = time.monotonic() + grace_s
        elif time.monotonic() > deadline:
            for p in procs:
                if p.poll() is None:
                    p.kill()
        time.sleep(0.2)
    if failed is None:
        failed = next(((i, p.returncode) for i, p in enumerate(procs) if p.returncode), None)
    return failed


def last_line(folder: Path, i: int) -> str:
    """The last line process `i` printed; for a crash, the fatal error and its innermost Python frame."""
    log = folder / f"log.{i}"
    lines = log.read_text().strip().splitlines() if log.exists() else []
    fatal = [k for k, line in enumerate(lines) if line.startswith("Fatal Python error")]
    if fatal:
        frames = [line.strip() for line in lines[fatal[-1] :] if line.strip().startswith("File ")]
        frames = [re.sub(r'File ".*/site-packages/', 'File "', frame) for frame in frames]  # the package's own path
        return "; ".join([lines[fatal[-1]], *frames[:3]])
    return lines[-1] if lines else "(no output)"


def env_steps(cfg) -> int:
    """Control steps of one episode of the config's task."""
    from bumps_jax.tasks import registry  # noqa: PLC0415

    return registry.get(cfg.task).env_class.n_steps_of(cfg.env)


if __name__ == "__main__":
    main()
