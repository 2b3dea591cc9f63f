"""The error map of a 2-D context from a run's records: which arms it draws, and none for a scalar context."""

import numpy as np

from bumps_jax.report import error_map

GOALS = [[0.0, 0.0], [1.0, 0.0], [0.0, -1.0]]


def _records():
    experts = {"per_task": [{"target_m": g, "error_mean_m": 0.1 * i} for i, g in enumerate(GOALS)], "unit": "m"}
    table1 = {"per_task": {"tasks": GOALS, "meta_4x256": {"error_mean_m": [0.5, 0.6, 0.7]}}}
    chosen = {"filtered_4x256": GOALS, "filtered_11x128": [[0.1, 0.0], [1.0, 0.1], [0.0, -0.9]]}
    table2 = {"tasks": GOALS, "per_task_error_m": {"filtered_ensemble": [0.2, 0.3, 0.4]}, "chosen_contexts": chosen}
    baseline = {"seeds": 3, "eval_tasks": GOALS, "per_task_error_m": [1.0, 1.1, 1.2]}
    return {"experts": experts, "meta": table1, "filter": table2, "baseline": baseline}


def test_every_arm_with_2d_targets_gets_a_panel(tmp_path):
    r = _records()
    maps = error_map.panels(r["experts"], r["meta"], r["filter"], r["baseline"])
    assert list(maps) == ["experts (own targets)", "meta_4x256 unfiltered", "BUMPS filtered ensemble",
                          "multi-task PPO (3 seeds)"]  # fmt: skip
    targets, err = maps["multi-task PPO (3 seeds)"]
    assert targets.shape == (3, 2) and np.allclose(err, [1.0, 1.1, 1.2])
    assert error_map.write(tmp_path, r).stat().st_size > 0
    # A missing stage leaves its panel out; filtering without an ensemble shows its first variant.
    assert list(error_map.panels(r["experts"], None, None, None)) == ["experts (own targets)"]
    single = {**r["filter"], "per_task_error_m": {"filtered_4x256": [0.2, 0.3, 0.4]}}
    assert "BUMPS filtered 4x256" in error_map.panels(None, None, single, None)


def test_a_scalar_context_has_no_map(tmp_path):
    experts = {"per_task": [{"target_m": 1.0, "error_mean_m": 0.1}, {"target_m": 2.0, "error_mean_m": 0.2}]}
    assert error_map.write(tmp_path, {"experts": experts}) is None
    assert not (tmp_path / error_map.NAME).exists()
