"""Where a step of the meta-policies' BC loop spends its time on the GPU.

Builds the meta stage's trainer (`bc.make_trainer`: both nets stacked in one program) on a
dataset of the experts' size, times a chunk of `--epochs` epochs (its second call), then traces one
more chunk with the JAX profiler and counts the device's kernels: how many a gradient step runs,
how long each kind takes, and how much of the traced span the device was busy. A chunk is also
compiled with `--program-options` (XLA options given to that one program, `jax.jit`'s
`compiler_options`, rather than to the process by XLA_FLAGS) and timed beside the plain one.

    python -m benchmarks.bc_profile --out benchmarks/results/bc_profile/none.json  # GPU
    XLA_FLAGS=... python -m benchmarks.bc_profile --out OUT.json                  # flags kept in the record
    python -m benchmarks.bc_profile --preset tiny --epochs 2 \
        --out runs/bc_profile.json                                                # CPU smoke test

Tracing slows kernels somewhat: `traced_busy_us_per_step` is for shares, `us_per_step` for speed.
"""

from __future__ import annotations

import argparse
import collections
import re
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from benchmarks.bench import bc_inputs
from bumps_jax import cli, config, runio
from bumps_jax.algo import bc

# The options `--program-options graphs` gives the chunk's program: XLA's default command-buffer
# kinds plus while loops and conditionals (CUDA graphs around the loop), with concurrent regions;
# what `benchmarks/bc_flags.sh`'s graphs_concurrent set gives the whole process.
PROGRAM_OPTIONS = {
    "graphs": {
        "xla_gpu_enable_command_buffer": "FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,WHILE,CONDITIONAL",
        "xla_gpu_graph_enable_concurrent_region": True,
    },
}


def _kind(name: str) -> str:
    """A kernel's kind from XLA's fusion name: gemm_fusion_dot_431 -> gemm_fusion_dot."""
    return re.sub(r"(_\d+)+$", "", name)


def _setup(cfg, epochs: int):
    """(chunk, state, obs, actions, keys, gradient steps per chunk) of the config's trainer."""
    train_cfg, models, obs, actions, keys = bc_inputs(cfg, epochs)
    init, chunk = bc.make_trainer(models, train_cfg, len(obs))
    return chunk, init(keys), obs, actions, keys, epochs * bc.steps_per_epoch(train_cfg, len(obs))


def _time(run, state, repeats: int = 3) -> tuple[list[float], object]:
    """Wall times of `repeats` calls after a first (compiling) one; the last state."""
    state, losses = run(state)
    jax.block_until_ready(losses)
    walls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        state, losses = run(state)
        jax.block_until_ready(losses)
        walls.append(time.perf_counter() - t0)
    return walls, state


def _trace(run, state, steps: int) -> dict:
    """Count the device kernels of one traced call of `run`."""
    with tempfile.TemporaryDirectory() as folder:
        jax.profiler.start_trace(folder)
        _, losses = run(state)
        jax.block_until_ready(losses)
        jax.profiler.stop_trace()
        planes = sorted(Path(folder).rglob("*.xplane.pb"))
        if not planes:
            return {"traced": False}
        data = jax.profiler.ProfileData.from_file(str(planes[-1]))
    total, count, first, last = collections.Counter(), collections.Counter(), None, None
    for plane in data.planes:
        if not plane.name.startswith("/device:GPU"):
            continue
        for line in plane.lines:
            if "Stream" not in line.name:
                continue
            for event in line.events:
                total[event.name] += event.duration_ns
                count[event.name] += 1
                first = event.start_ns if first is None else min(first, event.start_ns)
                end = event.start_ns + event.duration_ns
                last = end if last is None else max(last, end)
    if sum(count.values()) < steps:  # a CPU, or a loop run as CUDA graphs, whose kernels the tracer does not see
        return {"traced": False, "kernels_seen": sum(count.values())}
    kinds_total, kinds_count = collections.Counter(), collections.Counter()
    for name, ns in total.items():
        kinds_total[_kind(name)] += ns
        kinds_count[_kind(name)] += count[name]
    busy = sum(total.values())
    return {
        "traced": True,
        "kernels_per_step": sum(count.values()) / steps,
        "traced_busy_us_per_step": busy / steps / 1e3,
        "traced_busy_share_of_span": busy / (last - first),
        # each kind of kernel: (per step, us per step, us per kernel), the longest first
        "kinds": {
            kind: {
                "per_step": kinds_count[kind] / steps,
                "us_per_step": ns / steps / 1e3,
                "us_per_kernel": ns / kinds_count[kind] / 1e3,
            }
            for kind, ns in kinds_total.most_common()
        },
    }


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="paper", choices=config.PRESETS)
    p.add_argument("--set", action="append", nargs="+", default=[], metavar="KEY=VALUE",
                   help="dotted config overrides, e.g. meta.train.batch_size=256")  # fmt: skip
    p.add_argument("--epochs", type=int, default=1000, help="epochs per timed chunk (default 1000)")
    p.add_argument("--program-options", default="graphs", choices=sorted(PROGRAM_OPTIONS) + ["none"],
                   help="XLA options given to one program, timed beside the plain one (none: skip)")  # fmt: skip
    p.add_argument("--out", required=True, help="the record to write (JSON)")
    args = p.parse_args(argv)
    if args.epochs < 1:
        p.error(f"--epochs must be a positive integer, got {args.epochs}")
    try:
        cfg = config.make_config(args.preset, cli.parse_overrides(args.set))
        runio.check_writable(Path(args.out).parent)
    except ValueError as err:
        p.error(str(err))
    return args, cfg


def main(argv=None) -> dict:
    args, cfg = parse_args(argv)
    start = time.perf_counter()
    chunk, state, obs, actions, keys, steps = _setup(cfg, args.epochs)
    plain = lambda s: chunk(s, obs, actions, keys)  # noqa: E731
    walls, state = _time(plain, state)
    record = {
        "trainer": "stacked_batched",  # the one trainer, under the name it was measured by before
        "unroll": bc.steps_unrolled(bc.steps_per_epoch(cfg.meta.train, len(obs))),
        "epochs_per_chunk": args.epochs,
        "steps_per_chunk": steps,
        "us_per_step": float(np.mean(walls)) / steps * 1e6,
        "us_per_step_runs": [w / steps * 1e6 for w in walls],
    }
    # projected: both nets' full schedules at this rate (compiles and host work not included)
    record["bc_projected_s"] = cfg.meta.train.epochs * (steps / args.epochs) * record["us_per_step"] / 1e6
    if args.program_options != "none":
        options = PROGRAM_OPTIONS[args.program_options]
        compiled = chunk.lower(state, obs, actions, keys).compile(compiler_options=options)
        walls, state = _time(lambda s: compiled(s, obs, actions, keys), state)
        record["program_options"] = {"name": args.program_options, "options": options,
                                     "us_per_step": float(np.mean(walls)) / steps * 1e6}  # fmt: skip
    record.update(_trace(plain, state, steps))
    print({k: v for k, v in record.items() if k != "kinds"}, flush=True)
    record.update(runio.provenance(cfg.preset, time.perf_counter() - start, config.resolved_env(cfg)))
    runio.write_json(Path(args.out), record)
    print(f"wrote {args.out}")
    return record


if __name__ == "__main__":
    main()
