"""The command line: help, overrides, presets, and one clear line (never a traceback) for every user mistake."""

import json
import os
import subprocess
import sys
import traceback

import pytest

from bumps_jax import cli, config, resumable, runio
from bumps_jax import records as env_records
from bumps_jax.envs import base
from bumps_jax.pipeline import runner as pipeline
from bumps_jax.tasks.kick import env as kick_env


def test_every_command_has_help(capsys):
    own = cli.task_commands()
    assert {"render", "video", "showcase", "kick"} <= set(own)  # the kick's, from its folder
    for command in (*cli.STAGE_COMMANDS, *cli.PIPELINES, *cli.OTHER, *own):
        with pytest.raises(SystemExit) as exit_info:
            cli.main([command, "--help"])
        assert exit_info.value.code == 0
        own_only = command in own and own[command].own_options_only
        assert ("--preset" in capsys.readouterr().out) == (not own_only)


def test_set_may_repeat_and_every_item_is_kept():  # defect 2
    parsed = cli.parse_overrides([["experts.tasks=[3.0]"], ["experts.tune.generations=0", "env.physics_dt=0.005"]])
    assert parsed == {"experts.tasks": (3.0,), "experts.tune.generations": 0, "env.physics_dt": 0.005}
    args = cli.build_parser().parse_args(["train-experts", "--set", "tasks=[3.0]", "--set", "tune.generations=0"])
    assert cli.parse_overrides(args.set, "experts") == {"experts.tasks": (3.0,), "experts.tune.generations": 0}
    with pytest.raises(SystemExit, match=r"error: experts.tasks: target 3.0 m is outside the task range"):
        cli.main(["train-experts", "--set", "tasks=[3.0]", "--set", "tune.generations=0"])


def test_a_stage_reads_its_own_keys_without_their_section():
    assert cli.parse_overrides([["ppo.learning_rate=1e-5", "env.physics_dt=0.005"]], "experts") == {
        "experts.ppo.learning_rate": 1e-5,
        "env.physics_dt": 0.005,
    }
    with pytest.raises(ValueError, match="KEY=VALUE"):
        cli.parse_overrides([["novalue"]])


@pytest.mark.parametrize("item", ["preset=paper", "task=kick"])
def test_the_task_and_preset_are_chosen_by_their_options_not_set(item, tmp_path):
    """`--set preset=paper` labelled a tiny run "paper" and `--set task=kick` ran the kick under
    another --task: both are refused in one line pointing to the option."""
    key, value = item.split("=")
    with pytest.raises(ValueError, match=rf"^--set {item}: {key} is not a config value to set; use --{key} {value}$"):
        cli.parse_overrides([[item]], "experts", "point_goal")
    with pytest.raises(
        SystemExit, match=rf"^error: --set {item}: {key} is not a config value to set; use --{key} {value}$"
    ):
        cli.main(["demo", "--task", "point_goal", "--set", item, "--run-dir", str(tmp_path / "run")])
    assert not (tmp_path / "run").exists()  # refused before the run directory is made


@pytest.mark.parametrize(
    ("command", "item", "named"),
    [
        ("train-experts", "tasks=12", r"--set experts.tasks=12: expected a list like \[7.0, 7.5, 8.0, ...\]"),
        ("train-experts", "ppo.learning_rate=fast", r'--set experts.ppo.learning_rate="fast": expected a finite'),
        ("train-experts", "eval.repetitions=2.5", r"--set experts.eval.repetitions=2.5: expected an integer"),
        ("filter", "seed=1.5", r"--set filter.seed=1.5: expected an integer"),
        ("filter", "net_seed=5", r"filter.net_seed 5 names no network: meta.train.n_seeds is 1"),
        ("filter", "nope=1", r"unknown config key 'filter.nope'"),
        ("kick-prior", "env.impl=torch", r"env.impl must be one of"),
        ("train-experts", "tune.scheme=family", r"unknown config key 'experts.tune.scheme'"),
        ("train-experts", "env.task_range=[18.0,7.0]", r"env.task_range must be 0 < low < high, got"),
    ],
)
def test_wrong_values_are_one_line_before_any_work(tmp_path, command, item, named):  # defect 6
    with pytest.raises(SystemExit, match=f"^error: {named}"):
        cli.main([command, "--run-dir", str(tmp_path / "run"), "--set", item])
    assert not (tmp_path / "run").exists()


def test_presets_cannot_mismatch(tmp_path, monkeypatch):  # defect 5
    monkeypatch.chdir(tmp_path)  # the default run directories (runs/...) are made relative to it
    with pytest.raises(SystemExit, match="--preset 'tiny': reproduce takes 'paper'"):
        cli.main(["reproduce", "--preset", "tiny", "--run-dir", str(tmp_path)])
    with pytest.raises(SystemExit, match="--preset 'paper': demo takes 'tiny'"):
        cli.main(["demo", "--preset", "paper", "--run-dir", str(tmp_path)])
    seen = {}
    monkeypatch.setattr(pipeline, "run_pipeline", lambda stages, cfg, run_dir, force: seen.update(
        preset=cfg.preset, run_dir=run_dir))  # fmt: skip
    cli.main(["reproduce"])
    assert seen == {"preset": "paper", "run_dir": cli.default_run_dir("reproduce", "paper")}
    assert str(seen["run_dir"]) == "runs/paper"
    cli.main(["demo"])
    assert seen == {"preset": "tiny", "run_dir": cli.default_run_dir("demo", "tiny")}


def test_a_pipeline_runs_the_chosen_stages_in_its_order(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the default run directories (runs/...) are made relative to it
    seen = {}
    monkeypatch.setattr(pipeline, "run_pipeline", lambda stages, cfg, run_dir, force: seen.update(stages=stages))
    cli.main(["reproduce", "--stages", "heldout", "baseline", "meta"])
    assert seen["stages"] == ("meta", "heldout", "baseline")
    cli.main(["reproduce"])
    assert seen["stages"] == cli.PIPELINES["reproduce"][0]
    with pytest.raises(SystemExit, match=r"^error: --stages: demo has no stage 'baseline'; choose from experts, "):
        cli.main(["demo", "--stages", "baseline", "--run-dir", str(tmp_path / "run")])
    with pytest.raises(SystemExit, match=r"^error: the cheetah_vel task has no heldout stage; its stages are "):
        cli.main(["reproduce", "--task", "cheetah_vel", "--stages", "heldout", "--run-dir", str(tmp_path / "run")])
    assert not (tmp_path / "run").exists()


def test_stages_on_an_empty_directory_say_what_to_do(tmp_path):  # defect 6
    with pytest.raises(SystemExit, match=r"^error: .*meta/table1.json: no such file \(.*run meta-train first\)"):
        cli.main(["filter", "--run-dir", str(tmp_path)])
    with pytest.raises(SystemExit, match=r"^error: .*experts/experts.json: no such file \(.*run train-experts first\)"):
        cli.main(["meta-train", "--run-dir", str(tmp_path)])
    with pytest.raises(SystemExit, match="^error: .* holds no stage results yet"):
        cli.main(["report", "--run-dir", str(tmp_path)])
    with pytest.raises(SystemExit, match="^error: .*filter/table2.json: no such file"):
        cli.main(["video", "--run-dir", str(tmp_path)])


def test_report_on_a_folder_of_seed_runs_names_them(tmp_path):
    """`reproduce --seeds` writes one run per seed under the run directory: report names them."""
    for seed in (0, 1):
        runio.write_json(tmp_path / f"seed{seed}" / "baseline" / "baseline.json", {"seeds": 1})
    with pytest.raises(SystemExit, match=r"^error: .* holds one run per seed \(seed0, seed1\): report one of them, "
                                         r"e\.g\. --run-dir .*seed0$"):  # fmt: skip
        cli.main(["report", "--run-dir", str(tmp_path)])
    with pytest.raises(SystemExit, match="^error: run directory '/dev/null/run' is not writable"):
        cli.main(["train-experts", "--run-dir", "/dev/null/run"])
    with pytest.raises(SystemExit, match="^error: --episodes must be a positive integer, got -3"):
        cli.main(["showcase", "--episodes", "-3"])


def test_a_truncated_experts_record_is_named_at_once(tmp_path):  # defect 7
    (tmp_path / "experts").mkdir()
    (tmp_path / "experts" / "experts.json").write_text('{"accuracy_mean": 1.0, "tas')
    with pytest.raises(SystemExit, match=r"^error: .*experts/experts.json: cannot read it as JSON"):
        cli.main(["meta-train", "--run-dir", str(tmp_path)])


def test_an_interrupted_stage_says_how_to_resume(tmp_path, monkeypatch):
    def interrupted(*args, **kwargs):
        raise resumable.Interrupted

    monkeypatch.setattr(pipeline, "run_stage", interrupted)
    with pytest.raises(SystemExit, match=f"interrupted: rerun the same command to resume {tmp_path}"):
        cli.main(["filter", "--run-dir", str(tmp_path)])


def test_a_library_error_inside_a_stage_keeps_its_traceback(tmp_path, monkeypatch):
    # A shape mismatch deep in JAX printed one line, "error: Incompatible shapes for broadcasting",
    # with nothing saying where; this package's own ValueErrors stay one line.
    import jax.numpy as jnp

    def broken(*args, **kwargs):
        return jnp.ones((1, 2)) + jnp.ones(3)

    monkeypatch.setattr(pipeline, "run_stage", broken)
    with pytest.raises(ValueError, match="Incompatible shapes for broadcasting") as err:
        cli.main(["filter", "--run-dir", str(tmp_path)])
    assert any("test_cli.py" in str(frame.filename) for frame in traceback.extract_tb(err.value.__traceback__))

    def refused(*args, **kwargs):
        base.validate_task_range((2.0, 1.0))

    monkeypatch.setattr(pipeline, "run_stage", refused)
    with pytest.raises(SystemExit, match=r"^error: env.task_range must be finite with low < high, got \(2.0, 1.0\)$"):
        cli.main(["filter", "--run-dir", str(tmp_path)])


def test_an_interrupted_command_of_no_stage_promises_no_resume(monkeypatch):
    # Ctrl-C on `kick` said "rerun the same command to resume runs/tiny from what it saved"
    from bumps_jax.tasks.kick import policies

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(policies, "load", interrupted)
    with pytest.raises(SystemExit, match=r"^interrupted: kick stopped before it finished \(run it again"):
        cli.main(["kick", "--target", "12"])


def test_records_are_strict_json(tmp_path):  # defect 11
    path = runio.write_json(tmp_path / "r.json", {"error_mean_m": float("nan"), "rows": [float("inf"), 1.0]})
    assert json.loads(path.read_text(), parse_constant=lambda c: pytest.fail(f"not JSON: {c}")) == {
        "error_mean_m": None,
        "rows": [None, 1.0],
    }
    from bumps_jax.algo import evaluate

    row = evaluate.table_row({"accuracy": __import__("numpy").zeros(3), "error_mean_m": __import__("numpy").ones(3)})
    assert row["error_mean_m"] is None and row["tasks_above_threshold"] == 0


def test_no_stray_output_and_plain_numbers_in_errors():  # defect 12
    out = subprocess.run(
        [sys.executable, "-c", "import bumps_jax.tasks.kick.env, bumps_jax.algo.ppo, bumps_jax.config"],
        capture_output=True,
        text=True,
        env={"JAX_PLATFORMS": "cpu", "PATH": ""},
        check=True,
    )
    assert out.stdout == "" and "warp" not in out.stderr.lower()
    with pytest.raises(ValueError) as err:
        kick_env.check_targets([3.0], (7.0, 18.0))
    assert "np.float64" not in str(err.value) and "3.0 m" in str(err.value)


def test_env_overrides_reach_every_stage():
    cfg = config.make_config("tiny", {"env.physics_dt": 0.005, "env.noise.friction": 0.0})
    assert cfg.env.physics_dt == 0.005 and cfg.env.noise.friction == 0.0
    assert config.section(cfg, "meta")["env"]["physics_dt"] == 0.005
    with pytest.raises(ValueError, match=r"env.physics_dt: 0.0025 there, 0.005 here"):
        env_records.check_same_env(kick_env.resolved(config.make_config("tiny").env), cfg.env, "kick prior x")


@pytest.mark.parametrize("command", [["kick-prior"], ["reproduce"], ["reproduce", "--seeds", "0"]])
def test_a_run_directory_in_use_stops_a_stage_command_in_one_line(tmp_path, command):
    with runio.run_lock(tmp_path / "run"):  # as another process holding it would
        with pytest.raises(SystemExit, match=r"error: run directory .* is in use by another process"):
            cli.main([*command, "--preset", "tiny" if command[0] == "kick-prior" else "paper", "--run-dir",
                      str(tmp_path / "run")])  # fmt: skip


@pytest.mark.parametrize("command", [["demo"], ["reproduce"], ["config"], ["train-experts", "--run-dir", "run"]])
def test_an_unknown_task_is_one_line_before_any_work(tmp_path, monkeypatch, command):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit, match=r"^error: --task: unknown task 'nope'; choose one of \('kick', "):
        cli.main([*command, "--task", "nope"])
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["reproduce", "--task", "point_goal", "--preset", "tiny"], "--preset 'tiny': reproduce takes 'paper'"),
        (["demo", "--task", "point_goal", "--set", "experts.ppo.num_envs=0"], "num_envs must be a positive integer"),
    ],
)
def test_a_launch_checks_its_command_before_starting_processes(tmp_path, monkeypatch, argv, message):
    from bumps_jax import launch

    monkeypatch.setattr(launch, "run", lambda *a, **k: pytest.fail("processes started"))
    with pytest.raises(SystemExit, match=message):
        cli.main([*argv, "--run-dir", str(tmp_path / "run"), "--processes", "2"])
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("value", ["0", "-2"])
def test_a_bad_process_count_is_one_line_before_any_work(tmp_path, capsys, value):
    with pytest.raises(SystemExit, match=f"--processes must be an integer >= 1, got {value}"):
        cli.main(["train-experts", "--run-dir", str(tmp_path / "run"), "--processes", value])
    assert not (tmp_path / "run").exists()


def test_more_processes_than_gpus_is_refused(tmp_path, monkeypatch):
    from bumps_jax import launch

    monkeypatch.setattr(launch, "visible_gpus", lambda: ["0", "1"])
    with pytest.raises(SystemExit, match=r"--processes 4: this host shows 2 GPU\(s\) \(0,1\), one per process"):
        cli.main(["train-experts", "--run-dir", str(tmp_path / "run"), "--processes", "4"])


def test_the_launcher_runs_each_process_as_one_of_the_job_and_names_a_failure(tmp_path, monkeypatch, capsys):
    from bumps_jax import launch

    assert launch.without_processes(["demo", "--processes", "4", "--task", "x", "--processes=2"]) == [
        "demo",
        "--task",
        "x",
    ]
    env = launch.process_env(2, 4, 1234, ["5", "6", "7", "8"])
    assert (env["JAX_PROCESS_ID"], env["JAX_NUM_PROCESSES"], env["CUDA_VISIBLE_DEVICES"]) == ("2", "4", "7")
    assert env["JAX_COORDINATOR_ADDRESS"] == "127.0.0.1:1234"
    # a stand-in command: process 1 fails at once, process 0 would run on; the launcher stops it
    script = "import os, sys, time; i = int(os.environ['JAX_PROCESS_ID']); print('process', i, 'says no');"
    script += "sys.exit(3) if i == 1 else time.sleep(60)"
    monkeypatch.setattr(launch.sys, "executable", "python3")
    monkeypatch.setattr(launch, "visible_gpus", lambda: None)
    real_popen = launch.subprocess.Popen
    monkeypatch.setattr(launch.subprocess, "Popen", lambda cmd, **kw: real_popen([sys.executable, "-c", script], **kw))
    assert launch.run(["demo"], 2, tmp_path, poll_s=0.05) == 3
    err = capsys.readouterr().err
    assert "process 1 of 2 exited with 3: process 1 says no" in err


LAUNCHER = """
import subprocess, sys, time
from bumps_jax import launch
tied = launch.dies_with_this_process()
child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"], preexec_fn=tied)
print(child.pid, flush=True)
time.sleep(120)
"""


def _running(pid: int) -> bool:
    """Whether process `pid` runs (a zombie, ended but not yet reaped, does not)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a child's death signal is Linux's")
def test_no_process_outlives_a_killed_launcher():
    # kill -9 on the launcher (its lock on the run directory goes with it): its processes end too,
    # not write on into a directory that a rerun takes as free
    import signal
    import time

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {**os.environ, "PYTHONPATH": root}
    launcher = subprocess.Popen([sys.executable, "-c", LAUNCHER], stdout=subprocess.PIPE, text=True, env=env)
    child = int(launcher.stdout.readline())
    assert _running(child)
    os.kill(launcher.pid, signal.SIGKILL)
    launcher.wait()
    deadline = time.monotonic() + 20
    while _running(child) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _running(child), "the child ran on after its launcher was killed"


def test_the_launcher_runs_a_phase_s_branches_side_by_side_as_jobs_of_their_own(tmp_path, monkeypatch, capfd):
    from bumps_jax import launch

    argv = ["reproduce", "--stages", "meta", "baseline", "--task", "x"]
    assert launch.with_options(argv, {"--stages": ["meta"]}) == ["reproduce", "--task", "x", "--stages", "meta"]
    # Every process reports its command's stages, its job's size and index, and its GPU; then it
    # ends well, except the baseline's second process of the last phase.
    script = (
        "import os, sys; s = ' '.join(sys.argv[sys.argv.index('--stages') + 1 : -1]);"
        "e = os.environ; print(s, e['JAX_NUM_PROCESSES'], e['JAX_PROCESS_ID'], e['CUDA_VISIBLE_DEVICES'],"
        " e['JAX_COORDINATOR_ADDRESS'], flush=True);"
        "sys.exit(4 if s == 'baseline' and e['JAX_PROCESS_ID'] == '1' and 'fail' in e else 0)"
    )
    real_popen = launch.subprocess.Popen
    monkeypatch.setattr(launch, "visible_gpus", lambda: ["g0", "g1", "g2"])
    stand_in = [sys.executable, "-c", script]
    monkeypatch.setattr(launch.subprocess, "Popen", lambda cmd, **kw: real_popen([*stand_in, *cmd], **kw))
    phases = [[({"--stages": ["prior", "experts"]}, 3)], [({"--stages": ["meta"]}, 1), ({"--stages": ["baseline"]}, 2)]]
    assert launch.run(argv, 3, tmp_path, phases, poll_s=0.05) == 0
    logs = {i: (tmp_path / launch.LOGS / f"process{i}.log").read_text().splitlines()[-1].split() for i in (1, 2)}
    assert logs[1][:4] == ["baseline", "2", "0", "g1"] and logs[2][:4] == ["baseline", "2", "1", "g2"]
    assert logs[1][4] == logs[2][4]  # one coordinator per job
    out = capfd.readouterr().out
    assert "prior experts 3 0 g0" in out and "meta 1 0 g0" in out  # process 0 prints here
    assert "stages baseline: processes 1-2, side by side with the others" in out
    monkeypatch.setenv("fail", "1")
    assert launch.run(argv, 3, tmp_path, phases, poll_s=0.05) == 4
    assert "error: process 1 of 2 running stages baseline exited with 4: baseline 2 1 g2" in capfd.readouterr().err


def test_seeds_over_processes_run_side_by_side_the_baseline_with_the_first():
    every = ["prior", "experts", "meta", "baseline"]
    assert cli.seed_phases([0, 1, 2], every, 4) == [
        [
            ({"--seeds": [0], "--stages": every}, 2),
            ({"--seeds": [1], "--stages": ["prior", "experts", "meta"]}, 1),
            ({"--seeds": [2], "--stages": ["prior", "experts", "meta"]}, 1),
        ],
        [({"--seeds": [0, 1, 2], "--stages": every}, 1)],
    ]
    # fewer processes than seeds: each job runs its seeds one after another
    assert cli.seed_phases([0, 1, 2], every, 2)[0] == [
        ({"--seeds": [0, 2], "--stages": every}, 1),
        ({"--seeds": [1], "--stages": ["prior", "experts", "meta"]}, 1),
    ]


def test_a_baseline_at_budget_is_published_alone_and_needs_its_record(tmp_path):
    (tmp_path / "run").mkdir()
    with pytest.raises(SystemExit, match="^error: --baseline-at-budget publishes one baseline run: not with --seed"):
        cli.main(["publish", "--run-dir", str(tmp_path / "run"), "--baseline-at-budget", "--seed-runs", str(tmp_path)])
    with pytest.raises(SystemExit, match=r"^error: .*baseline.json: no such file \(a finished baseline"):
        cli.main(["publish", "--run-dir", str(tmp_path / "run"), "--baseline-at-budget"])


@pytest.mark.parametrize("command", [["filter"], ["meta-train"], ["publish"], ["baseline", "--task", "point_goal"]])
def test_another_tasks_run_directory_is_refused_in_one_line(tmp_path, command):
    """A command given the run directory of another task than its --task (the kick by default)
    says whose run it is before it reads anything under the wrong config."""
    runio.write_json(tmp_path / "experts" / "experts.json", {"task": "cheetah_vel"})
    refused = r"^error: .* holds no (kick|point_goal) run \(its records name 'cheetah_vel'\): "
    with pytest.raises(SystemExit, match=refused + "add --task cheetah_vel, or give another --run-dir$"):
        cli.main([*command, "--run-dir", str(tmp_path)])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["experts"]  # nothing written


def test_another_tasks_seed_run_is_refused_before_any_seed_runs(tmp_path):
    runio.write_json(tmp_path / "seed1" / "experts" / "experts.json", {"task": "cheetah_vel"})
    with pytest.raises(SystemExit, match=r"^error: .*seed1 holds no kick run .*: add --task cheetah_vel"):
        cli.main(["reproduce", "--seeds", "0", "1", "--stages", "experts", "--run-dir", str(tmp_path)])
    assert not (tmp_path / "seed0").exists()


def test_a_run_of_another_preset_whose_env_differs_asks_for_its_preset(tmp_path):
    """A paper run read with the default tiny preset, where their envs differ, names the preset to
    add; where the envs agree, the command may read it with another preset's settings."""
    paper = config.make_config("paper", {"task": "cheetah_vel"})
    record = {"task": "cheetah_vel", "preset": "paper", "env": config.resolved_env(paper)}
    runio.write_json(tmp_path / "experts" / "experts.json", record)
    refused = r"^error: .* holds a run of preset 'paper' \(its records say so\), whose env this command's preset "
    with pytest.raises(SystemExit, match=refused + r"'tiny' does not share: add --preset paper$"):
        cli.main(["meta-train", "--task", "cheetah_vel", "--run-dir", str(tmp_path)])
    tiny = config.make_config("tiny", {"task": "cheetah_vel"})
    cli.check_run(tmp_path, paper)  # its own preset
    runio.write_json(tmp_path / "experts" / "experts.json", {**record, "env": config.resolved_env(tiny)})
    cli.check_run(tmp_path, tiny)  # another preset's record, made under this env: read as it is


def test_processes_beside_distributed_and_a_missing_job_are_one_line(tmp_path):
    with pytest.raises(SystemExit, match=r"^error: --processes 2 starts its own processes; --distributed is for one"):
        cli.main(["reproduce", "--processes", "2", "--distributed", "--run-dir", str(tmp_path / "run")])
    assert not (tmp_path / "run").exists()
    job_keys = ("SLURM_", "JAX_COORDINATOR", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID")  # none: no job to join
    env = {k: v for k, v in os.environ.items() if not k.startswith(job_keys)}
    cmd = [sys.executable, "-m", "bumps_jax", "demo", "--task", "point_goal", "--distributed", "--run-dir",
           str(tmp_path / "run")]  # fmt: skip
    done = subprocess.run(cmd, env={**env, "JAX_PLATFORMS": "cpu"}, capture_output=True, text=True, timeout=300)
    assert done.returncode != 0 and "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines()[-1].startswith("error: --distributed: no multi-process job found (")


def test_a_command_reading_the_default_run_after_a_demo_names_the_demos_run(tmp_path, monkeypatch):
    # `demo` writes runs/demo, `report` reads runs/tiny: it said "run its stages first (e.g.
    # python -m bumps_jax demo)", which never makes runs/tiny.
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit, match=r"^error: no run directory 'runs/tiny': .*then --run-dir runs/demo\)$"):
        cli.main(["report"])
    (tmp_path / "runs" / "demo").mkdir(parents=True)
    with pytest.raises(SystemExit, match=r"or add --run-dir runs/demo \(the demo's run\)$"):
        cli.main(["report"])


@pytest.mark.parametrize("command", ["config", "report"])
def test_processes_on_a_command_without_device_work_is_refused(tmp_path, command):
    # `config --processes 3` launched three processes and left a runs/tiny/ behind.
    with pytest.raises(SystemExit, match=rf"^error: --processes 3: {command} computes nothing on a device"):
        cli.main([command, "--processes", "3", "--run-dir", str(tmp_path / "run")])
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("gif", ["x.png", "."])
def test_a_gif_that_cannot_be_written_is_refused_before_the_kicks(gif):
    # `kick --gif /tmp` selected and kicked for 70 s, then ended in PIL's "unknown file extension".
    with pytest.raises(SystemExit, match=rf"^error: --gif '{gif}': give a file name ending in .gif$"):
        cli.main(["kick", "--target", "12", "--gif", gif])


def test_a_gif_in_a_missing_folder_is_refused_not_made(tmp_path):
    # `kick --gif /nonexistent_dir/k.gif` made the folder /nonexistent_dir and kicked on.
    gif = tmp_path / "nonexistent_dir" / "k.gif"
    with pytest.raises(
        SystemExit, match=r"^error: the GIF's folder '.*nonexistent_dir' does not exist: create it first$"
    ):
        cli.main(["kick", "--target", "12", "--gif", str(gif)])
    assert not gif.parent.exists()
    # `render --out` likewise (its default lies in the run directory; `video --out` is checked so too).
    out = tmp_path / "missing" / "s.png"
    with pytest.raises(SystemExit, match=r"^error: output folder '.*missing' does not exist: create it first$"):
        cli.main(["render", "--run-dir", str(tmp_path), "--out", str(out)])
    assert not out.parent.exists()


def test_the_report_and_the_kicks_own_commands_are_checked_against_the_runs_task(tmp_path):
    # `report --task point_goal` on a cheetah run wrote the cheetah's report and exited 0; `video`
    # on it said "add --task cheetah_vel", which then said the cheetah has no video command.
    runio.write_json(tmp_path / "experts" / "experts.json", {"task": "cheetah_vel"})
    with pytest.raises(SystemExit, match=r"records name 'cheetah_vel'\): add --task cheetah_vel, or give another"):
        cli.main(["report", "--task", "point_goal", "--run-dir", str(tmp_path)])
    with pytest.raises(SystemExit, match=r"^error: --set: report reads a run's records as they are"):
        cli.main(["report", "--run-dir", str(tmp_path), "--set", "env.physics_dt=0.005"])
    with pytest.raises(SystemExit, match=r"'cheetah_vel'\), and cheetah_vel has no video command: give another"):
        cli.main(["video", "--run-dir", str(tmp_path)])


def test_evaluate_on_a_task_without_the_held_out_stage_or_dev_targets_is_one_line(tmp_path):
    """`evaluate --dev` runs the held-out stage's evaluation on the dev targets: a task without
    that stage (point_goal: a KeyError or a TypeError before) or a config without the dev section
    is refused in one line, before the run directory gets a dev/ folder."""
    import types

    import ml_collections

    from bumps_jax import config
    from bumps_jax.pipeline import commands

    run = tmp_path / "run"
    run.mkdir()
    for flag in ("--dev", "--heldout"):
        with pytest.raises(SystemExit, match=r"^error: the point_goal task has no heldout stage; its stages are"):
            cli.main(["evaluate", flag, "--task", "point_goal", "--run-dir", str(run)])
    tree = config.make_config("tiny").to_dict()
    del tree["dev"]
    with pytest.raises(ValueError, match=r"^evaluate --dev: the kick task's config has no dev section"):
        commands.evaluate(ml_collections.ConfigDict(tree), run, types.SimpleNamespace(heldout=False, dev=True))
    assert not (run / "dev").exists() and not (run / "heldout").exists()


def test_the_demos_help_and_an_unfinished_runs_refusal_hold_for_every_task(tmp_path, capsys):
    # `demo --help` said "(a prior from assets/)", true of the kick only; publishing a demo run
    # without its baseline said "rerun the same reproduce to finish it".
    with pytest.raises(SystemExit):
        cli.main(["demo", "--help"])
    assert "the experts, meta and filter stages at CPU size" in " ".join(capsys.readouterr().out.split())
    from bumps_jax.pipeline import commands

    (tmp_path / "experts").mkdir()
    with pytest.raises(ValueError, match=r"has not finished .*; run those stages into it before publishing$"):
        commands.publish(config.make_config("tiny", {"task": "point_goal"}), tmp_path, None)
