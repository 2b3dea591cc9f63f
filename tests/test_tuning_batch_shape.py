"""The batch-shape comparison (experiments/tuning_batch_shape.py) on synthetic rows: the per-seed
differences and their sign-flip p-value (the tuning itself runs only in the experiment)."""

import pytest

from experiments import tuning_batch_shape


def row(whole, parts):
    arm = lambda cost: {"runs_mean": [cost, cost + 0.1], "tuned_mean": cost, "runs_kept": [1], "seconds": 1.0}  # noqa: E731
    return {"whole": arm(whole), "parts": arm(parts)}


def test_parts_worse_in_every_seed_gives_the_least_p_there_is():
    out = tuning_batch_shape.compare({"0": row(0.4, 0.7), "1": row(0.5, 0.6), "2": row(0.3, 0.5)})
    t = out["tuned_mean"]
    assert t["difference_per_seed"] == pytest.approx([0.3, 0.1, 0.2])
    assert t["parts_higher"] == 3 and t["difference_mean"] == pytest.approx(0.2)
    assert t["sign_flip_p"] == pytest.approx(2 / 8)  # all + or all -: 2 of the 8 sign patterns
    assert out["runs_mean"]["whole"] == pytest.approx([0.45, 0.55, 0.35])


def test_equal_arms_give_p_one():
    out = tuning_batch_shape.compare({"0": row(0.4, 0.4), "1": row(0.5, 0.5)})
    assert out["tuned_mean"]["sign_flip_p"] == 1.0 and out["tuned_mean"]["parts_higher"] == 0
