"""Priors grouped by the processes that made them, each tuned again (experiments/prior_draws.py),
on synthetic records."""

import json

import pytest

from bumps_jax import runio
from experiments import prior_draws


def write_pair(folder, processes, costs, error=0.25, device="gpu", **tuning_extra):
    """A prior's record and a whole-batch tuning record from it; the tuning's path."""
    prior = folder / "prior" / "kick_prior.json"
    runio.write_json(prior, {"mean_error_m": error, "n_processes": processes, "device": device, "date": "d"})
    tuning = {"prior": str(prior), "seeds": {"0": {"whole": {"runs_mean": costs}}}, "env": {"impl": "warp"},
              "settings": {"generations": 60}, "preset": "paper", "device": "gpu", **tuning_extra}  # fmt: skip
    runio.write_json(folder / "tuning.json", tuning)
    return folder / "tuning.json"


def test_priors_are_grouped_by_their_processes_each_one_sample(tmp_path):
    paths = [write_pair(tmp_path / f"p{i}", p, c) for i, (p, c) in
             enumerate([(1, [0.3, 0.4]), (1, [0.5, 0.5]), (2, [0.7, 0.8]), (2, [0.6, 0.6])])]  # fmt: skip
    rows = [prior_draws.prior_row(str(p)) for p in paths]
    assert [r["prior_processes"] for r in rows] == [1, 1, 2, 2]
    assert rows[0]["tuning_mean"] == pytest.approx(0.35) and rows[0]["tuning_fresh_costs"] == [0.3, 0.4]
    out = prior_draws.compare(rows)
    assert out["priors"] == {"one_process": 2, "several_processes": 2}
    assert out["tuning_mean"]["mean_one"] == pytest.approx(0.425)
    assert out["tuning_mean"]["mean_several"] == pytest.approx(0.675)
    assert out["tuning_mean"]["permutation_p"] == pytest.approx(2 / 6)  # the two extreme splits of 4 into 2 + 2
    record = tmp_path / "out.json"
    prior_draws.main([*map(str, paths), "--out", str(record)])
    assert json.loads(record.read_text())["tuning_mean"]["permutation_p"] == pytest.approx(2 / 6)


def test_the_tunings_are_also_grouped_by_the_gpu_each_prior_was_made_on(tmp_path):
    made = [(1, [0.3], "A"), (1, [0.4], "B"), (2, [0.8], "A"), (2, [0.5], "A"), (1, [0.2], "B")]
    rows = [prior_draws.prior_row(str(write_pair(tmp_path / f"p{i}", n, c, device=d)))
            for i, (n, c, d) in enumerate(made)]  # fmt: skip
    out = prior_draws.by_device(rows)["by_prior_device"]
    assert out["devices"]["A"]["tuning_mean"] == pytest.approx([0.3, 0.8, 0.5])
    assert out["devices"]["B"]["mean"] == pytest.approx(0.3)
    # A's mean 0.533 against B's 0.3 (0.233 apart); of the 10 splits of the five into 3 + 2, four lie
    # as far apart or further: B = {0.4, 0.2} itself, {0.3, 0.2} (0.317), {0.8, 0.5} (0.35), {0.8, 0.4} (0.267)
    assert out["permutation_p"] == pytest.approx(4 / 10)
    three = prior_draws.by_device([*rows, {**rows[0], "prior_device": "C"}])["by_prior_device"]
    assert three["permutation_p"] is None and set(three["devices"]) == {"A", "B", "C"}


def test_a_prior_kept_elsewhere_is_named_after_an_equals_sign(tmp_path):
    tuning = write_pair(tmp_path / "a", 1, [0.4])
    moved = tmp_path / "kept.json"
    runio.write_json(moved, {"mean_error_m": 0.3, "n_processes": 4})
    row = prior_draws.prior_row(f"{tuning}={moved}")
    assert row["prior_record"] == str(moved) and row["prior_processes"] == 4 and row["prior_error_m"] == 0.3


def test_records_that_do_not_fit_are_one_line(tmp_path):
    both = write_pair(tmp_path / "a", 1, [0.4])
    runio.write_json(tmp_path / "b.json", {"prior": "x", "seeds": {"0": {"parts": {}}}})
    with pytest.raises(ValueError, match=r"b\.json: not one seed's whole-batch tuning from a prior"):
        prior_draws.prior_row(str(tmp_path / "b.json"))
    other = write_pair(tmp_path / "c", 2, [0.5], settings={"generations": 3})
    with pytest.raises(SystemExit, match=r"tuned under another settings than"):
        prior_draws.main([str(both), str(other), "--out", str(tmp_path / "out.json")])
