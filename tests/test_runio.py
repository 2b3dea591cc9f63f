"""The run-I/O layer: Ctrl-C stops a chunk loop between chunks, with a resumable state."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bumps_jax import resumable, runio
from bumps_jax.pipeline import runner as pipeline

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


def test_a_manifest_and_messages_name_paths_relative_to_the_working_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "run" / "prior").mkdir(parents=True)
    start = tmp_path / "run" / "prior" / "start.json"
    start.write_text("{}")
    wanted = pipeline.manifest({"a": 1}, {"start": start.resolve()})
    assert wanted["inputs"]["start"]["path"] == "run/prior/start.json"
    assert runio.shown(tmp_path.parent / "elsewhere") == str(tmp_path.parent / "elsewhere")


def test_an_experiment_record_is_named_by_the_backend_and_carries_its_provenance(tmp_path):
    from bumps_jax import config
    from bumps_jax.tasks.kick import env as kick_env

    cfg = config.make_config("tiny")
    path = runio.write_experiment(tmp_path, "probe", {"value": 1.5}, cfg, 2.0)
    assert path == tmp_path / "probe_cpu.json"  # the tests run on the CPU
    record = runio.read_json(path)
    assert record["value"] == 1.5 and record["wall_s"] == 2.0 and record["preset"] == "tiny"
    assert record["env"]["physics_dt"] == kick_env.resolved(cfg.env)["physics_dt"] > 0
    assert runio.read_json(runio.write_experiment(tmp_path, "bare", {"value": 2})) == {"value": 2}


def test_a_record_keeps_the_compiler_flags_it_ran_under(monkeypatch):
    from bumps_jax import config

    env = config.resolved_env(config.make_config("tiny"))
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert "xla_flags" not in runio.provenance("tiny", 1.0, env)
    monkeypatch.setenv("XLA_FLAGS", "--xla_gpu_enable_command_buffer=FUSION,WHILE")
    assert runio.provenance("tiny", 1.0, env)["xla_flags"] == "--xla_gpu_enable_command_buffer=FUSION,WHILE"


def test_a_kept_result_comes_back_only_under_its_own_fingerprint(tmp_path):
    path = tmp_path / "kept" / "run.json"
    key = runio.fingerprint({"b": [1, 2], "a": 0.5})
    assert key == runio.fingerprint({"a": 0.5, "b": [1, 2]})  # the order of keys does not matter
    assert runio.read_kept(path, key) is None  # nothing kept yet
    runio.write_kept(path, key, {"seconds": 3.0})
    assert runio.read_kept(path, key) == {"seconds": 3.0, "fingerprint": key}
    assert runio.read_kept(path, runio.fingerprint({"a": 0.25, "b": [1, 2]})) is None  # other inputs
    path.write_text('{"seconds": 3.0, "fingerprint": ')  # a file cut short: made again, not a crash
    assert runio.read_kept(path, key) is None
    assert runio.read_kept(None, key) is None  # nothing is kept where no folder is given


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


def test_a_run_directory_in_use_by_another_process_is_refused_in_one_line(tmp_path):
    hold = (
        "import sys, time; from bumps_jax import runio\n"
        "with runio.run_lock(sys.argv[1]):\n print('held', flush=True); time.sleep(60)"
    )
    proc = subprocess.Popen([sys.executable, "-c", hold, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "held"
        with pytest.raises(ValueError, match=rf"in use by another process \(pid {proc.pid}\): run one command"):
            with runio.run_lock(tmp_path):
                pass
    finally:
        proc.kill()
        proc.wait()
    with runio.run_lock(tmp_path) as run_dir:  # a killed holder leaves the directory free
        assert (run_dir / ".lock").read_text().strip() == str(os.getpid())


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
