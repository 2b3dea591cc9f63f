"""The tuning-split comparison (experiments/tuning_split.py): the record built from three arms'
payloads, on synthetic arrays (the tuning itself runs only in the experiment)."""

import numpy as np
import pytest

from experiments import tuning_split


def payload(shift=0.0, part_calls=False):
    gens = [{"best": [1.0 + shift, 2.0], "mean": [3.0, 4.0], "valid": [1.0, 0.5], "overflow": [0.0, 0.0]}] * 2
    out = {"starts": [[0.5, 0.5]], "generations": gens, "final_mean": [[[1.0 + shift, 2.0]]], "best_cost": [[1.0, 2.0]],
           "fresh_costs": [[[1.0, 2.0 + shift]]], "params": [[1.0, 2.0]], "runs_kept": [1, 0],
           "tuned_cost": [1.0, 2.0], "start_cost": [1.5, 2.5], "one_generation": [], "episodes": None}  # fmt: skip
    if part_calls:
        out["one_generation"] = [{"whole_call": gens[0], "carry_max_abs": 0.0}] * 2
        out["episodes"] = {"whole": {"cost": [0.0, 1.0, 2.0, 3.0], "distance": [1.0, 2.0, 3.0, 4.0]},
                           "parts": {"cost": [0.0, 1.0, 2.5, 3.0001], "distance": [1.0, 2.0, 3.5, 4.0]}}  # fmt: skip
    return out


def test_differences_are_absolute_relative_and_bitwise():
    assert tuning_split.differences([1.0, 2.0], [1.0, 2.0]) == {"max_abs": 0.0, "max_rel": 0.0, "identical": True}
    d = tuning_split.differences([2.0, 4.0], [2.0, 5.0])
    assert d["max_abs"] == 1.0 and d["max_rel"] == pytest.approx(0.25) and not d["identical"]
    assert tuning_split.differences([0.0], [1.0])["max_rel"] is None  # no relative difference from 0
    with pytest.raises(ValueError, match="shapes"):
        tuning_split.differences([1.0], [1.0, 2.0])


def test_the_record_compares_the_split_with_its_parts_and_the_whole_batch():
    record = tuning_split.compare(payload(), payload(part_calls=True), payload(shift=0.5))
    assert record["split_equals_part_calls"]
    gen = record["per_generation"][0]
    assert gen["split_vs_part_calls"]["best"]["max_abs"] == 0.0
    assert gen["split_vs_whole_run"]["best"]["max_abs"] == 0.5
    assert record["final_mean"]["split_vs_whole_run"]["max_abs"] == 0.5
    assert record["fresh_costs"]["split_vs_whole_run"]["max_abs"] == 0.5
    episodes = record["gen1_episodes"]["cost"]
    assert (episodes["episodes"], episodes["over_tolerance"], episodes["differing"]) == (4, 1, 2)
    assert episodes["max_abs"] == pytest.approx(0.5)
    assert record["gen1_episodes"]["distance_m"]["max_abs"] == pytest.approx(0.5)
    # a split that computes other numbers than its parts is said so
    assert not tuning_split.compare(payload(shift=1e-7), payload(part_calls=True), payload())["split_equals_part_calls"]
    with pytest.raises(ValueError, match="different kicks"):
        tuning_split.compare(payload(), {**payload(part_calls=True), "starts": np.zeros((1, 2)).tolist()}, payload())
