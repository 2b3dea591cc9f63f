"""Resumable training: Ctrl-C stops a chunk loop between chunks with its state saved, nets resume
from the newest step they all hold, and the progress clock's ETA."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bumps_jax import resumable

ROOT = Path(__file__).resolve().parents[1]


def test_sigint_sets_a_flag_and_a_second_one_stops_at_once():  # the second: SIGINT's default action
    said = []
    before = signal.getsignal(signal.SIGINT)  # a test worker may run with SIGINT ignored
    with resumable.stop_on_interrupt(lambda *a, **k: said.append(a[0])) as stop:
        stop.check()  # nothing pressed yet
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the handler runs between bytecodes: no exception here
        assert stop.requested and "stopping after this chunk" in said[0]
        with pytest.raises(resumable.Interrupted):
            stop.check()
        # a second Ctrl-C ends the process at once (the default action), even inside a compiled program
        assert signal.getsignal(signal.SIGINT) is signal.SIG_DFL
    assert signal.getsignal(signal.SIGINT) is before  # restored


def test_a_loop_inside_a_guard_shares_its_flag():
    """A chunk loop inside a stage's guard sees an interrupt the guard caught before the loop began."""
    said = []
    before = signal.getsignal(signal.SIGINT)
    with resumable.stop_on_interrupt(lambda *a, **k: said.append(a[0]), at="this stage") as guard:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        assert said == ["\ninterrupt: stopping after this stage, saving it (Ctrl-C again to stop at once, losing it)"]
        with resumable.stop_on_interrupt() as loop:
            assert loop is guard
            with pytest.raises(resumable.Interrupted):
                loop.check()
        assert signal.getsignal(signal.SIGINT) is signal.SIG_DFL  # the inner one left it: a second Ctrl-C stops
    assert signal.getsignal(signal.SIGINT) is before


def test_ctrl_c_stops_a_training_run_within_a_chunk_and_it_resumes(tmp_path):  # issue: defect 10
    env = dict(
        os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])
    )
    cmd = [sys.executable, str(ROOT / "tests" / "interrupted_run.py"), str(tmp_path / "net")]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    lines = []
    for line in proc.stdout:  # wait until training runs (compiled, a chunk done)
        lines.append(line)
        if "epoch" in line:
            break
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    lines += out.splitlines()
    assert proc.returncode == 1, (lines, err)
    assert "interrupted: rerun the same command to resume" in err
    assert "Exception ignored" not in err and "Traceback" not in err and "free()" not in err
    assert not any("finished" in line for line in lines)  # it stopped, it did not run on
    saved = sorted(int(p.name) for p in (tmp_path / "net" / "checkpoints").iterdir() if p.name.isdigit())
    assert saved and max(saved) < 10  # stopped early (10 epochs in all), after a saved chunk
    # The same command resumes from the last checkpoint and finishes.
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "resumed from epoch" in done.stdout and "finished" in done.stdout


def test_nets_resume_from_the_newest_step_all_hold_and_drop_the_steps_past_it(tmp_path):
    """Several nets' checkpoints (`restore_latest_common`): a net a chunk ahead, or the only one with
    a checkpoint at all, loses the steps past the common one, which the loop then saves again."""
    import numpy as np  # noqa: PLC0415
    import orbax.checkpoint as ocp  # noqa: PLC0415

    def save(manager, step):
        manager.save(step, args=ocp.args.StandardSave({"w": np.full(3, float(step))}))
        manager.wait_until_finished()

    args = {name: ocp.args.StandardRestore({"w": np.zeros(3)}) for name in ("a", "b")}
    with resumable.checkpoint_manager(tmp_path / "a", 3) as a, resumable.checkpoint_manager(tmp_path / "b", 3) as b:
        save(a, 1)  # killed before b saved its first chunk
        assert resumable.restore_latest_common({"a": a, "b": b}, args) == (None, None)
        assert a.all_steps() == []
        for step in (1, 2):
            save(a, step)
            save(b, step)
        save(a, 3)  # killed between the two saves of chunk 3
        step, restored = resumable.restore_latest_common({"a": a, "b": b}, args)
        assert step == 2 and list(restored["a"]["w"]) == list(restored["b"]["w"]) == [2.0] * 3
        assert list(a.all_steps()) == [1, 2] and list(b.all_steps()) == [1, 2]


def test_the_progress_clock_takes_its_eta_from_the_chunks_after_the_first(monkeypatch):
    """A stage that spent 300 s before its loop (a tuning), then a first chunk of 25 updates that
    compiled (40 s), then chunks of 25 updates in 25 s each: the ETA is 1 s an update, not the
    13.6 s an update of everything so far."""
    now = [0.0]
    monkeypatch.setattr(resumable.time, "perf_counter", lambda: now[0])
    start = now[0]
    now[0] = 300.0
    pace = resumable.Clock(100, since=start)
    now[0] += 40.0
    assert pace.tick(25) == "340.0 s (compile included)"
    now[0] += 25.0
    assert pace.tick(50) == "365.0 s, ETA 50 s"
    now[0] += 25.0
    assert pace.tick(75) == "390.0 s, ETA 25 s"
    now[0] += 25.0
    assert pace.tick(100) == "415.0 s, ETA 0 s"
    long = resumable.Clock(10_000)
    now[0] += 1.0
    long.tick(1)
    now[0] += 1.0
    assert long.tick(2).endswith("ETA 166.6 min")  # minutes past two of them
