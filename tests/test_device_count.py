"""The device-count comparison (experiments/device_count.py): two arms of the same seeds, read
from their seeds.json, compared row by row."""

import json

import pytest

from experiments import device_count


def test_the_permutation_p_value_counts_every_split():
    # Three and three: 20 splits; only the observed one and its mirror reach the full shift.
    assert device_count.permutation_p([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]) == pytest.approx(0.1)
    assert device_count.permutation_p([1.0, 2.0, 3.0], [1.0, 2.0, 3.0]) == pytest.approx(1.0)
    # {1, 2, 3, 4} into pairs, by hand: the means differ by 2 ({1, 2} | {3, 4} and its mirror),
    # 1 ({1, 3} | {2, 4}, mirrored) or 0 ({1, 4} | {2, 3}, mirrored); the observed 2 is reached by 2 of 6.
    assert device_count.permutation_p([1.0, 2.0], [3.0, 4.0]) == pytest.approx(2 / 6)


def write_arm(path, values, seeds=(1, 2), processes=1, env=None):
    env = env or {"impl": "warp", "physics_dt": 0.01}
    runs = []
    for s in seeds:
        run = path / f"seed{s}"
        (run / "experts").mkdir(parents=True)
        (run / "experts" / "experts.json").write_text(json.dumps({"n_processes": processes}))
        runs.append({"run": run.name, "seeds": {"experts.seed": s}})
    rows = {name: {"per_seed": v} for name, v in values.items()}
    (path / "seeds.json").write_text(json.dumps({"rows": rows, "runs": runs, "env": env, "unit": "m/s"}))
    return device_count.arm(path)


def test_arms_of_the_same_seeds_are_compared_row_by_row(tmp_path):
    one = write_arm(tmp_path / "one", {"experts": [0.1, 0.3], "meta_4x256": [0.2, 0.2]})
    four = write_arm(tmp_path / "four", {"experts": [0.2, 0.2], "filtered_4x256": [0.1, 0.1]}, processes=4)
    assert four["processes"] == [4, 4]
    rows = device_count.compare(one, four)
    assert list(rows) == ["experts"]  # only the rows both arms have
    assert rows["experts"]["difference_per_seed"] == pytest.approx([0.1, -0.1])
    assert rows["experts"]["difference_of_means"] == pytest.approx(0.0)
    assert rows["experts"]["permutation_p"] == pytest.approx(1.0)
    other_seeds = write_arm(tmp_path / "other", {"experts": [0.2, 0.2]}, seeds=(1, 3))
    with pytest.raises(ValueError, match="other training seeds"):
        device_count.compare(one, other_seeds)
    other_env = write_arm(tmp_path / "env", {"experts": [0.2, 0.2]}, env={"impl": "jax", "physics_dt": 0.01})
    with pytest.raises(ValueError, match="another env config"):
        device_count.compare(one, other_env)


def test_a_published_task_is_an_arm():
    """The committed cheetah seeds (results/cheetah_vel: seeds.json, seeds/seed<S>/experts.json)
    read as the one-process arm, as published."""
    from pathlib import Path

    published = device_count.arm(Path(__file__).resolve().parent.parent / "results" / "cheetah_vel")
    assert published["processes"] == [1, 1, 1] and len(published["seeds"]) == 3
    assert published["device"] == "NVIDIA H200"  # each arm's own: the kick's published seeds ran on H100s
    assert device_count.procs(published) == "1 process"


def test_an_arm_of_mixed_processes_names_each_run():
    assert device_count.procs({"processes": [4, 2, 2]}) == "4, 2, 2 processes"
    assert device_count.procs({"processes": [4, 4, 4]}) == "4 processes"
