"""The multi-task PPO baseline's training curves, drawn from its record (`baseline/baseline.json`)."""

from __future__ import annotations

from pathlib import Path

from bumps_jax import runio
from bumps_jax.report import budgets


def baseline(payload: dict, path: Path) -> Path:
    """Per arm, over env steps: the training episodes' mean final error and mean return, with the
    95 % bootstrap band over seeds where there are several; the targets' range and unit are the
    record's."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    unit, (lo, hi) = payload["unit"], payload["sample_task_range"]
    seeds = int(payload["seeds"])
    arms = payload.get("arms") or [payload]
    fig, (ax_err, ax_ret) = plt.subplots(1, 2, figsize=(10, 4))
    banded = False
    for arm in arms:
        label = arm_label(arm, seeds)
        for ax, key in ((ax_err, "error_curve"), (ax_ret, "curve")):
            c = arm.get(key)
            if c is None:
                continue
            (line,) = ax.plot(c["env_steps"], c["mean"], label=label)
            if c["ci_low"] is not None and seeds > 1:
                ax.fill_between(c["env_steps"], c["ci_low"], c["ci_high"], alpha=0.25, color=line.get_color())
                banded = True
    ax_err.set_ylabel(f"training episodes' mean final error ({unit})")
    ax_ret.set_ylabel("mean episode return")
    for ax in (ax_err, ax_ret):
        ax.set_xlabel("environment steps (per seed)")
        ax.legend(fontsize=8, title="95% bootstrap bands" if banded else None, title_fontsize=8)
    targets = f"targets U[{lo:g}, {hi:g}] {unit}"
    fig.suptitle(f"Multi-task PPO, {targets} ({payload['device']}, {payload['preset']})", fontsize=9)
    return runio.save_figure(fig, path)


def arm_label(arm: dict, seeds: int) -> str:
    """'lr 1e-06, mean over 6 seeds'; one seed is that seed's curve: 'lr 1e-06, 1 seed'."""
    label = f"lr {arm['learning_rate']:g}" if "learning_rate" in arm else "baseline"
    return label + (f", mean over {seeds} seeds" if seeds > 1 else f", {budgets.seeds_phrase(seeds)}")
