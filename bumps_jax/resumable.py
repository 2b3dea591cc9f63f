"""Training that survives a kill: orbax checkpoints written whole or not at all, restored from the
newest that reads (a corrupt one set aside), the chunked training loop with its progress lines,
ETA and carried wall time, and Ctrl-C stopping it after the chunk in flight."""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

from bumps_jax.runio import (
    CHECKSUMS,
    CorruptError,
    append_csv,
    error_reason,
    fingerprint,
    read_json,
    remove,
    shown,
    sync,
    trim_csv,
    verify_checksums,
    write_checksums,
    write_json,
    writes_here,
)


class Interrupted(Exception):
    """Ctrl-C (SIGINT) was pressed; the loop stopped after its chunk, with its state saved."""


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
                if isinstance(kwargs.get("args"), ocp.args.StandardRestore):
                    kwargs["args"] = ocp.args.StandardRestore(restorable(kwargs["args"].item))
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


def restorable(abstract):
    """The shapes `abstract` as orbax restores them in any number of processes: as they are in
    one; in several, each array on this process's own device. A checkpoint keeps the devices it
    was saved from, and one saved by a single process names a device that only process 0 holds,
    so without this the other processes of a `--processes N` resume could not read it."""
    jax = sys.modules.get("jax")
    if jax is None or jax.process_count() == 1 or abstract is None:
        return abstract
    own = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=own), abstract)


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
    moved aside to `<step>.corrupt`, and the next older one is tried. One whose checksums match
    but that does not restore (another version's state) is kept: ValueError naming it.
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
            sealed = (path / CHECKSUMS).is_file()
            try:
                if not sealed:
                    say(f"checkpoint {shown(path)} carries no checksums (an older version's): restoring it unverified")
                restored[name] = manager.restore(step, args=restore_args[name])  # (verifies its checksums first)
            except Exception as err:  # noqa: BLE001 (orbax and tensorstore raise many kinds)
                if sealed and not isinstance(err, CorruptError):  # its bytes are as written: the reader is at fault
                    raise ValueError(
                        f"checkpoint {shown(path)} is intact (its checksums match) but does not restore here "
                        f"({error_reason(err)}): resume with the version of bumps_jax that wrote it, or remove "
                        f"{shown(path.parent)} to train afresh"
                    ) from None
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
