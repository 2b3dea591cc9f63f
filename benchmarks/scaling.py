"""Scale-out: the same work on one GPU and on N, side by side in one run.

The work is the pipeline's two batched programs at the preset's sizes (`bench.SIZES`): a chunk
of PPO updates of every expert (env-steps/s) and the high-sample-rate filtering variant end to
end (rollouts/s). With K copies per device (`--copies`, several values measured in turn), N
devices do N x K times the preset's work: N x K copies of every expert, each copy its own
seeds, and N x K times the filtering's selection rollouts, their noise drawn afresh. One GPU
does all of it in one program; N GPUs share it in one of two layouts:

- `processes` (the default): N processes, each with one GPU visible and K copies of the work.
  MJX's Warp physics runs on one GPU per process (`sharding.device_mesh`), so this is how
  Warp scales: independent runs side by side, as the experts of two seeds or two development
  arms are run on a two-GPU host.
- `distributed`: N processes joined by JAX's multi-process runtime (`jax.distributed`, as
  `--processes N` and several hosts run), one GPU each, sharing one batch of N x K copies:
  each process computes its share of every program call and the results are gathered to all
  (`sharding.over_batch`). This is how the pipeline itself spreads over GPUs.
- `mesh`: one process splitting the N x K copies over a mesh of N devices (`sharding.over_batch`),
  for MJX-JAX physics (`--set env.impl=jax`) or several CPU devices.

Each measuring process compiles its program with a first call, waits until every process of
its phase has, and then times a second call; a phase's rate is its total work over the span
from the first start to the last end, so N processes count only while they all run. A GPU
that one copy does not fill gains from more (the physics' rate grows with the batch up to
tens of thousands of episodes), so the ratio depends on K: the record keeps every K measured,
its top-level rates being the largest K's. `--workload W` names the total instead (W copies
shared by the N devices, a layout sharing one batch): `--workload 1` is the preset's own work.

    python -m benchmarks.scaling --preset paper --devices 2 --copies 1 4  # benchmarks/results/scaling.json
    python -m benchmarks.scaling --preset paper --devices 4 --layout distributed --workload 1
    python -m benchmarks.scaling --preset tiny --out-dir runs/bench  # CPU smoke test
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks import bench
from bumps_jax import cli, config, runio

# Each measured work and the record's key of its rate (`bench.Work.amount` per second).
WORKS = {"experts": "experts_env_steps_per_s", "filter": "filter_rollouts_per_s"}
LAYOUTS = ("processes", "distributed", "mesh")
# Seconds a worker may take to build and compile its program, and to run it once timed.
COMPILE_TIMEOUT_S = 1200.0
POLL_S = 0.05


def parse_args(argv=None):
    """(args, pipeline config), every argument checked before any process starts."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", choices=tuple(bench.SIZES), default="paper")
    parser.add_argument("--set", action="append", nargs="+", default=[], metavar="KEY=VALUE",
                        help="config overrides, e.g. env.impl=jax")  # fmt: skip
    parser.add_argument("--devices", type=int, default=2, help="N: the devices the work is spread over")
    parser.add_argument("--layout", choices=LAYOUTS, default="processes",
                        help="one process per device, or one process with a mesh of N devices")  # fmt: skip
    parser.add_argument("--copies", type=int, nargs="+", default=None,
                        help="K: copies of the preset's work per device, each value measured in turn")  # fmt: skip
    parser.add_argument("--workload", type=int, nargs="+", default=None,
                        help="W: copies of the work in all, shared by the devices (not with --copies)")  # fmt: skip
    parser.add_argument("--updates", type=int, default=None,
                        help="PPO updates in the timed chunk (default: the bench's for the preset)")  # fmt: skip
    parser.add_argument("--skip", nargs="*", default=(), choices=tuple(WORKS))
    parser.add_argument("--out-dir", default="benchmarks/results")
    # A worker: one measuring process (started by this module, not by hand).
    parser.add_argument("--worker", choices=tuple(WORKS), help=argparse.SUPPRESS)
    parser.add_argument("--worker-dir", help=argparse.SUPPRESS)
    parser.add_argument("--worker-index", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--worker-devices", type=int, default=1, help=argparse.SUPPRESS)
    parser.add_argument("--worker-copies", type=int, default=1, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.devices < 2:
        parser.error(f"--devices must be at least 2 (the scale-out of one device is itself), got {args.devices}")
    if set(args.skip) >= set(WORKS):
        parser.error(f"--skip leaves nothing to measure: it names every work ({', '.join(WORKS)})")
    if args.copies is not None and args.workload is not None:
        parser.error("--copies and --workload both name the work: give one")
    args.copies = args.copies or [1]
    if any(k < 1 for k in args.copies):
        parser.error(f"--copies must be positive integers, got {args.copies}")
    if args.workload is not None:
        if any(w < 1 for w in args.workload):
            parser.error(f"--workload must be positive integers, got {args.workload}")
        if args.layout == "processes":
            parser.error("--workload needs a layout sharing one batch (distributed or mesh): "
                         "the processes layout gives every device whole copies (--copies)")  # fmt: skip
    if args.updates is not None and args.updates < 1:
        parser.error(f"--updates must be a positive integer, got {args.updates}")
    try:
        cfg = config.make_config(args.preset, cli.parse_overrides(args.set))
        if args.worker is None:
            runio.check_writable(args.out_dir)
    except ValueError as err:
        parser.error(str(err))
    return args, cfg


def layout_of(layout: str, m: int, w: int) -> list[dict]:
    """The processes of a phase doing `w` copies of the preset's work on `m` devices: each one's
    visible GPU (None: the host's as they are), the devices its mesh spans and the copies it
    does (the processes layout: w / m each, a whole number)."""
    if m == 1:
        return [{"gpu": "0", "devices": 1, "copies": w}]
    if layout == "processes":
        return [{"gpu": str(i), "devices": 1, "copies": w // m} for i in range(m)]
    if layout == "distributed":  # one batch of every copy, each process computing its share
        return [{"gpu": str(i), "devices": 1, "copies": w, "processes": m} for i in range(m)]
    return [{"gpu": None, "devices": m, "copies": w}]


def combine(results: list[dict]) -> dict:
    """One phase's measurement from its processes' records (`worker`'s: start, end, amount, ...):
    the total amount over the span from the first start to the last end."""
    span = max(r["end"] for r in results) - min(r["start"] for r in results)
    amount = sum(r["amount"] for r in results)
    return {
        "rate": amount / span,
        "amount": amount,
        "span_s": span,
        # seconds during which every process was timing (the last start to the first end)
        "overlap": min(r["end"] for r in results) - max(r["start"] for r in results),
        "processes": [
            {**{k: r[k] for k in ("amount", "wall_s", "compile_s", "gpu")}, "device": r["provenance"]["device"]}
            for r in results
        ],
    }


def worker_env(gpu: str | None) -> dict:
    """The environment of a measuring process: one GPU visible (`gpu`), or all."""
    env = dict(os.environ)
    if gpu is not None:
        env["CUDA_VISIBLE_DEVICES"] = gpu
    return env


def run_phase(args, work: str, m: int, w: int, folder: Path) -> dict:
    """Start the processes of one phase, let them time their work together, and combine."""
    from bumps_jax import launch  # noqa: PLC0415

    folder.mkdir(parents=True)
    port = launch.free_port()
    base = [sys.executable, "-m", "benchmarks.scaling", "--preset", args.preset, "--worker", work,
            "--worker-dir", str(folder), "--devices", str(args.devices)]  # fmt: skip
    for group in args.set:
        base += ["--set", *group]
    if args.updates is not None:
        base += ["--updates", str(args.updates)]
    procs = []
    for i, p in enumerate(layout_of(args.layout, m, w)):
        log = open(folder / f"log.{i}", "w")  # noqa: SIM115 (closed with its process below)
        own = ["--worker-index", str(i), "--worker-devices", str(p["devices"]), "--worker-copies", str(p["copies"])]
        cmd = [*base, *own]
        env = worker_env(p["gpu"])
        if "processes" in p:  # joined: `sharding.initialize_distributed` reads these
            env = {**launch.process_env(i, p["processes"], port, None), **env}
        procs.append((subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT), log))
    try:
        wait_for(procs, [folder / f"ready.{i}" for i in range(len(procs))], folder, COMPILE_TIMEOUT_S)
        (folder / "go").touch()
        wait_for(procs, [folder / f"result.{i}.json" for i in range(len(procs))], folder, COMPILE_TIMEOUT_S)
    finally:
        for proc, log in procs:
            if proc.poll() is None:
                proc.kill()
            proc.wait()
            log.close()
    return combine([json.loads((folder / f"result.{i}.json").read_text()) for i in range(len(procs))])


def wait_for(procs, files: list[Path], folder: Path, timeout: float) -> None:
    """Until every file exists; ValueError with a process's last line if one fails or time runs
    out (the phase's folder is temporary, so the line is all that is left of its log)."""
    deadline = time.monotonic() + timeout
    while not all(f.exists() for f in files):
        for i, (proc, _) in enumerate(procs):
            if proc.poll() not in (None, 0) or (proc.poll() == 0 and not files[i].exists()):
                raise ValueError(f"measuring process {i} failed (exit {proc.poll()}): {last_line(folder, i)}")
        if time.monotonic() > deadline:
            late = [i for i, f in enumerate(files) if not f.exists()]
            raise ValueError(
                f"measuring process {late[0]} did not finish within {timeout:.0f} s; its last line: "
                f"{last_line(folder, late[0])}"
            )
        time.sleep(POLL_S)


def last_line(folder: Path, i: int) -> str:
    """The last line process `i` of a phase printed."""
    log = folder / f"log.{i}"
    lines = log.read_text().strip().splitlines() if log.exists() else []
    return lines[-1] if lines else "(no output)"


def worker(args, cfg) -> None:
    """One measuring process: build and compile its work, say it is ready, wait for the phase to
    start, time one call, and write what it did."""
    import jax  # noqa: PLC0415 (a worker's devices are set by its environment, before jax starts)

    from bumps_jax.algo import sharding  # noqa: PLC0415

    folder, i = Path(args.worker_dir), args.worker_index
    if "JAX_NUM_PROCESSES" in os.environ:  # the distributed layout
        sharding.initialize_distributed()
    mesh = sharding.device_mesh(args.worker_devices, impl=cfg.env.impl)
    size = bench.SIZES[args.preset]
    # each process its own noise (the copies within one program are seeded apart already); one
    # batch shared by joined processes has one seed
    seed = 1000 * i if jax.process_count() == 1 else 0
    if args.worker == "experts":
        work = bench.experts_work(cfg, args.updates or size["bench_updates"], mesh, args.worker_copies,
                                  seed=cfg.experts.seed + seed)  # fmt: skip
    else:
        work = bench.filter_work(cfg, size["filter_step"], size["filter_reps"], mesh, args.worker_copies, seed=seed)
    t0 = time.perf_counter()
    jax.block_until_ready(work.run())
    first = time.perf_counter() - t0
    (folder / f"ready.{i}").touch()
    deadline = time.monotonic() + COMPILE_TIMEOUT_S  # a launcher gone for good does not leave us waiting
    while not (folder / "go").exists():
        if time.monotonic() > deadline:
            raise ValueError(f"no start signal within {COMPILE_TIMEOUT_S:.0f} s")
        time.sleep(POLL_S)
    start = time.time()
    jax.block_until_ready(work.run())
    end = time.time()
    record = {"start": start, "end": end, "wall_s": end - start, "compile_s": first - (end - start),
              "amount": work.amount / jax.process_count(), "detail": work.detail,  # a joined process: its share
              "gpu": os.environ.get("CUDA_VISIBLE_DEVICES"),
              "provenance": runio.provenance(cfg.preset, 0.0, config.resolved_env(cfg))}  # fmt: skip
    # every process its own file (runio writes only the first process's in a joined job)
    (folder / f"result.{i}.json").write_text(json.dumps(runio.json_safe(record)))


def measure(args, work: str, w: int, folder: Path, say) -> dict:
    """One work at `w` copies in all, on one device and on all: rates, ratio and phases."""
    n, key = args.devices, WORKS[work]
    k = w // n if w % n == 0 else w / n
    out: dict = {"copies_per_device": k, "workload": w, key: {}, "phases": {}}
    for m in (1, n):
        say(f"{work} on {m} device(s), {w} times the preset's work")
        phase = run_phase(args, work, m, w, folder / f"{work}.{w}.{m}")
        out["phases"][str(m)] = {kk: v for kk, v in phase.items() if kk != "rate"}
        out[key][str(m)] = phase["rate"]
        say(f"{key} on {m}: {phase['rate']:,.0f}")
    out[key.replace("_per_s", "_speedup")] = out[key][str(n)] / out[key]["1"]
    return out


def eta_s(costs: list[tuple[int, float]], left: list[int]) -> float:
    """Seconds left for measurements at the workloads `left`, from those done (`costs`: (W,
    seconds) pairs): each a fixed cost (start-up and compiles, which do not grow with W) plus a
    cost per copy, fitted by least squares once two workloads are measured; before that, every
    measurement counted at the mean cost so far (too short where the work per copy dominates)."""
    if not costs:
        return 0.0
    ws = [w for w, _ in costs]
    mean_w, mean_t = sum(ws) / len(ws), sum(t for _, t in costs) / len(costs)
    var = sum((w - mean_w) ** 2 for w in ws)
    per_copy = max(sum((w - mean_w) * (t - mean_t) for w, t in costs) / var, 0.0) if var else 0.0
    fixed = max(mean_t - per_copy * mean_w, 0.0)
    return sum(fixed + per_copy * w for w in left)


def add_measurement(record: dict, work: str, part: dict) -> dict:
    """File one measurement (`measure`'s output for `work`) under its K in record["by_copies"], in
    place, and return the record's top level: the entry of the K measured last (K ascends), with
    the results contract's `experts_speedup` where the experts were measured at that K."""
    k = part["copies_per_device"]
    entry = next((e for e in record["by_copies"] if e["copies_per_device"] == k), None)
    if entry is None:
        record["by_copies"].append(entry := {"copies_per_device": k, "workload": part["workload"], "phases": {}})
    entry["phases"][work] = part["phases"]
    entry.update({key: v for key, v in part.items() if key != "phases"})
    top = {**record, **{key: v for key, v in entry.items() if key != "phases"}}
    if "experts_env_steps_speedup" in top:
        top["experts_speedup"] = top["experts_env_steps_speedup"]
    return top


def main(argv=None) -> dict | None:
    args, cfg = parse_args(argv)
    if args.worker:
        return worker(args, cfg)
    n, start = args.devices, time.perf_counter()
    works = [w for w in WORKS if w not in args.skip]
    size = bench.SIZES[args.preset]
    sizes = {**size, "bench_updates": args.updates or size["bench_updates"]}
    record: dict = {"devices": n, "layout": args.layout, "backend": cfg.env.impl, "sizes": sizes, "by_copies": []}
    workloads = args.workload or [n * k for k in args.copies]
    steps = [(w, work) for w in sorted(set(workloads)) for work in works]
    costs: list[tuple[int, float]] = []  # (W, seconds) of each measurement done

    def say(line: str) -> None:
        spent, done = time.perf_counter() - start, len(costs)
        eta = f", ETA {eta_s(costs, [w for w, _ in steps[done:]]):.0f} s" if done else ""
        print(f"[scaling] {done}/{len(steps)} measured, {spent:.0f} s in{eta}: {line}", flush=True)

    with tempfile.TemporaryDirectory(prefix="scaling-") as tmp:
        for w, work in steps:
            began = time.perf_counter()
            part = measure(args, work, w, Path(tmp), say)
            costs.append((w, time.perf_counter() - began))
            top = add_measurement(record, work, part)
            result = Path(tmp) / f"{work}.{w}.{n}" / "result.0.json"
            prov = json.loads(result.read_text())["provenance"]
            prov.update(n_devices=n, command=runio.command_line(), wall_s=round(time.perf_counter() - start, 3))
            runio.write_json(Path(args.out_dir) / "scaling.json", {**top, **prov})  # after each measurement
    return top


if __name__ == "__main__":
    try:
        main()
    except ValueError as err:
        sys.exit(f"error: {err}")
    except KeyboardInterrupt:  # the measuring processes are stopped with their phase (run_phase)
        sys.exit("interrupted: scaling.json holds the measurements finished so far")
