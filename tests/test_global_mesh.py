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
