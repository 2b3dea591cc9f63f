"""The repeatability check's comparison (experiments/repeatability.py) on synthetic distances (the
replays themselves run in the experiment)."""

import numpy as np
import pytest

from experiments import repeatability


def test_equal_calls_are_identical_and_a_moved_ball_is_counted():
    first = np.array([[10.0, 12.0], [14.0, 16.0]], np.float32)
    assert repeatability.differences(first, first.copy()) == {
        "identical": True, "max_abs": 0.0, "median_abs": 0.0, "episodes": 4, "over_tolerance": 0,
        "tolerance": repeatability.TOLERANCE_M, "differing": 0,
    }  # fmt: skip
    moved = first.copy()
    moved[1, 0] += 0.5  # one ball rests half a metre away
    moved[0, 1] += 1e-5  # one by rounding
    out = repeatability.differences(first, moved)
    assert not out["identical"] and out["over_tolerance"] == 1 and out["max_abs"] == pytest.approx(0.5)


@pytest.mark.parametrize("option, value, least", [("--calls", "1", 2), ("--reps", "0", 1), ("--targets", "0", 1)])
def test_too_few_calls_reps_or_targets_are_one_line(option, value, least, capsys):
    with pytest.raises(SystemExit):
        repeatability.parse_args([option, value, "--out", "x.json"])
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.endswith(f"error: {option} must be at least {least}, got {value}")


def test_a_record_of_another_batch_is_refused_before_any_replay(tmp_path):
    from bumps_jax import runio

    other = tmp_path / "other.json"
    runio.write_json(other, {"targets_m": [8.0, 12.0], "reps": 4, "distance_m": [[8.0] * 4, [12.0] * 4]})
    with pytest.raises(SystemExit, match=r"holds another batch \(its targets or --reps differ from these\)$"):
        repeatability.main(["--targets", "3", "--reps", "4", "--against", str(other), "--out", str(tmp_path / "o")])
