"""The development script's dispatch of arms over GPUs (experiments/dev_starting_kicks.sh, GPUS=n):
each arm a run of the script alone, one GPU each, round robin; a failing arm fails the whole."""

import os
import subprocess
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "experiments" / "dev_starting_kicks.sh"


def run(tmp_path, *arms, gpus="2"):
    env = {**os.environ, "GPUS": gpus}
    return subprocess.run([str(SCRIPT), *arms], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)


def test_arms_go_round_robin_over_the_gpus_each_with_its_own_log(tmp_path):
    out = run(tmp_path, "bogus_a", "bogus_b", "bogus_c")
    assert out.returncode == 1  # every arm failed (an unknown part), so the whole fails
    lines = [line for line in out.stdout.splitlines() if line.startswith("arm ")]
    assert lines == [
        "arm bogus_a on GPU 0: runs/dev_bogus_a.log",
        "arm bogus_b on GPU 1: runs/dev_bogus_b.log",
        "arm bogus_c on GPU 0: runs/dev_bogus_c.log",
    ]
    for arm in ("bogus_a", "bogus_b", "bogus_c"):
        assert (tmp_path / "runs" / f"dev_{arm}.log").read_text().strip() == f"unknown arm part: {arm}"


def test_a_bad_gpu_count_stops_before_any_arm(tmp_path):
    out = run(tmp_path, "bogus_a", "bogus_b", gpus="two")
    assert out.returncode == 2 and "GPUS must be a positive integer, got 'two'" in out.stderr
    assert not (tmp_path / "runs").exists()


def test_an_arm_from_another_starts_from_its_experts(tmp_path):
    """FROM=ARM copies ARM's finished experts into the new arm's run directory once, before its
    stages run (a stand-in `python` records the stage commands instead of training)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "python").write_text('#!/usr/bin/env bash\necho "$@" >> "$CALLS"\n')
    (bin_dir / "python").chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "CALLS": str(tmp_path / "calls")}
    source = tmp_path / "runs" / "dev_per_task" / "experts"
    source.mkdir(parents=True)
    (source / "experts.json").write_text('{"device": "cpu"}')
    arm = "per_task,meta.train.batch_size=256"
    out = subprocess.run([str(SCRIPT), arm], cwd=tmp_path, env={**env, "FROM": "per_task"}, capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert out.returncode == 0, out.stderr
    copied = tmp_path / "runs" / "dev_per_task_meta.train.batch_size_256" / "experts" / "experts.json"
    assert copied.read_text() == '{"device": "cpu"}'
    stages = [line.split()[2] for line in (tmp_path / "calls").read_text().splitlines() if "--run-dir" in line]
    assert stages == ["train-experts", "meta-train"]
    assert "meta.train.batch_size=256" in (tmp_path / "calls").read_text()
    missing = subprocess.run([str(SCRIPT), "long_start,meta.train.batch_size=256"], cwd=tmp_path,
                             env={**env, "FROM": "long_start"}, capture_output=True, text=True,
                             timeout=120)  # fmt: skip
    assert missing.returncode == 2
    assert "FROM=long_start: no finished experts in runs/dev_long_start/experts" in missing.stderr


def test_a_bad_arm_part_is_one_line(tmp_path):
    env = dict(os.environ)
    bad = subprocess.run([str(SCRIPT), "per_task,ppo_updates=0"], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=60)  # fmt: skip
    assert bad.returncode == 2 and "ppo_updates must be a positive integer, got '0'" in bad.stderr
