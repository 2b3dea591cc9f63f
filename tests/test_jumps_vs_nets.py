"""experiments/jumps_vs_nets: the committed development arms read back, the family scheme's left
out, and the rank correlation it prints."""

import json

import numpy as np
import pytest

from experiments import jumps_vs_nets as jv

KEEP_TASK = "start_long_spread_neighbour_leash_1_restarts_4_keep_task_polish_generations_20_seed_102_paper_budget"


def test_every_committed_arm_with_both_records_is_read_and_the_family_scheme_left_out():
    found = {arm.name: arm for arm in jv.arms()}
    tables = {p.name.removesuffix("_table1_h100.json") for p in jv.DEV_RECORDS.glob("*_table1_h100.json")}
    assert {"family", "family12"} <= tables and not {"family", "family12"} & set(found)
    assert set(found) == {
        n for n in tables - {"family", "family12"} if (jv.DEV_RECORDS / f"{n}_experts_h100.json").exists()
    }
    arm = found[KEEP_TASK]
    experts = json.loads((jv.DEV_RECORDS / f"{KEEP_TASK}_experts_h100.json").read_text())
    table1 = json.loads((jv.DEV_RECORDS / f"{KEEP_TASK}_table1_h100.json").read_text())
    assert arm.paper_budget and arm.jump == experts["starting_kicks_smoothness"]["jump"]
    assert arm.excess_m["meta_4x256"] == pytest.approx(table1["rows"]["meta_4x256"]["error_mean_m"] - arm.experts_m)


def test_the_scheme_is_the_last_one_the_command_set():
    assert jv.scheme("x --set experts.tune.scheme=per_task a=1 experts.tune.scheme=family") == "family"
    assert jv.scheme("x --set experts.tune.scheme=per_task") == "per_task"
    assert jv.scheme("python -m bumps_jax train-experts --preset paper") == "per_task"


def test_spearman_ranks():
    x = [0.6, 1.3, 2.9, 8.7]
    assert jv.spearman(x, [0.1, 0.2, 0.3, 1.0]) == pytest.approx(1.0)  # any increasing y
    assert jv.spearman(x, [0.9, 0.5, 0.4, 0.0]) == pytest.approx(-1.0)
    # one swap among four: 1 - 6 * 2 / (4 * 15) = 0.8
    assert jv.spearman(x, [0.1, 0.3, 0.2, 1.0]) == pytest.approx(0.8)
    assert np.isfinite(jv.spearman(x, x))


def test_too_few_arms_is_one_line(capsys):
    with pytest.raises(SystemExit) as stop:
        jv.main(["--device", "a100"])
    assert stop.value.code == 2
    assert "0 arm(s) with experts and table1 records of device 'a100'" in capsys.readouterr().err
