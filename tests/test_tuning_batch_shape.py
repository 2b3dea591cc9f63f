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


def test_a_published_prior_record_gives_its_anchors_in_the_kicks_order(tmp_path):
    from bumps_jax import runio
    from bumps_jax.tasks.kick import keyframes

    names = keyframes.ANCHORS
    path = tmp_path / "kick_prior.json"
    runio.write_json(path, {"anchors": {a: [float(i)] * 14 for i, a in enumerate(reversed(names))}, "sweep": [{}]})
    prior = tuning_batch_shape.read_prior(path)
    assert [row[0] for row in prior["anchors"]] == [float(len(names) - 1 - i) for i in range(len(names))]
    assert tuning_batch_shape.read_prior(None) is None  # the shipped prior
    runio.write_json(path, {"anchors": {"main": [0.0] * 14}, "sweep": [{}]})
    with pytest.raises(ValueError, match=r"anchors \['main'\], expected"):
        tuning_batch_shape.read_prior(path)
    runio.write_json(path, {"anchors": [[0.0] * 14]})
    with pytest.raises(ValueError, match=r"not a kick prior record \(it needs anchors and sweep\)$"):
        tuning_batch_shape.read_prior(path)
