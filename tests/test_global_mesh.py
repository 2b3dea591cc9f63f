"""The two ways past one device (experiments/global_mesh.py): two CPU processes roll out one
batch with the pipeline's per-process programs and with one program over a global mesh that
takes the env's arrays as arguments; both give the same episodes."""

import json
import os
import subprocess
import sys
from pathlib import Path

from experiments import global_mesh

ROOT = Path(__file__).resolve().parent.parent


def test_both_ways_run_the_same_episodes_on_two_processes(tmp_path):
    out = tmp_path / "global_mesh.json"
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, str(ROOT / "experiments" / "global_mesh.py"), "--processes", "2", "--preset", "tiny",
           "--episodes", "4", "--out", str(out)]  # fmt: skip
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    record = json.loads(out.read_text())
    assert record["same_metrics"] is True and record["max_difference"] == 0.0
    assert set(record["ways"]) == set(global_mesh.WAYS)
    assert all(way["episodes_per_s"] > 0 for way in record["ways"].values())
    assert [r["per_process"]["episodes"] for r in record["per_process_results"]] == [8, 8]
    assert record["n_processes"] == 2 and record["task"] == "cheetah_vel"


def test_one_process_is_refused_in_one_line(capsys):
    import pytest

    with pytest.raises(SystemExit):
        global_mesh.parse_args(["--processes", "1", "--out", "x.json"])
    assert "--processes must be at least 2" in capsys.readouterr().err


def test_a_crashed_process_stops_its_peers_and_is_named():
    import time

    procs = [subprocess.Popen([sys.executable, "-c", "import sys; sys.exit(3)"]),
             subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])]  # fmt: skip
    began = time.monotonic()
    assert global_mesh.wait_all(procs, grace_s=0.5) == (0, 3)
    assert procs[1].returncode != 0 and time.monotonic() - began < 30  # the waiting peer was stopped
    hung = [subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"]) for _ in range(2)]
    assert global_mesh.wait_all(hung, limit_s=1.0) == (0, "stopped after --limit-s 1")
    assert all(p.returncode is not None for p in hung)


def test_a_segfaulted_process_is_named_by_its_fatal_error_and_innermost_frames(tmp_path):
    """A process killed by a signal with the fault handler on: the record names the error and the
    innermost frames (package paths from the package on), not the module list after them."""
    crash = "import ctypes, faulthandler; faulthandler.enable(); ctypes.string_at(0)"
    with open(tmp_path / "log.0", "w") as log:
        code = subprocess.run([sys.executable, "-c", crash], stdout=log, stderr=subprocess.STDOUT, check=False)
    assert code.returncode != 0
    line = global_mesh.last_line(tmp_path, 0)
    assert line.startswith("Fatal Python error: Segmentation fault; File ")
    assert "site-packages" not in line and "Extension modules" not in line
    (tmp_path / "log.1").write_text(
        "Fatal Python error: Segmentation fault\n\nCurrent thread 0x1 (most recent call first):\n"
        '  File "/opt/env/lib/python3.12/site-packages/jax/_src/compiler.py", line 395 in backend_compile_and_load\n'
        '  File "/opt/env/lib/python3.12/site-packages/jax/_src/profiler.py", line 420 in wrapper\n\n'
        "Extension modules: numpy, jaxlib (total: 2)\n"
    )
    assert global_mesh.last_line(tmp_path, 1) == (
        'Fatal Python error: Segmentation fault; File "jax/_src/compiler.py", line 395 in backend_compile_and_load; '
        'File "jax/_src/profiler.py", line 420 in wrapper'
    )
    (tmp_path / "log.2").write_text("step 1\nerror: out of memory\n")
    assert global_mesh.last_line(tmp_path, 2) == "error: out of memory"
    assert global_mesh.last_line(tmp_path, 3) == "(no output)"
