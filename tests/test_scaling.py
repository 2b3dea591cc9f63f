"""The scale-out benchmark (benchmarks/scaling.py): its layouts, how a phase's rate is combined,
its argument checks, and a failing measuring process reported in one line."""

import subprocess
import sys

import pytest

from benchmarks import scaling


@pytest.mark.parametrize("layout", scaling.LAYOUTS)
@pytest.mark.parametrize("k", [1, 4])
def test_one_device_and_n_devices_do_the_same_work(layout, k):
    one = scaling.layout_of(layout, 1, 3 * k)
    every = scaling.layout_of(layout, 3, 3 * k)
    assert one == [{"gpu": "0", "devices": 1, "copies": 3 * k}]
    if layout == "distributed":  # one batch of every copy, shared: each of 3 joined processes computes a third
        assert [p["gpu"] for p in every] == ["0", "1", "2"]
        assert all(p["copies"] == 3 * k and p["processes"] == 3 and p["devices"] == 1 for p in every)
        return
    assert sum(p["copies"] for p in one) == sum(p["copies"] for p in every) == 3 * k
    if layout == "processes":  # one GPU visible to each process, k copies each
        assert [p["gpu"] for p in every] == ["0", "1", "2"] and {p["devices"] for p in every} == {1}
    else:  # one process, a mesh over all three
        assert every == [{"gpu": None, "devices": 3, "copies": 3 * k}]


def test_a_phase_counts_its_work_over_the_span_of_all_its_processes():
    parts = [
        {"start": 10.0, "end": 14.0, "amount": 400, "wall_s": 4.0, "compile_s": 30.0, "gpu": "0",
         "provenance": {"device": "d"}},
        {"start": 10.5, "end": 15.0, "amount": 400, "wall_s": 4.5, "compile_s": 31.0, "gpu": "1",
         "provenance": {"device": "d"}},
    ]  # fmt: skip
    out = scaling.combine(parts)
    assert out["amount"] == 800 and out["span_s"] == pytest.approx(5.0)
    assert out["rate"] == pytest.approx(160.0)  # not 400 / 4 + 400 / 4.5: the processes did not start together
    assert out["overlap"] == pytest.approx(3.5)
    assert [p["gpu"] for p in out["processes"]] == ["0", "1"]


def test_each_process_sees_only_its_gpu(monkeypatch):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0,1")
    assert scaling.worker_env("1")["CUDA_VISIBLE_DEVICES"] == "1"
    assert scaling.worker_env(None)["CUDA_VISIBLE_DEVICES"] == "0,1"


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--devices", "1"], "--devices must be at least 2"),
        (["--updates", "0"], "--updates must be a positive integer"),
        (["--copies", "1", "0"], "--copies must be positive integers, got [1, 0]"),
        (["--skip", "experts", "filter"], "--skip leaves nothing to measure"),
        (["--set", "env.impl=bullet"], "env.impl must be one of"),
        (["--layout", "ring"], "invalid choice: 'ring'"),
        (["--workload", "0"], "--workload must be positive integers, got [0]"),
        (["--workload", "1"], "--workload needs a layout sharing one batch"),
        (["--layout", "mesh", "--copies", "2", "--workload", "1"], "--copies and --workload both name the work"),
    ],
)
def test_bad_arguments_stop_before_any_process_starts(argv, message, capsys, tmp_path):
    with pytest.raises(SystemExit):
        scaling.parse_args([*argv, "--out-dir", str(tmp_path)])
    assert message in capsys.readouterr().err


def test_a_failing_process_is_reported_with_its_last_line(tmp_path):
    log = open(tmp_path / "log.0", "w")  # noqa: SIM115
    proc = subprocess.Popen(
        [sys.executable, "-c", "import sys; print('warming up'); sys.exit('error: n_devices must be in [1, 1]')"],
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    proc.wait()
    log.close()
    with pytest.raises(ValueError, match=r"process 0 failed \(exit 1\): error: n_devices must be in \[1, 1\]"):
        scaling.wait_for([(proc, log)], [tmp_path / "ready.0"], tmp_path, timeout=5.0)


def test_a_process_that_never_gets_ready_times_out(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        with pytest.raises(ValueError, match=r"process 0 did not finish within 0 s; its last line: \(no output\)"):
            scaling.wait_for([(proc, None)], [tmp_path / "ready.0"], tmp_path, timeout=0.2)
    finally:
        proc.kill()
        proc.wait()


def test_the_eta_counts_a_fixed_cost_and_a_cost_per_copy():
    # one workload measured: its mean cost for each left
    assert scaling.eta_s([(1, 100.0), (1, 60.0)], [32, 32]) == pytest.approx(160.0)
    # two: 40 s fixed + 5 s a copy (W=1 took 45 s, W=8 took 80 s)
    assert scaling.eta_s([(1, 45.0), (8, 80.0)], [32]) == pytest.approx(40.0 + 5.0 * 32)
    assert scaling.eta_s([(1, 45.0)], []) == 0.0 and scaling.eta_s([], [4]) == 0.0


def _part(work: str, k: int, one: float, two: float) -> dict:
    key = scaling.WORKS[work]
    return {"copies_per_device": k, "workload": 2 * k, key: {"1": one, "2": two},
            key.replace("_per_s", "_speedup"): two / one, "phases": {"1": {}, "2": {}}}  # fmt: skip


def test_the_record_keeps_every_k_and_its_top_level_is_the_largest_measured():
    record = {"devices": 2, "by_copies": []}
    scaling.add_measurement(record, "experts", _part("experts", 1, 100.0, 155.0))
    top = scaling.add_measurement(record, "filter", _part("filter", 1, 10.0, 19.0))
    assert top["experts_speedup"] == pytest.approx(1.55) and top["filter_rollouts_speedup"] == pytest.approx(1.9)
    top = scaling.add_measurement(record, "experts", _part("experts", 4, 300.0, 570.0))
    assert [e["copies_per_device"] for e in record["by_copies"]] == [1, 4]
    assert top["workload"] == 8 and top["experts_env_steps_per_s"] == {"1": 300.0, "2": 570.0}
    assert top["experts_speedup"] == pytest.approx(1.9) and "filter_rollouts_per_s" not in top  # not yet at K = 4
    assert set(record["by_copies"][0]["phases"]) == {"experts", "filter"} and "phases" not in top


def test_the_presets_own_work_is_one_batch_shared_by_every_device(monkeypatch, tmp_path):
    args, _ = scaling.parse_args(["--devices", "4", "--layout", "distributed", "--workload", "1",
                                  "--out-dir", str(tmp_path)])  # fmt: skip
    assert scaling.layout_of(args.layout, 4, 1) == [
        {"gpu": str(i), "devices": 1, "copies": 1, "processes": 4} for i in range(4)
    ]
    phases = []
    monkeypatch.setattr(scaling, "run_phase", lambda a, work, m, w, folder: phases.append((m, w)) or {"rate": 10.0 * m})
    out = scaling.measure(args, "experts", 1, tmp_path, lambda line: None)
    assert phases == [(1, 1), (4, 1)]  # one copy on one GPU, the same one copy over four
    assert out["workload"] == 1 and out["copies_per_device"] == 0.25 and out["experts_env_steps_speedup"] == 4.0
