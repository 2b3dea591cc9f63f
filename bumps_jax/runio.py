"""What a run writes and reads: provenance, strict JSON, file checksums and fingerprints, the run
directory's lock, figures and resumable CSV. Checkpoints and the chunked training loop that
writes them are `resumable`'s; the stage manifest built from these lives in `pipeline`."""

from __future__ import annotations

import contextlib
import csv
import datetime
import hashlib
import json
import math
import os
import shutil
import sys
from importlib import metadata
from pathlib import Path

PACKAGES = ("jax", "jaxlib", "mujoco", "mujoco-mjx", "brax", "flax", "optax", "orbax-checkpoint", "evosax", "warp-lang")


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
    """How this process was started, as a user would type it (no absolute paths: `portable_argument`):
    `python -m <module>` where it ran as a module, else `python <script>`."""
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    if spec is not None and spec.name:  # python -m bumps_jax[.module], python -m experiments.<name>
        head = f"python -m {spec.name.removesuffix('.__main__')}"
    elif sys.argv[0] in ("-c", ""):
        head = "python -c <inline>"
    else:
        script = Path(sys.argv[0]).resolve()
        try:
            head = f"python {script.relative_to(Path.cwd()).as_posix()}"
        except ValueError:
            head = f"python {script.name}"
    return " ".join([head, *(portable_argument(a) for a in sys.argv[1:])])


def portable_argument(argument: str, cwd: Path | None = None) -> str:
    """A command-line argument as a record keeps it: an absolute path (alone or after `--opt=`)
    relative to the working directory where it lies under it, else by its name alone, so that a
    record names no folder of the machine that made it."""
    flag, eq, value = argument.partition("=") if argument.startswith("-") else ("", "", argument)
    if not value.startswith("/"):
        return argument
    path, here = Path(value), (cwd or Path.cwd()).resolve()
    try:
        shown = path.resolve().relative_to(here).as_posix()
    except ValueError:
        shown = path.name or value
    return f"{flag}{eq}{shown}"


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


def update_json(path: str | os.PathLike, change, what: str = "") -> dict:
    """Read `path` (an empty dict where it does not exist), apply `change(record)` (in place) and
    write it back, holding a lock on path + ".lock" throughout: commands that run side by side
    in one run directory (`launch`) each update their own keys of one record without losing the
    other's. Returns the record as written. what: the record in words, for `read_json`'s error."""
    import fcntl  # noqa: PLC0415 (POSIX only, as `run_lock`)

    path = Path(path)
    if not writes_here():  # the writer's copy is the record; the others compute the same values
        record = read_json(path, what) if path.exists() else {}
        change(record)
        return record
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path.with_name(path.name + ".lock"), os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        record = read_json(path, what) if path.exists() else {}
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


def check_writable(directory: str | os.PathLike, what: str = "run directory", create: bool = True) -> Path:
    """Create `directory` and prove it writable, or ValueError naming it as `what` (before any
    long work). create=False: a folder that does not exist is refused, not made (a file the user
    named, whose folder a typo would otherwise create)."""
    directory = Path(directory)
    if directory.exists() and not directory.is_dir():
        raise ValueError(f"{what} {str(directory)!r} is a file, not a folder")
    if not create and not directory.is_dir():
        raise ValueError(f"{what} {str(directory)!r} does not exist: create it first")
    try:
        directory.mkdir(parents=True, exist_ok=True)
        probe = directory / f".write_probe{os.getpid()}"  # one per process: several may start at once
        probe.write_text("")
        probe.unlink()
    except OSError as err:
        raise ValueError(f"{what} {str(directory)!r} is not writable: {err.strerror or err}") from None
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
