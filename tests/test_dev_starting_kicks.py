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
    arm = "per_task,meta.inputs=raw"
    out = subprocess.run([str(SCRIPT), arm], cwd=tmp_path, env={**env, "FROM": "per_task"}, capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert out.returncode == 0, out.stderr
    copied = tmp_path / "runs" / "dev_per_task_meta.inputs_raw" / "experts" / "experts.json"
    assert copied.read_text() == '{"device": "cpu"}'
    stages = [line.split()[2] for line in (tmp_path / "calls").read_text().splitlines() if "--run-dir" in line]
    assert stages == ["train-experts", "meta-train"]
    assert "meta.inputs=raw" in (tmp_path / "calls").read_text()
    missing = subprocess.run([str(SCRIPT), "family,meta.inputs=raw"], cwd=tmp_path, env={**env, "FROM": "family"},
                             capture_output=True, text=True, timeout=120)  # fmt: skip
    assert missing.returncode == 2 and "FROM=family: no finished experts in runs/dev_family/experts" in missing.stderr


def test_the_inputs_comparison_clones_every_map_from_one_seeds_experts(tmp_path):
    """experiments/dev_meta_inputs.sh: per seed the reference arm trains the experts (PPO cut to one
    update) once; the raw and centred arms start from them; PRIOR= gives each arm the prior stage
    (a stand-in `python` records the stage commands and writes the experts' record)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "python").write_text(
        '#!/usr/bin/env bash\necho "$@" >> "$CALLS"\n'
        'if [[ "$*" == *train-experts* ]]; then a="$*"; d=${a##*--run-dir }; d=${d%% *}\n'
        '  mkdir -p "$d/experts"; echo \'{"device": "cpu"}\' > "$d/experts/experts.json"; fi\n'
    )
    (bin_dir / "python").chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "CALLS": str(tmp_path / "calls")}
    (tmp_path / "runs" / "paper" / "prior").mkdir(parents=True)
    (tmp_path / "runs" / "paper" / "prior" / "kick_prior.json").write_text("{}")
    script = SCRIPT.parent / "dev_meta_inputs.sh"
    out = subprocess.run([str(script), "102"], cwd=tmp_path, env={**env, "PRIOR": "runs/paper"}, capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert out.returncode == 0, out.stderr
    calls = [line for line in (tmp_path / "calls").read_text().splitlines() if line.startswith("-m bumps_jax")]
    ref = "runs/dev_start_long_spread_neighbour_leash_1_restarts_4_keep_chain_polish_generations_20_polish_sigma_0.25"
    ref += "_paper_budget_ppo_updates_1_seed_102"
    for suffix, maps in (("", "unit"), ("_meta.inputs_raw", "raw"), ("_meta.inputs_centred", "centred")):
        mine = [line for line in calls if f"--run-dir {ref}{suffix} " in line]
        assert [line.split()[2] for line in mine][-3:] == ["train-experts", "meta-train", "filter"]
        assert all("experts.ppo.total_env_steps=19200" in line and "experts.seed=102" in line for line in mine)
        assert all(("meta.inputs=" in line) == (maps != "unit") for line in mine)
        assert (tmp_path / f"{ref}{suffix}" / "prior" / "kick_prior.json").exists()
    # the experts are trained once, by the reference arm; the others copy them
    trained = [line for line in calls if "train-experts" in line]
    assert len(trained) == 4 and sum(f"--run-dir {ref} " in line for line in trained) == 2
    bad = subprocess.run([str(script), "1o2"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "SEED must be a non-negative integer, got '1o2'" in bad.stderr
    bad = subprocess.run([str(SCRIPT), "per_task,ppo_updates=0"], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=60)  # fmt: skip
    assert bad.returncode == 2 and "ppo_updates must be a positive integer, got '0'" in bad.stderr
