"""Sharding over devices and processes changes where work runs, not what it computes: tiny
experts (stopped and resumed from a checkpoint) and a filtering selection split over 2 processes
of 2 (host) devices each (JAX's multi-process runtime on localhost) equal those of one process on
one device (on PointGoal: tests/sharded_run.py says why)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
import sharded_run

from bumps_jax import launch
from bumps_jax.algo import sharding
from bumps_jax.pipeline import expert_programs
from bumps_jax.pipeline.stages import experts

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def sharded_vs_single(tmp_path_factory):
    devices = f"--xla_force_host_platform_device_count={sharded_run.N_DEVICES}"
    run_env = dict(os.environ, XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} {devices}".strip(), JAX_PLATFORMS="cpu")
    run_env["PYTHONPATH"] = os.pathsep.join([str(ROOT), run_env.get("PYTHONPATH", "")])
    run_dir, port = tmp_path_factory.mktemp("processes"), launch.free_port()
    logs = tmp_path_factory.mktemp("logs")
    command = [sys.executable, str(ROOT / "tests" / "sharded_run.py"), str(run_dir)]
    procs = []
    for i in range(sharded_run.PROCESSES):
        # each its own hash seed: nothing the processes agree on may follow Python's hash order;
        # output to files, read once they end (this process works meanwhile, so pipes could fill)
        env = {**launch.process_env(i, sharded_run.PROCESSES, port, None), **run_env, "PYTHONHASHSEED": str(1 + i)}
        with (logs / f"{i}.out").open("w") as out, (logs / f"{i}.err").open("w") as err:
            procs.append(subprocess.Popen(command, stdout=out, stderr=err, cwd=ROOT, env=env))
    try:
        # The single-device side runs here while the processes run: the same experts uninterrupted,
        # the selection in one call of 8 episodes (the split one's 2 on each device of each process).
        single, one_device = _single_device(tmp_path_factory)
        for p in procs:
            p.wait(timeout=900)
    finally:
        for p in procs:
            if p.poll() is None:  # the single side failed: no process is left behind
                p.kill()
    outs = [((logs / f"{i}.out").read_text(), (logs / f"{i}.err").read_text()) for i in range(len(procs))]
    for p, (_, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err[-4000:]
    sharded = json.loads(outs[0][0].strip().splitlines()[-1])
    assert not any(line.startswith("{") for line in outs[1][0].splitlines()), "only the first process reports"
    # Both sides trained a family: candidates, a choice (on both sides the same one), the chosen alone.
    choices = [
        json.loads((d / "experts" / "centre" / "choice.json").read_text())["chosen"] for d in (one_device, run_dir)
    ]
    assert choices[0] == choices[1] and (run_dir / "experts" / "centre_chosen" / "progress.csv").exists()
    return single, sharded


def _single_device(tmp_path_factory) -> tuple[dict, Path]:
    """What one process on one device makes of sharded_run's work, and its run directory."""
    cfg = sharded_run.experts_config()
    env = sharded_run.make_env(cfg)
    programs = expert_programs.compile_programs(cfg, env)
    one_device = tmp_path_factory.mktemp("one_device")
    out = experts.train(cfg, one_device, programs, say=lambda *a, **k: None)
    leaves = jax.tree.leaves(expert_programs.expert_params(out["state"]))
    grid, params = sharded_run.contextual_grid(env)
    return {
        "experts": {"params": [np.asarray(x) for x in leaves], "finished": out["finished"]},
        "filter": sharded_run.filter_synthetic(env, grid, params, 1),
        "nets": sharded_run.train_nets(tmp_path_factory.mktemp("nets")),
    }, one_device


def test_sharded_experts_equal_single_device_experts(sharded_vs_single):
    single, sharded = sharded_vs_single
    assert single["experts"]["finished"] and sharded["experts"]["finished"]
    a, b = single["experts"]["params"], sharded["experts"]["params"]
    assert len(a) == len(b) and len(a) > 0
    for x, y in zip(a, b, strict=True):
        x, y = np.asarray(x), np.asarray(y)
        assert x.shape == y.shape and x.shape[0] == 3  # the padded fourth task is dropped
        # Not bit-identical: XLA picks its CPU kernels per batch shape (3 tasks vs 1 per device);
        # measured 1e-6 at most (on a normaliser's variance of 14), most leaves within 3e-8. Each
        # expert starts from its own random init, so a wrong slice or a mixed-up task would
        # differ by 1e-2 or more.
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6)


def test_sharded_filtering_makes_the_same_choices(sharded_vs_single):
    single, sharded = sharded_vs_single
    assert single["filter"]["chosen"] == sharded["filter"]["chosen"]
    # Not bit-identical (the batch shape changes XLA's kernels), but nothing collides: the final
    # positions and scores agree within 3e-8 m (measured). A wrong slice moves a whole block of
    # episodes to another rollout's place: the candidate goals lie 0.3 m or more apart.
    np.testing.assert_allclose(single["filter"]["distance"], sharded["filter"]["distance"], atol=1e-5)
    np.testing.assert_allclose(single["filter"]["scores"], sharded["filter"]["scores"], atol=1e-5)


def test_nets_split_over_processes_train_as_one_process_trains_them(sharded_vs_single):
    # Each process trained one net (and resumed it) and took the other's from its owner: the
    # same params as both stacked in one process, to the rounding of a net trained beside another.
    single, sharded = sharded_vs_single
    assert sharded["nets_trained_here"] == ["wide"]  # "deep" came from the second process
    for name in sharded_run.NETS:
        a, b = single["nets"][name], sharded["nets"][name]
        assert len(a["params"]) == len(b["params"]) > 0
        for x, y in zip(a["params"], b["params"], strict=True):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-4, atol=1e-5)
        # every chunk's row written once, by the first process, for the net the other trained too
        assert len(a["rows"]) == len(b["rows"]) == 2
        assert [r.split(",")[:2] for r in a["rows"]] == [r.split(",")[:2] for r in b["rows"]]


def test_each_device_steps_only_its_own_episodes(sharded_vs_single):
    # A plain jit over the mesh ran Warp's physics on the whole batch on every device (gathered
    # around each physics call): 8 episodes through a contact pool for 4 overflowed, all 8.
    _, sharded = sharded_vs_single
    pool = sharded["pool"]
    assert len(pool["overflow"]) == sharded_run.PROCESSES * sharded_run.N_DEVICES * sharded_run.POOL_EPISODES
    assert not any(pool["overflow"]) and pool["finite"]
    assert not pool["gathers"]


def test_padding_repeats_the_last_item_and_unpad_drops_it():
    mesh = sharding.device_mesh(1)
    assert sharding.padded_size(23, mesh) == 23
    x = {"a": np.arange(3.0), "b": np.arange(6.0).reshape(3, 2)}
    grown = sharding.pad(x, 5)
    np.testing.assert_array_equal(grown["a"], [0, 1, 2, 2, 2])
    np.testing.assert_array_equal(grown["b"][-1], [4, 5])
    np.testing.assert_array_equal(sharding.unpad(grown, 3)["b"], x["b"])


def test_bad_device_counts_are_named():
    with pytest.raises(ValueError, match="n_devices"):
        sharding.device_mesh(0)
    with pytest.raises(ValueError, match="n_devices"):
        sharding.device_mesh(10_000)


def test_warp_on_gpus_runs_on_one_gpu_a_process_and_refuses_more(monkeypatch):
    # Warp's physics crashes a process that steps episodes on a second GPU (mujoco-mjx 3.17):
    # several GPUs are several processes, each splitting batches with the others.
    class Gpu:
        platform = "gpu"

    monkeypatch.setattr(jax, "local_devices", lambda: [Gpu(), Gpu()])
    monkeypatch.setattr(sharding, "Mesh", lambda devices, axes: np.asarray(devices))  # the devices it would span
    assert len(sharding.device_mesh(impl="warp")) == 1
    assert len(sharding.device_mesh(impl="jax")) == 2 and len(sharding.device_mesh()) == 2
    assert len(sharding.device_mesh(1, impl="warp")) == 1
    with pytest.raises(ValueError, match="n_devices 2 with env.impl 'warp'.*--processes"):
        sharding.device_mesh(2, impl="warp")
    monkeypatch.setattr(jax, "process_count", lambda: 4)  # --processes 4: one GPU each
    mesh = sharding.device_mesh(impl="warp")
    assert sharding.ways(mesh) == 4 and sharding.padded_size(37, mesh) == 40


def test_each_process_takes_its_own_rows(monkeypatch):
    monkeypatch.setattr(jax, "process_count", lambda: 2)
    monkeypatch.setattr(jax, "process_index", lambda: 1)
    rows = sharding.own_rows({"a": np.arange(8.0), "b": np.arange(16.0).reshape(2, 8)})
    np.testing.assert_array_equal(rows["a"], [4, 5, 6, 7])
    np.testing.assert_array_equal(
        sharding.own_rows(np.arange(16.0).reshape(2, 8), axis=1), [[4, 5, 6, 7], [12, 13, 14, 15]]
    )
    with pytest.raises(ValueError, match="a batch of 7 does not split over 2 processes"):
        sharding.own_rows(np.arange(7.0))


GATHER = """
import sys, numpy as np, jax
from bumps_jax.algo import sharding
sharding.initialize_distributed()
i = jax.process_index()
tree = {"f": np.full((2, 3), i, np.float32), "u": np.full((2,), 10 + i, np.uint32), "b": np.array([i == 0, True]),
        "n": np.full((2, 2), -i, np.int32)}
print(repr({k: v.tolist() for k, v in sorted(sharding.gather(tree).items())}))
"""


SLURM = """
import jax, numpy as np
from bumps_jax.algo import sharding
sharding.initialize_distributed()
print(jax.process_count(), jax.process_index(), sharding.gather({"i": np.array([jax.process_index()])})["i"].tolist())
"""


CHECKPOINT = """
import json, os, sys
from pathlib import Path
import jax, jax.numpy as jnp, numpy as np
import orbax.checkpoint as ocp
from brax.training.types import UInt64
from bumps_jax import resumable
from bumps_jax.algo import sharding
if "JAX_NUM_PROCESSES" in os.environ:
    sharding.initialize_distributed()
state = {"w": jnp.arange(12.0).reshape(3, 4), "count": UInt64(hi=1, lo=7)}
manager = resumable.checkpoint_manager(Path(sys.argv[2]), keep=2)
if sys.argv[1] == "save":
    manager.save(3, args=ocp.args.StandardSave(state))
else:
    said = []
    step, got = resumable.restore_latest(manager, ocp.args.StandardRestore(jax.eval_shape(lambda: state)), said.append)
    print(json.dumps({"step": step, "w": np.asarray(got["w"]).tolist(), "count": int(got["count"]), "said": said}))
manager.close()
"""


def _checkpoint_job(mode: str, directory: Path, processes: int) -> list[str]:
    """CHECKPOINT run as `processes` processes of one job: each one's last line."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT)}
    port = launch.free_port()
    procs = [
        subprocess.Popen([sys.executable, "-c", CHECKPOINT, mode, str(directory)],
                         env={**launch.process_env(i, processes, port, None), **env} if processes > 1 else env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for i in range(processes)
    ]  # fmt: skip
    outs = [p.communicate(timeout=120) for p in procs]
    assert all(p.returncode == 0 for p in procs), "".join(err[-2000:] for _, err in outs)
    return [out.strip().splitlines()[-1] if out.strip() else "" for out, _ in outs]


@pytest.mark.parametrize(("saved_by", "resumed_by"), [(1, 2), (2, 1)])
def test_a_checkpoint_resumes_whatever_the_process_count(tmp_path, saved_by, resumed_by):
    # A run stopped on one GPU and resumed with --processes 4 (or the other way): a one-process
    # checkpoint names a device only process 0 holds; the others read it all the same, and
    # nothing valid is set aside as corrupt.
    _checkpoint_job("save", tmp_path, saved_by)
    restored = [json.loads(line) for line in _checkpoint_job("restore", tmp_path, resumed_by)]
    for got in restored:
        assert got == {"step": 3, "w": np.arange(12.0).reshape(3, 4).tolist(), "count": (1 << 32) + 7, "said": []}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["3"]


def test_processes_started_as_srun_starts_them_join_one_job():
    # srun sets these for every task; JAX's SLURM detection derives the coordinator (the first
    # node, a port from the job id) from them: no JAX_* variable is set.
    job = next(j for j in range(4096) if _port_free(61440 + j))
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_COORDINATOR", "JAX_NUM", "JAX_PROCESS"))}
    env.update(JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT), SLURM_JOB_ID=str(job), SLURM_STEP_NODELIST="localhost",
               SLURM_NTASKS="2", SLURM_STEP_NUM_NODES="1")  # fmt: skip
    procs = [
        subprocess.Popen([sys.executable, "-c", SLURM], env={**env, "SLURM_PROCID": str(i), "SLURM_LOCALID": str(i)},
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for i in range(2)
    ]  # fmt: skip
    outs = [p.communicate(timeout=120) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs[0][1][-2000:] + outs[1][1][-2000:]
    assert [out.strip().splitlines()[-1] for out, _ in outs] == ["2 0 [0, 1]", "2 1 [0, 1]"]


def _port_free(port: int) -> bool:
    import socket

    with socket.socket() as s:
        try:
            s.bind(("localhost", port))
        except OSError:
            return False
    return True


def test_gather_joins_every_process_rows_in_order():
    # Two processes whose hash seeds order a set of dtypes differently (seeds 1 and 2 do): the
    # per-dtype collectives must still pair up.
    port = launch.free_port()
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT)}
    procs = [
        subprocess.Popen([sys.executable, "-c", GATHER], env={**launch.process_env(i, 2, port, None), **env,
                         "PYTHONHASHSEED": str(1 + i)}, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for i in range(2)
    ]  # fmt: skip
    outs = [p.communicate(timeout=120) for p in procs]  # unpaired collectives hang
    assert all(p.returncode == 0 for p in procs), outs[0][1][-2000:] + outs[1][1][-2000:]
    first, second = (eval(out.strip().splitlines()[-1]) for out, _ in outs)  # noqa: S307 (our own repr)
    assert (
        first
        == second
        == {
            "b": [True, True, False, True],
            "f": [[0, 0, 0], [0, 0, 0], [1, 1, 1], [1, 1, 1]],
            "n": [[0, 0], [0, 0], [-1, -1], [-1, -1]],
            "u": [10, 10, 11, 11],
        }
    )


def test_a_job_of_one_process_starts_no_coordinator(monkeypatch):
    calls = []
    monkeypatch.setattr(jax.distributed, "initialize", lambda **kw: calls.append(kw))
    monkeypatch.setenv("JAX_NUM_PROCESSES", "1")
    monkeypatch.setenv("JAX_PROCESS_ID", "0")
    sharding.initialize_distributed()
    assert calls == []  # one process: nothing to join
    monkeypatch.setenv("JAX_NUM_PROCESSES", "2")
    sharding.initialize_distributed()
    assert calls == [{"num_processes": 2, "process_id": 0}]
