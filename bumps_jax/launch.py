"""`--processes N`: one command as N processes of JAX's multi-controller runtime on this host.

Each process runs the same command with `--distributed` (`sharding.initialize_distributed`
joins them through a coordinator on this host) and, on a GPU host, sees one GPU of its own
(`CUDA_VISIBLE_DEVICES`: MJX's Warp physics runs on one GPU per process). Every batched program
is then split over the processes (`sharding.over_batch`) and the first process writes the run's
files. The first process prints to this terminal; the others to run_dir/processes/process<i>.log.
If one process fails, the others are stopped and the failure is named with its log's last line;
none outlives the launcher (on Linux, even a kill -9 of it ends them).
Several hosts (SLURM) start the processes themselves: `srun ... --distributed`.
A pipeline may run in phases whose branches run side by side as jobs of their own
(`runner.schedule`: the baseline beside the meta-policies).
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

LOGS = "processes"  # run_dir/processes/process<i>.log: the output of every process but the first


def check_count(n) -> int:
    """`--processes`: an integer >= 1, else ValueError naming it."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"--processes must be an integer >= 1, got {n!r}")
    return n


def visible_gpus() -> list[str] | None:
    """The GPUs the processes can be given, one each: CUDA_VISIBLE_DEVICES's list where it is set,
    else the indices `nvidia-smi` lists; None where JAX runs on the CPU (JAX_PLATFORMS=cpu) or
    the host shows no GPU."""
    if os.environ.get("JAX_PLATFORMS", "").split(",")[0] == "cpu":
        return None
    if os.environ.get("CUDA_VISIBLE_DEVICES") is not None:
        return [g for g in os.environ["CUDA_VISIBLE_DEVICES"].split(",") if g.strip()] or None
    if shutil.which("nvidia-smi") is None:
        return None
    out = subprocess.run(
        ["nvidia-smi", "--query-gpu=index", "--format=csv,noheader"], capture_output=True, text=True, check=False
    )
    gpus = [line.strip() for line in out.stdout.splitlines() if line.strip()]
    return gpus or None


def free_port() -> int:
    """A TCP port free on this host now, for the processes' coordinator."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def process_env(i: int, n: int, port: int, gpus: list[str] | None) -> dict:
    """Process i's environment: the coordinator, the process count and index, and its own GPU."""
    env = {**os.environ, "JAX_COORDINATOR_ADDRESS": f"127.0.0.1:{port}", "JAX_NUM_PROCESSES": str(n),
           "JAX_PROCESS_ID": str(i)}  # fmt: skip
    if gpus is not None:
        env["CUDA_VISIBLE_DEVICES"] = gpus[i]
    return env


def without_processes(argv: list[str]) -> list[str]:
    """argv without its --processes option (as `--processes N` or `--processes=N`)."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == "--processes":
            skip = True
        elif not a.startswith("--processes="):
            out.append(a)
    return out


def with_options(argv: list[str], options: dict) -> list[str]:
    """argv with each option of `options` (e.g. {"--stages": ["meta"]}) given these values instead
    of its own (the values after it up to the next option)."""
    out, skip = [], False
    for a in argv:
        if a in options:
            skip = True
        elif skip and not a.startswith("-"):
            continue
        else:
            skip = False
            out.append(a)
    for flag, values in options.items():
        out += [flag, *map(str, values)]
    return out


def dies_with_this_process():
    """A `preexec_fn` for a child process that ends when this process ends, however it ends (kill
    -9 too; Linux): the launcher holds the run directory's lock, and processes outliving it would
    go on writing into a directory that a rerun then takes as free. Elsewhere None (no such
    call): there the processes outlive a killed launcher."""
    if not sys.platform.startswith("linux"):
        return None
    import ctypes  # noqa: PLC0415 (here, not in the child: nothing is imported between fork and exec)

    prctl, parent = ctypes.CDLL(None, use_errno=True).prctl, os.getpid()

    def preexec():
        prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
        if os.getppid() != parent:  # the launcher died before the call above
            os._exit(1)

    return preexec


def last_line(path: Path) -> str:
    lines = [x for x in path.read_text(errors="replace").splitlines() if x.strip()] if path.is_file() else []
    return lines[-1] if lines else "(no output)"


def branch_name(options: dict) -> str:
    """A branch in words: its options' values (its stages, its seeds)."""
    if not options:
        return "the command"
    return "; ".join(f"{flag.lstrip('-')} {' '.join(map(str, v))}" for flag, v in options.items())


def run(argv: list[str], n: int, run_dir: Path, phases=None, poll_s: float = 0.5) -> int:
    """Run `python -m bumps_jax <argv> --distributed` as n processes; the exit code: 0 when every
    process ended well, else the first failure's (named on stderr).

    phases: lists of branches (options, processes) run one list after another, the branches of a
    list side by side, each a job of its own (its own coordinator, its share of the GPUs, argv's
    options replaced by the branch's, e.g. {"--stages": [...]}); default: the whole command on all n."""
    gpus = visible_gpus()
    if gpus is not None and n > len(gpus):
        raise ValueError(f"--processes {n}: this host shows {len(gpus)} GPU(s) ({','.join(gpus)}), one per process")
    phases = phases or [[({}, n)]]
    logs = Path(run_dir) / LOGS
    shutil.rmtree(logs, ignore_errors=True)  # this call's logs only
    logs.mkdir(parents=True, exist_ok=True)
    where = "one GPU each" if gpus is not None else "on the CPU"
    print(f"{n} processes ({where}); every process but the first writes to {logs}/process<i>.log", flush=True)
    for phase in phases:
        code = run_phase(argv, phase, gpus, logs, poll_s)
        if code:
            return code
    return 0


def stop(procs, grace_s: float = 5.0) -> None:
    """SIGTERM every process still running, then SIGKILL those alive after `grace_s` (JAX's
    preemption notifier catches SIGTERM, and the process would wait for its peers' heartbeats
    to time out, minutes)."""
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for p in procs:
        try:
            p.wait(timeout=max(deadline - time.monotonic(), 0.0))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def run_phase(argv: list[str], branches, gpus, logs: Path, poll_s: float) -> int:
    """The branches of one phase side by side: branch b's processes take the next GPUs in turn
    (process slots 0, 1, ... over every branch); slot 0 prints here, the others to their logs."""
    procs, files, names, slot = [], [], [], 0
    tied = dies_with_this_process()  # no process outlives the launcher
    for options, count in branches:
        port = free_port()
        command = [sys.executable, "-m", "bumps_jax", *with_options(without_processes(argv), options), "--distributed"]
        first = slot
        for i in range(count):
            out = None if slot == 0 else (logs / f"process{slot}.log").open("a")  # one log over the phases
            env = process_env(i, count, port, None if gpus is None else gpus[first:])
            files.append(out)
            procs.append(subprocess.Popen(command, env=env, stdout=out, stderr=out, preexec_fn=tied))
            names.append((slot, branch_name(options), i, count))
            slot += 1
        if len(branches) > 1:
            shown = f"process {first}" if count == 1 else f"processes {first}-{slot - 1}"
            print(f"{branch_name(options)}: {shown}, side by side with the others", flush=True)
    failed = None
    try:
        while True:
            codes = [p.poll() for p in procs]  # every process's, each time
            failed = next((i for i, c in enumerate(codes) if c not in (None, 0)), None)
            if failed is not None or all(c == 0 for c in codes):
                break
            time.sleep(poll_s)
    except KeyboardInterrupt:  # Ctrl-C reached every process too: each stops after its chunk
        for p in procs:
            p.wait()
        raise
    finally:
        if failed is not None:
            stop(procs)
        for f in files:
            if f is not None:
                f.close()
    if failed is None:
        return 0
    code = procs[failed].returncode if procs[failed].returncode > 0 else 1  # killed by a signal: 1
    slot, name, i, count = names[failed]
    if slot > 0:
        log = logs / f"process{slot}.log"
        which = f"process {i} of {count}" + ("" if len(branches) == 1 else f" running {name}")
        print(f"error: {which} exited with {code}: {last_line(log)} (its log: {log})", file=sys.stderr)
    return code
