"""The run-I/O layer: paths in messages, experiment records and their provenance, kept results, the run lock."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from bumps_jax import runio
from bumps_jax.pipeline import runner as pipeline

ROOT = Path(__file__).resolve().parents[1]


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


def test_a_file_given_as_a_folder_is_named_as_what_it_was_given_for(tmp_path):
    # `kick --gif README.md/k.gif` said "run directory 'README.md' is not writable: File exists".
    blocker = tmp_path / "afile"
    blocker.write_text("")
    with pytest.raises(ValueError, match=r"^the GIF's folder '.*afile' is a file, not a folder$"):
        runio.check_writable(blocker, "the GIF's folder")
    with pytest.raises(ValueError, match=r"^run directory '.*afile' is a file, not a folder$"):
        runio.check_writable(blocker)


def test_a_folder_that_must_exist_is_refused_not_made(tmp_path):
    missing = tmp_path / "missing"
    with pytest.raises(ValueError, match=r"^the GIF's folder '.*missing' does not exist: create it first$"):
        runio.check_writable(missing, "the GIF's folder", create=False)
    assert not missing.exists()
    assert runio.check_writable(tmp_path, "the GIF's folder", create=False) == tmp_path
    assert runio.check_writable(missing).is_dir()  # a run directory is made


def test_the_command_line_names_the_module_a_process_ran_as(tmp_path):
    """A record's command reads as it was typed: `python -m experiments.<name>` for an experiment
    run as a module (it said `python experiments/<name>.py`, which cannot import its package)."""
    code = "from bumps_jax import runio; print(runio.command_line())"
    (tmp_path / "probe").mkdir()
    (tmp_path / "probe" / "__init__.py").write_text("")
    (tmp_path / "probe" / "show.py").write_text(code)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path])}
    run = lambda *argv: subprocess.run([sys.executable, *argv], cwd=tmp_path, env=env, capture_output=True,  # noqa: E731
                                       text=True, check=True).stdout.strip()  # fmt: skip
    assert run("-m", "probe.show", "--out", "x.json") == "python -m probe.show --out x.json"
    assert run("probe/show.py", "--seeds", "1") == "python probe/show.py --seeds 1"
    inside, outside = tmp_path / "runs" / "r.json", tmp_path.parent / "elsewhere" / "out"
    assert run("-m", "probe.show", "--out", str(inside), f"--out-dir={outside}", "--prior", "/") == (
        "python -m probe.show --out runs/r.json --out-dir=out --prior /"
    )


def test_a_records_command_names_no_folder_outside_the_working_directory(tmp_path):
    """Absolute paths: under the working directory relative to it, elsewhere by name alone;
    anything else (relative paths, numbers, flags, a negative number) as typed."""
    shown = lambda a: runio.portable_argument(a, cwd=tmp_path)  # noqa: E731
    assert shown(str(tmp_path / "a" / "b.json")) == "a/b.json"
    assert shown("/srv/out/b.json") == "b.json"
    assert shown("--out=/srv/out/b.json") == "--out=b.json"
    assert shown("--out=" + str(tmp_path / "c.json")) == "--out=c.json"
    for typed in ("runs/x.json", "-3", "--seeds", "0.5", "--set=a.b=/c"):
        assert shown(typed) == typed
