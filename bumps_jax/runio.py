"""What a run writes and reads: provenance, strict JSON, file fingerprints, resumable CSV, orbax
checkpoints, and the chunked training loop with its progress lines and Ctrl-C handling. The stage
manifest built from these lives in `pipeline`."""

from __future__ import annotations

import contextlib
import csv
import datetime
import hashlib
import json
import logging
import math
import os
import shutil
import signal
import sys
import time
from collections.abc import Callable
from importlib import metadata
from pathlib import Path
from typing import Any, NamedTuple

PACKAGES = ("jax", "jaxlib", "mujoco", "mujoco-mjx", "brax", "flax", "optax", "orbax-checkpoint", "evosax", "warp-lang")


class Interrupted(Exception):
    """Ctrl-C (SIGINT) was pressed; the loop stopped after its chunk, with its state saved."""


# -- provenance --------------------------------------------------------------------------------


def device_name() -> str:
    """e.g. 'NVIDIA H100 80GB HBM3', or 'cpu'."""
    import jax  # noqa: PLC0415

    dev = jax.devices()[0]
    return "cpu" if dev.platform == "cpu" else str(dev.device_kind)


def versions() -> dict:
    out = {}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    out["python"] = sys.version.split()[0]
    return out


def provenance(preset: str, wall_s: float, env: dict, command: str | None = None) -> dict:
    """The keys every results file carries: device, versions, date, command, preset, wall time, and
    the env config it ran under (`env`, as its task resolves it: `config.resolved_env`)."""
    import jax  # noqa: PLC0415

    from bumps_jax.algo import sharding  # noqa: PLC0415

    resolved = dict(env)
    record = {
        "device": device_name(),
        # the devices its programs were split over, in every process (Warp: one GPU a process)
        "n_devices": sharding.ways(sharding.device_mesh(impl=resolved.get("impl"))),
        "n_processes": jax.process_count(),
        "versions": versions(),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": command or command_line(),
        "preset": preset,
        "wall_s": round(float(wall_s), 3),
        "env": resolved,
    }
    if os.environ.get("XLA_FLAGS"):  # compiler flags change speed (and may change numbers): kept with them
        record["xla_flags"] = os.environ["XLA_FLAGS"]
    return record


def command_line() -> str:
    """How this process was started, as a user would type it (no absolute paths)."""
    script = Path(sys.argv[0]).resolve()
    package = Path(__file__).resolve().parent
    if script.parent == package:  # python -m bumps_jax[.module]
        head = "python -m bumps_jax" + ("" if script.stem == "__main__" else f".{script.stem}")
    elif sys.argv[0] in ("-c", ""):
        head = "python -c <inline>"
    else:
        try:
            head = f"python {script.relative_to(Path.cwd()).as_posix()}"
        except ValueError:
            head = f"python {script.name}"
    return " ".join([head, *sys.argv[1:]])


# -- files -------------------------------------------------------------------------------------


def json_safe(obj):
    """NaN / inf -> None, numpy scalars and arrays -> Python, recursively: strict JSON."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    if hasattr(obj, "tolist"):  # numpy / jax scalars and arrays
        return json_safe(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_experiment(out_dir: str | os.PathLike, name: str, payload: dict, cfg=None, wall_s: float = 0.0) -> Path:
    """An experiment's record: out_dir/<name>_<cpu|gpu>.json (a CPU run never overwrites the GPU's);
    with `cfg` (the pipeline config it ran under) the payload gains its provenance."""
    import jax  # noqa: PLC0415

    kind = "cpu" if jax.default_backend() == "cpu" else "gpu"
    if cfg is not None:
        from bumps_jax import config  # noqa: PLC0415

        payload = payload | provenance(cfg.preset, wall_s, config.resolved_env(cfg))
    return write_json(Path(out_dir) / f"{name}_{kind}.json", payload)


def shown(path: str | os.PathLike) -> str:
    """`path` as a message or a record names it: relative to the working directory when it lies
    inside it (so that a record never carries where the checkout happened to be)."""
    path = Path(path)
    try:
        return path.resolve().relative_to(Path.cwd().resolve()).as_posix()
    except ValueError:
        return str(path)


def recorded_path(path: str | os.PathLike, run_dir: str | os.PathLike | None = None) -> str:
    """`path` as a record keeps it: relative to `run_dir` where it lies inside it, else relative
    to the repository (a committed asset), else as `shown`."""
    resolved = Path(path).resolve()
    for base in ([Path(run_dir)] if run_dir is not None else []) + [Path(__file__).resolve().parents[1]]:
        try:
            return resolved.relative_to(base.resolve()).as_posix()
        except ValueError:
            continue
    return shown(path)


def write_npz(path: str | os.PathLike, **arrays) -> Path:
    """numpy arrays into `path` (.npz), atomically (temp file + rename)."""
    import numpy as np  # noqa: PLC0415

    path = Path(path)
    if not writes_here():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **arrays)
    tmp.replace(path)
    return path


def sync(name: str) -> None:
    """Wait until every process of a multi-process run has got here (`sharding.barrier`), so none
    reads a file before the process that writes it (`writes_here`) has written it."""
    jax = sys.modules.get("jax")
    if jax is not None and jax.process_count() > 1:
        from bumps_jax.algo import sharding  # noqa: PLC0415

        sharding.barrier(name)


def remove(path: str | os.PathLike) -> None:
    """Remove a file, or a directory and everything under it, if it exists (by the process that
    writes: `writes_here`)."""
    path = Path(path)
    if not writes_here():
        return
    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def write_json(path: str | os.PathLike, payload: dict) -> Path:
    """Strict JSON (no NaN), written atomically (temp file + rename): a killed run never leaves half a file."""
    return write_text(path, json.dumps(json_safe(payload), indent=2, allow_nan=False) + "\n")


def update_json(path: str | os.PathLike, change) -> dict:
    """Read `path` (an empty dict where it does not exist), apply `change(record)` (in place) and
    write it back, holding a lock on path + ".lock" throughout: commands that run side by side
    in one run directory (`launch`) each update their own keys of one record without losing the
    other's. Returns the record as written."""
    import fcntl  # noqa: PLC0415 (POSIX only, as `run_lock`)

    path = Path(path)
    if not writes_here():  # the writer's copy is the record; the others compute the same values
        record = read_json(path) if path.exists() else {}
        change(record)
        return record
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path.with_name(path.name + ".lock"), os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        record = read_json(path) if path.exists() else {}
        change(record)
        write_json(path, record)
        return record
    finally:
        os.close(fd)


def write_text(path: str | os.PathLike, text: str) -> Path:
    """`text` into `path` (UTF-8), atomically (`write_bytes`)."""
    return write_bytes(path, text.encode("utf-8"))


def writes_here() -> bool:
    """Whether this process writes the run's files: every process but the later ones of a
    multi-process run (`sharding.over_batch`), which compute the same values as the first."""
    jax = sys.modules.get("jax")
    return jax is None or jax.process_index() == 0


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """`data` into `path`, atomically (temp file + rename), as `write_text`."""
    path = Path(path)
    if not writes_here():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    tmp.replace(path)
    return path


def replace_block(path: str | os.PathLike, begin: str, end: str, block: str, what: str) -> Path:
    """Replace the text of `path` from the line `begin` to the line `end` (both included) by `block`,
    which carries the markers again. ValueError naming the file and the markers where it lacks them."""
    path = Path(path)
    text = path.read_text()
    start, stop = text.find(begin), text.find(end)
    if start < 0 or stop < start:
        raise ValueError(f"{path} has no {what} (its markers {begin!r} ... {end!r})")
    return write_text(path, text[:start] + block + text[stop + len(end) :])


def read_json(path: str | os.PathLike, what: str = "") -> dict:
    """The JSON object in `path`, or ValueError naming the path (missing, unreadable or not JSON)."""
    path = Path(path)
    hint = f" ({what})" if what else ""
    if not path.is_file():
        raise ValueError(f"{path}: no such file{hint}")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: cannot read it as JSON{hint}: {err}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object{hint}")
    return data


def file_hash(path: str | os.PathLike) -> str:
    """sha256 of a file, or of every file under a directory (names and contents)."""
    path = Path(path)
    h = hashlib.sha256()
    # (a directory's checksum manifest is not its content: a fingerprint does not change when it is added)
    files = sorted(p for p in path.rglob("*") if p.is_file() and p.name != CHECKSUMS) if path.is_dir() else [path]
    for p in files:
        h.update(p.relative_to(path).as_posix().encode() if path.is_dir() else b"")
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


CHECKSUMS = "checksums.json"  # a directory artifact's sha256 of each of its files
FILE_CHECKSUM = ".sha256"  # a file artifact's sha256, in <file>.sha256 beside it


class CorruptError(ValueError):
    """An artifact's bytes differ from the checksum written with it (or it lacks a file it had)."""


def sha256_of(path: str | os.PathLike) -> str:
    """The full sha256 (hex) of one file's bytes."""
    h = hashlib.sha256()
    with Path(path).open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_checksums(directory: str | os.PathLike) -> Path:
    """Seal a finished directory artifact (a checkpoint step, final_params): the sha256 of every
    file under it into directory/checksums.json, written atomically, for `verify_checksums`."""
    directory = Path(directory)
    if not writes_here():
        return directory / CHECKSUMS
    files = sorted(p for p in directory.rglob("*") if p.is_file() and p.name != CHECKSUMS)
    return write_json(
        directory / CHECKSUMS, {"sha256": {p.relative_to(directory).as_posix(): sha256_of(p) for p in files}}
    )


def verify_checksums(directory: str | os.PathLike) -> bool:
    """True if every file `write_checksums` sealed under `directory` holds the bytes it had;
    False if the directory carries no checksums (written by an older version); CorruptError naming
    the first file that differs or is missing."""
    directory = Path(directory)
    path = directory / CHECKSUMS
    if not path.is_file():
        return False
    try:
        sums = json.loads(path.read_text())["sha256"]
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError):
        raise CorruptError(f"{shown(path)}: unreadable checksums") from None
    for name, digest in sums.items():
        file = directory / name
        if not file.is_file():
            raise CorruptError(f"{shown(file)}: missing (its checksum is in {CHECKSUMS})")
        if sha256_of(file) != digest:
            raise CorruptError(f"{shown(file)}: checksum mismatch (its bytes changed since it was written)")
    return True


def write_file_checksum(path: str | os.PathLike) -> Path:
    """Seal a finished file artifact (a dataset): its sha256 into <path>.sha256, atomically."""
    path = Path(path)
    if not writes_here():  # the file is the writing process's (`write_npz`)
        return path.with_name(path.name + FILE_CHECKSUM)
    return write_text(path.with_name(path.name + FILE_CHECKSUM), f"{sha256_of(path)}  {path.name}\n")


def verify_file_checksum(path: str | os.PathLike) -> bool:
    """True if `path` matches its <path>.sha256; False if it has none (an older version's);
    CorruptError naming the file if it differs."""
    path = Path(path)
    sealed = path.with_name(path.name + FILE_CHECKSUM)
    if not sealed.is_file():
        return False
    digest = sealed.read_text().split()[0] if sealed.read_text().strip() else ""
    if not path.is_file() or sha256_of(path) != digest:
        raise CorruptError(f"{shown(path)}: checksum mismatch (its bytes differ from {sealed.name})")
    return True


def error_reason(err: BaseException) -> str:
    """One short line for an exception from a library: its message's first line, or its type's
    name where the message is empty or a repr (pybind11's `<bound method ...>`)."""
    text = str(err).strip()
    line = text.splitlines()[0][:160] if text else ""
    return line if line and not line.startswith("<") else type(err).__name__


def fingerprint(payload) -> str:
    """sha256 of `payload` as sorted JSON (what is not JSON, as its str): the key under which an
    intermediate result is kept (`write_kept`)."""
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()


def write_kept(path: str | os.PathLike, key: str, payload: dict) -> Path:
    """Keep an intermediate result (`payload`) under its fingerprint `key`, written atomically:
    `read_kept` gives it back to a rerun of the same inputs."""
    return write_json(path, {**payload, "fingerprint": key})


def read_kept(path: str | os.PathLike | None, key: str) -> dict | None:
    """What `write_kept` kept at `path` under the fingerprint `key`, else None: no such file, an
    unreadable one (a rerun makes it again), or one kept under another fingerprint."""
    if path is None or not Path(path).is_file():
        return None
    try:
        kept = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return kept if isinstance(kept, dict) and kept.get("fingerprint") == key else None


def check_writable(directory: str | os.PathLike) -> Path:
    """Create `directory` and prove it writable, or ValueError naming it (before any long work)."""
    directory = Path(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        probe = directory / f".write_probe{os.getpid()}"  # one per process: several may start at once
        probe.write_text("")
        probe.unlink()
    except OSError as err:
        raise ValueError(f"run directory {str(directory)!r} is not writable: {err.strerror or err}") from None
    return directory


@contextlib.contextmanager
def run_lock(run_dir: str | os.PathLike, shared: bool = False):
    """Hold run_dir/.lock while a command writes stages into `run_dir`: two processes in one run
    directory would interleave its checkpoints and `pipeline.json`. ValueError at once, naming
    the holder's process id, if another process holds it; the lock goes with the process that
    holds it, however that process ends. shared: held beside other shared holders (commands of
    `--seeds` that each lock their own seed's directory), never beside an exclusive one."""
    import fcntl  # noqa: PLC0415 (POSIX only, as the rest of the tooling)

    run_dir = check_writable(run_dir)
    fd = os.open(run_dir / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            raise ValueError(
                f"run directory {shown(run_dir)} is in use by another process (pid {holder}): run one command "
                "at a time in it, or give this one its own --run-dir"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield run_dir
    finally:
        os.close(fd)  # releases the lock


def save_figure(fig, path: str | os.PathLike) -> Path:
    """Save a matplotlib figure as PNG (tight layout, 120 dpi) and close it."""
    import matplotlib.pyplot as plt  # noqa: PLC0415

    path = Path(path)
    if writes_here():
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.tight_layout()
        fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


# -- resumable CSV -----------------------------------------------------------------------------


def trim_csv(path: Path, fields, key: str, last: int) -> None:
    """Rewrite `path` with the header `fields` and only the rows whose `key` column is <= `last`:
    rows of a chunk whose checkpoint never landed are redone by the resumed run."""
    rows = []
    if not writes_here():
        return
    if path.exists():
        with path.open(newline="") as f:
            rows = [r for r in csv.DictReader(f) if r.get(key) not in (None, "") and int(r[key]) <= last]
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(fields))
        writer.writeheader()
        writer.writerows({k: r.get(k, "") for k in fields} for r in rows)
    tmp.replace(path)


def append_csv(path: Path, fields, rows) -> None:
    """Append dict rows (header first if the file is new)."""
    if not writes_here():
        return
    new = not path.exists()
    with path.open("a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(fields))
        if new:
            writer.writeheader()
        writer.writerows(rows)


# -- checkpoints -------------------------------------------------------------------------------


def checkpoint_manager(directory: Path, keep: int, read_only: bool = False):
    """An orbax manager over `directory`: each step is written to a temporary folder and renamed
    when complete, so a run killed mid-save leaves the previous checkpoint as the latest."""
    import orbax.checkpoint as ocp  # noqa: PLC0415

    manager_class = _sealed_manager_class()
    if not read_only:
        # Several managers save the same step at once (nets trained in one loop): in a
        # multi-process run each needs barriers of its own, named after its directory.
        own = ocp.options.MultiprocessingOptions(barrier_sync_key_prefix=fingerprint(str(Path(directory).resolve())))
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=True, multiprocessing_options=own)
        return manager_class(Path(directory).resolve(), options=options)
    # Orbax logs a warning for every read-only manager; reading a policy is not worth one.
    absl_logger = logging.getLogger("absl")
    level = absl_logger.level
    absl_logger.setLevel(logging.ERROR)
    try:
        return manager_class(Path(directory).resolve(), options=ocp.CheckpointManagerOptions(read_only=True))
    finally:
        absl_logger.setLevel(level)


_SEALED_MANAGER = None


def _sealed_manager_class():
    """orbax's CheckpointManager whose steps carry checksums: a step is sealed (`write_checksums`)
    once its write has finished (`wait_until_finished`, `close`), and `restore` verifies a step
    first (CorruptError naming the file whose bytes changed: a flipped bit never resumes)."""
    global _SEALED_MANAGER  # noqa: PLW0603 (one class, made on first use: orbax loads lazily)
    if _SEALED_MANAGER is None:
        import orbax.checkpoint as ocp  # noqa: PLC0415

        class SealedCheckpointManager(ocp.CheckpointManager):
            def save(self, step, *args, **kwargs):
                if isinstance(kwargs.get("args"), ocp.args.StandardSave):
                    kwargs["args"] = ocp.args.StandardSave(savable(kwargs["args"].item))
                saved = super().save(step, *args, **kwargs)
                self.__dict__.setdefault("_unsealed", []).append(int(step))
                return saved

            def wait_until_finished(self):
                import jax  # noqa: PLC0415

                super().wait_until_finished()
                for step in self.__dict__.pop("_unsealed", []):  # (one host seals a multi-host step)
                    if jax.process_index() == 0 and (Path(self.directory) / str(step)).is_dir():
                        write_checksums(Path(self.directory) / str(step))

            def close(self):
                self.wait_until_finished()
                super().close()

            def restore(self, step, *args, **kwargs):
                verify_checksums(Path(self.directory) / str(step))
                return super().restore(step, *args, **kwargs)

        _SEALED_MANAGER = SealedCheckpointManager
    return _SEALED_MANAGER


def savable(tree):
    """`tree` as orbax saves it from any number of processes: as it is in one process; as host
    (numpy) arrays in several, where orbax refuses an array on one process's device (every
    process holds the same values: `sharding.over_batch` gathers them). Brax's 64-bit counter
    (`UInt64`, in the observation statistics) turns numpy back into device arrays when built,
    so it goes as a dict of its two halves: orbax stores both the same way, and restores either
    as the counter."""
    jax = sys.modules.get("jax")
    if jax is None or jax.process_count() == 1:
        return tree
    import numpy as np  # noqa: PLC0415
    from brax.training.types import UInt64  # noqa: PLC0415

    def host(x):
        return {"hi": np.asarray(x.hi), "lo": np.asarray(x.lo)} if isinstance(x, UInt64) else np.asarray(x)

    return jax.tree.map(host, tree, is_leaf=lambda x: isinstance(x, UInt64))


def keep_newest_checkpoint(directory: Path) -> None:
    """Remove every numbered checkpoint under `directory` but the newest (a finished stage's), once
    the newest is verified (`verify_checksums`): CorruptError naming its bad file, and nothing removed."""
    steps = sorted(int(p.name) for p in Path(directory).iterdir() if p.name.isdigit()) if directory.exists() else []
    if steps:
        verify_checksums(Path(directory) / str(steps[-1]))
    for step in steps[:-1]:
        remove(Path(directory) / str(step))


def restore_latest(manager, restore_args, say=print):
    """(step, restored) from the newest checkpoint that reads, or (None, None) if there is none.

    A corrupt checkpoint (a truncated file, a broken _METADATA) is reported with its path and
    moved aside to `<step>.corrupt`, and the next older one is tried.
    """
    step, restored = restore_latest_common({"": manager}, {"": restore_args}, say)
    return step, None if restored is None else restored[""]


def restore_latest_common(managers: dict, restore_args: dict, say=print) -> tuple[int | None, dict | None]:
    """(step, {name: restored}) from the newest step that every manager holds and that reads in all
    of them, or (None, None). Several nets trained in one loop save one checkpoint each after a
    chunk, so a kill between the saves leaves a net a chunk ahead (or the only one with a first
    checkpoint): its later steps are deleted, and the loop redoes them for all. A corrupt
    checkpoint is set aside as in `restore_latest`."""
    step, restored = None, None
    while restored is None:
        common = set.intersection(*(set(m.all_steps()) for m in managers.values()))
        if not common:
            break
        step, restored = max(common), {}
        for name, manager in managers.items():
            path = Path(manager.directory) / str(step)
            try:
                if not verify_checksums(path):
                    say(f"checkpoint {shown(path)} carries no checksums (an older version's): restoring it unverified")
                restored[name] = manager.restore(step, args=restore_args[name])
            except Exception as err:  # noqa: BLE001 (orbax and tensorstore raise many kinds)
                if isinstance(err, CorruptError):
                    say(f"corrupt checkpoint {shown(path)}: {err}; set aside as {step}.corrupt, trying an older one")
                else:
                    say(f"checkpoint {shown(path)} is unreadable ({error_reason(err)}); set aside as {step}.corrupt, "
                        "trying an older one")  # fmt: skip
                aside = path.with_name(f"{step}.corrupt")
                if writes_here():
                    shutil.rmtree(aside, ignore_errors=True)  # an earlier one set aside at this step
                    shutil.move(str(path), str(aside))
                sync(f"set aside {shown(path)}")
                manager.reload()
                step, restored = None, None
                break
    for manager in managers.values():  # steps past the one restored: the loop saves them again
        for later in [s for s in manager.all_steps() if step is None or s > step]:
            manager.delete(later)
    return step, restored


# -- long loops -------------------------------------------------------------------------------


def _seconds(s: float) -> str:
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.1f} min"


class Clock:
    """The time part of a long loop's progress line: seconds since `since` (default: the clock's
    start) and an ETA from the loop's own pace. The first tick says it includes compiling (a loop's
    first chunk compiles its program); from the second on, the ETA comes from the chunks after the
    first, so neither the compile nor any work before the loop (a stage's setup, say) inflates it.
    total: the units of work the loop ends at (`tick` is given the units done so far)."""

    def __init__(self, total: int, since: float | None = None):
        self.total, self.since, self.mark = total, time.perf_counter() if since is None else since, None

    def tick(self, done: int) -> str:
        now = time.perf_counter()
        elapsed = f"{now - self.since:.1f} s"
        if self.mark is None:
            self.mark = (done, now)
            return f"{elapsed} (compile included)"
        (d0, t0), left = self.mark, max(self.total - done, 0)
        if done <= d0:
            return elapsed
        return f"{elapsed}, ETA {_seconds((now - t0) / (done - d0) * left)}"


class CarriedClock:
    """Seconds a phase took over every process that ran it: what earlier processes recorded in
    `path` (up to their last `save`, e.g. a progress line after a checkpoint) plus this one's.
    A killed process loses only the time since its last save."""

    def __init__(self, path: str | os.PathLike):
        self.path, self.start = Path(path), time.perf_counter()
        try:
            self.before = float(read_json(self.path).get("seconds", 0.0)) if self.path.is_file() else 0.0
        except ValueError:
            self.before = 0.0

    def seconds(self) -> float:
        return self.before + time.perf_counter() - self.start

    def save(self) -> float:
        seconds = self.seconds()
        write_json(self.path, {"seconds": seconds})
        return seconds


class _StopFlag:
    def __init__(self):
        self.requested = False

    def check(self) -> None:
        """Raise Interrupted if Ctrl-C was pressed since the loop started: call it after a chunk is saved."""
        if self.requested:
            raise Interrupted()


_ACTIVE_FLAG: list = []  # the stop flag of the outermost `stop_on_interrupt` now open


@contextlib.contextmanager
def stop_on_interrupt(say=print, at: str = "this chunk"):
    """A chunk loop that Ctrl-C stops cleanly: SIGINT only sets a flag, which the loop reads between
    chunks (`flag.check()`), so the interrupt never lands inside JAX, Warp or orbax (where it can be
    swallowed or crash the process). A second Ctrl-C stops the process at once (SIGINT's default
    action: a compiled program in flight would hold a Python exception back until it returns),
    losing only the work since the last checkpoint. `at`: where the loop stops, as the message
    says it. Inside another one (a stage's guard around its chunk loops) it shares the outer flag,
    also after that flag was set, so an interrupt either catches stops the inner loop at its next
    chunk. Outside the main thread it changes nothing."""
    if _ACTIVE_FLAG:
        yield _ACTIVE_FLAG[-1]
        return
    flag = _StopFlag()

    def handler(signum, frame):
        flag.requested = True
        signal.signal(signal.SIGINT, signal.SIG_DFL)  # the next Ctrl-C ends the process at once
        say(f"\ninterrupt: stopping after {at}, saving it (Ctrl-C again to stop at once, losing it)", flush=True)

    handler.stop_flag = flag
    try:
        previous = signal.signal(signal.SIGINT, handler)
    except ValueError:  # not the main thread
        yield flag
        return
    _ACTIVE_FLAG.append(flag)
    try:
        yield flag
    finally:
        _ACTIVE_FLAG.pop()
        signal.signal(signal.SIGINT, previous)


class ChunkedTraining(NamedTuple):
    """What `train_in_chunks` needs from a stage whose training runs as a loop of compiled chunks."""

    init: Callable[[], Any]  # () -> a fresh state (saved as checkpoint 0)
    chunk: Callable[[Any], tuple]  # state -> (state, metrics) after one chunk of updates
    abstract: Any  # the state's shapes and dtypes, for restoring a checkpoint
    updates: Callable[[Any], int]  # state -> updates it has done
    rows: Callable[[int, Any], list]  # (updates before the chunk, metrics) -> progress.csv rows
    line: Callable[[Any, int, str], str]  # (metrics, updates done, ETA text) -> the progress line
    fields: tuple  # progress.csv's columns; the first counts updates


def train_in_chunks(stage_dir: Path, loop: ChunkedTraining, total: int, keep: int, say=print, max_chunks=None) -> dict:
    """Run `loop` to `total` updates under stage_dir, resuming from its newest readable checkpoint.

    After every chunk: its rows appended to progress.csv, an orbax checkpoint, the training
    seconds so far in wall_time.json (carried across resumes; work redone after a kill counts
    once) and a progress line with an ETA; Ctrl-C stops after the chunk in flight. max_chunks:
    stop after this many chunks in this call (tests of the resume path).
    Returns {"state", "finished": bool, "wall_s": training seconds over every call, "call_s": this call's}.
    """
    import orbax.checkpoint as ocp  # noqa: PLC0415

    stage_dir = Path(stage_dir)
    start = time.perf_counter()
    manager = checkpoint_manager(stage_dir / "checkpoints", keep)
    progress, clock_path = stage_dir / "progress.csv", stage_dir / "wall_time.json"
    clock = read_json(clock_path) if clock_path.exists() else {}
    step, state = restore_latest(manager, ocp.args.StandardRestore(loop.abstract), say)
    previous = 0.0
    if step is not None:
        previous = float(clock.get(str(step), 0.0))
        trim_csv(progress, loop.fields, loop.fields[0], step)
        say(f"resumed from update {step} in {shown(stage_dir)}")
    else:
        state = loop.init()
        manager.save(0, args=ocp.args.StandardSave(state))
        manager.wait_until_finished()
        clock = {"0": time.perf_counter() - start}
        write_json(clock_path, clock)
        progress.unlink(missing_ok=True)
    chunks, pace = 0, Clock(total, since=start)
    with stop_on_interrupt(say) as stop:
        while loop.updates(state) < total and (max_chunks is None or chunks < max_chunks):
            before = loop.updates(state)
            state, metrics = loop.chunk(state)
            update = loop.updates(state)
            # Rows first: if the run dies before the checkpoint lands, the resume trims and redoes them.
            append_csv(progress, loop.fields, loop.rows(before, metrics))
            manager.save(update, args=ocp.args.StandardSave(state))
            manager.wait_until_finished()
            clock[str(update)] = previous + time.perf_counter() - start
            write_json(clock_path, clock)
            chunks += 1
            say(loop.line(metrics, update, pace.tick(update)), flush=True)
            stop.check()
    manager.close()
    call_s = time.perf_counter() - start
    return {"state": state, "finished": loop.updates(state) >= total, "wall_s": previous + call_s, "call_s": call_s}
