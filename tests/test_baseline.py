"""The multi-task PPO baseline (experiments/multitask_baseline.py) at its tiny preset."""

import json

import numpy as np
import pytest

from experiments import multitask_baseline


def test_tiny_baseline_writes_curve_for_two_seeds(tmp_path):
    payload = multitask_baseline.run(multitask_baseline.tiny_config(), tmp_path)
    saved = json.loads((tmp_path / "baseline.json").read_text())
    assert saved["seeds"] == 2
    curve = saved["curve"]
    n = len(curve["env_steps"])
    assert n == 3 and all(len(curve[k]) == n for k in ("mean", "ci_low", "ci_high"))
    assert np.all(np.asarray(curve["ci_low"]) <= np.asarray(curve["mean"]) + 1e-6)
    assert np.all(np.asarray(curve["mean"]) <= np.asarray(curve["ci_high"]) + 1e-6)
    assert curve["env_steps"][-1] == payload["env_steps"] == 3 * 8 * 75
    assert np.isfinite(saved["error_mean_m"]) and 0.0 <= saved["accuracy_mean"] <= 1.0
    assert (tmp_path / "baseline_curve.png").stat().st_size > 0


def test_sampled_task_range_is_validated():
    cfg = multitask_baseline.tiny_config()
    cfg.ppo.sample_task_range = (18.0, 7.0)
    with pytest.raises(ValueError, match="sample_task_range"):
        multitask_baseline.run(cfg, "unused")
