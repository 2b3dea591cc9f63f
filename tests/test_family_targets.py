"""The smooth-family targets (experiments/family_targets.py) read from committed development records:
the verdicts decisions.md states for them, and missing or bad records."""

import json

import pytest

from experiments import family_targets

REPS_32 = "start_long_spread_neighbour_leash_1_repetitions_32_env.warp_contacts_282624_paper_budget"


def _verdicts(capsys, *argv) -> tuple[int, dict[str, str]]:
    """(exit status, target name -> its verdict word) of one call."""
    status = family_targets.main(list(argv))
    lines = capsys.readouterr().out.splitlines()
    rows = {line[:52].strip(): line.split()[-1] for line in lines if line.startswith("  ")}
    return status, rows


def test_the_arm_decisions_md_says_met_every_target_meets_every_target(capsys):
    status, rows = _verdicts(capsys, "--arm", REPS_32)  # seed 101: experts 0.329 m, filtered 0.327-0.341 m
    assert status == 0 and len(rows) == 12 and set(rows.values()) == {"met"}


def test_the_second_seed_misses_at_the_experts_and_one_task_above_2_m(capsys):
    status, rows = _verdicts(capsys, "--arm", REPS_32 + "_seed_102")  # experts 0.429 m; 2.21 m at 16.65 m
    assert status == 1
    assert rows["experts: error (m)"] == "MISSED"
    assert rows["meta_4x256 unfiltered: worst task (m)"] == "MISSED"
    assert rows["meta_11x128 unfiltered: worst task (m)"] == "met"
    assert rows["high_sample_rate_4x256 minus filtered_4x256 (m)"] == "met"


def test_an_arm_without_its_filtering_record_leaves_those_targets_unmeasured(capsys, tmp_path):
    run = tmp_path / "run"
    arm = family_targets.DEV_RECORDS / REPS_32
    for stage, name in (("experts", "experts"), ("meta", "table1")):
        (run / stage).mkdir(parents=True)
        (run / stage / f"{name}.json").write_text((arm.parent / f"{arm.name}_{name}_h100.json").read_text())
    status, rows = _verdicts(capsys, "--run-dir", str(run))
    assert status == 2  # nothing missed, but not everything measured
    assert rows["filtered_ensemble: error (m)"] == "-" and rows["experts: error (m)"] == "met"
    experts = json.loads((run / "experts" / "experts.json").read_text())
    (run / "experts" / "experts.json").write_text(json.dumps({**experts, "error_mean_m": 0.36}))
    assert _verdicts(capsys, "--run-dir", str(run))[0] == 1  # a missed target outranks an unmeasured one


def test_no_records_or_a_bad_one_is_one_line(capsys, tmp_path):
    assert family_targets.main(["--run-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: none of the records exists") and err.count("\n") == 1
    (tmp_path / "meta").mkdir()
    (tmp_path / "meta" / "table1.json").write_text("{not json")
    assert family_targets.main(["--run-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "table1.json: cannot read it as JSON" in err and err.count("\n") == 1


def test_the_published_records_are_named_as_the_meta_test_evaluation(capsys):
    family_targets.main(["--published"])
    assert capsys.readouterr().out.startswith("evaluation: the meta-test tasks and seed (seed 1, 110 tasks")


@pytest.mark.parametrize("missing", ["--arm", "--device"])
def test_the_command_line_needs_one_source(missing):
    with pytest.raises(SystemExit):
        family_targets.main([missing])
