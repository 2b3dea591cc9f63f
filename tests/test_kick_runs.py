"""The kick's runs grouped by their processes (experiments/kick_runs.py), on synthetic records."""

import pytest

from bumps_jax import runio
from experiments import kick_runs


def experts_record(path, processes, costs, error, **extra):
    record = {"task": "kick", "n_processes": processes, "error_mean_m": error, "env": {"impl": "warp"},
              **({} if costs is None else {"starting_kicks_tuning_runs": {"fresh_costs": costs}}), **extra}  # fmt: skip
    runio.write_json(path / "experts.json", record)
    return path / "experts.json"


def test_runs_are_grouped_by_processes_each_run_one_sample(tmp_path):
    runs = [(1, 0.3, 0.25), (1, 0.4, 0.26), (4, 0.7, 0.35), (2, 0.6, 0.36)]  # processes, cost, experts' error
    paths = [experts_record(tmp_path / f"r{i}", p, [c, c + 0.02], e) for i, (p, c, e) in enumerate(runs)]
    runio.write_json(tmp_path / "r0" / "kick_prior.json", {"mean_error_m": 0.28})
    rows = [kick_runs.run_row(p) for p in paths]
    assert rows[0]["prior_error_m"] == 0.28 and rows[1]["prior_error_m"] is None
    assert rows[0]["tuning_mean"] == pytest.approx(0.31) and rows[0]["tuning_spread"] == pytest.approx(0.02)
    out = kick_runs.groups(rows)
    assert out["runs"] == {"one_process": 2, "several_processes": 2}
    assert out["tuning_mean"]["one_process"] == pytest.approx([0.31, 0.41])
    assert out["experts_error_m"]["mean_several"] == pytest.approx(0.355)
    assert out["experts_error_m"]["permutation_p"] == pytest.approx(2 / 6)  # the two extreme splits of 4 into 2 + 2
    assert out["tuning_within_vs_between"]["runs_range"] == pytest.approx([0.31, 0.71])


def test_a_record_without_the_tuning_or_of_another_env_is_one_line(tmp_path):
    bare = tmp_path / "bare"
    runio.write_json(bare / "experts.json", {"task": "cheetah_vel", "error_mean_m": 0.1})
    with pytest.raises(ValueError, match=r"not a kick experts record with its starting kicks' tuning$"):
        kick_runs.run_row(bare / "experts.json")
    untuned = experts_record(tmp_path / "untuned", 1, None, 0.4)  # a tiny run: one tuning, no restarts' costs
    with pytest.raises(ValueError, match=r"not a kick experts record with its starting kicks' tuning$"):
        kick_runs.run_row(untuned)
    row = kick_runs.run_row(untuned, tuned=False)
    with pytest.raises(ValueError, match=r"not a kick experts record$"):  # nothing asked of a tuning it may lack
        kick_runs.run_row(bare / "experts.json", tuned=False)
    assert row["experts_error_m"] == 0.4 and row["tuning_mean"] is None and row["tuning_spread"] is None
    one = experts_record(tmp_path / "a", 1, [0.3], 0.2)
    other = experts_record(tmp_path / "b", 2, [0.4], 0.3, env={"impl": "jax"})
    with pytest.raises(SystemExit, match=r"ran another env than .* \(keys \['impl'\]\)$"):
        kick_runs.main([str(one), str(other), "--out", str(tmp_path / "out.json")])


def test_the_experts_are_compared_beside_the_line_through_the_tunings():
    def rows(points):  # (processes, tuning mean, experts' error)
        return [{"processes": p, "tuning_mean": t, "experts_error_m": e} for p, t, e in points]

    # Every run on one line: whatever the groups' raw errors, nothing is left beside it.
    on_line = rows([(1, 0.3, 0.19), (1, 0.4, 0.22), (4, 0.6, 0.28), (2, 0.7, 0.31)])
    g = kick_runs.given_tuning(on_line[:2], on_line[2:])
    assert g["slope_m_per_cost"] == pytest.approx(0.3) and g["intercept_m"] == pytest.approx(0.1)
    assert g["residual_one_process"] + g["residual_several_processes"] == pytest.approx([0.0] * 4, abs=1e-12)
    assert g["permutation_p"] == 1.0
    # The several-process runs 0.05 m above the one-process runs at the same tunings.
    apart = rows([(1, 0.3, 0.19), (1, 0.5, 0.25), (2, 0.3, 0.24), (2, 0.5, 0.30)])
    g = kick_runs.given_tuning(apart[:2], apart[2:])
    assert g["mean_residual_several"] - g["mean_residual_one"] == pytest.approx(0.05)
    assert kick_runs.given_tuning(apart[:1], apart[1:]) is None
