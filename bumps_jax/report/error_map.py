"""The error over a 2-D context space, read from a run's records: each arm's mean final error at
its targets (the experts at their training targets; the unfiltered and filtered meta-policies and
the baseline at the test targets), and the contexts filtering chose against the test targets.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bumps_jax import runio

NAME = "error_map.png"  # under the run directory


def panels(experts: dict | None, table1: dict | None, table2: dict | None, baseline: dict | None) -> dict:
    """name -> (targets (n, 2), mean error (n,)) of every arm a record holds, vector targets only."""
    out = {}
    if experts:
        out["experts (own targets)"] = ([t["target_m"] for t in experts["per_task"]],
                                        [t["error_mean_m"] for t in experts["per_task"]])  # fmt: skip
    per_task = (table1 or {}).get("per_task", {})
    if "meta_4x256" in per_task:
        out["meta_4x256 unfiltered"] = (per_task["tasks"], per_task["meta_4x256"]["error_mean_m"])
    filtered = (table2 or {}).get("per_task_error_m", {})
    if filtered:  # the ensemble where filtering ran it, else its first variant
        name = "filtered_ensemble" if "filtered_ensemble" in filtered else next(iter(filtered))
        out[f"BUMPS {name.replace('_', ' ')}"] = (table2["tasks"], filtered[name])
    if baseline and "per_task_error_m" in baseline:
        out[f"multi-task PPO ({baseline['seeds']} seeds)"] = (baseline["eval_tasks"], baseline["per_task_error_m"])
    return {k: (np.asarray(t, float), np.asarray(e, float)) for k, (t, e) in out.items() if np.ndim(t) == 2}


def plot(path, maps: dict, table2: dict | None, unit: str = "m") -> Path | None:
    """One panel per arm (`panels`), its targets coloured by mean error on one scale, and a last
    panel of arrows from each test target to the context each net's filtering chose for it.
    None (no figure) where no arm has 2-D targets."""
    if not maps:
        return None
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    chosen = (table2 or {}).get("chosen_contexts", {})
    nets = [k for k in ("filtered_4x256", "filtered_11x128") if k in chosen]
    n = len(maps) + (1 if nets else 0)
    fig, axes = plt.subplots(1, n, figsize=(3.6 * n, 3.8), squeeze=False)
    axes = axes[0]
    top = max(float(np.nanmax(e)) for _, e in maps.values())
    reach = max(float(np.abs(t).max()) for t, _ in maps.values()) * 1.1
    for ax, (name, (targets, err)) in zip(axes, maps.items(), strict=False):
        dots = ax.scatter(targets[:, 0], targets[:, 1], c=err, cmap="viridis", vmin=0.0, vmax=top, s=28)
        ax.set_title(f"{name}\nmean {np.nanmean(err):.2f} {unit}", fontsize=8)
    if nets:
        ax = axes[-1]
        tasks = np.asarray(table2["tasks"], float)
        for i, net in enumerate(nets):
            c = np.asarray(chosen[net], float)
            ax.quiver(tasks[:, 0], tasks[:, 1], c[:, 0] - tasks[:, 0], c[:, 1] - tasks[:, 1], angles="xy",
                      scale_units="xy", scale=1, width=0.004, color=f"C{i}", label=net)  # fmt: skip
        ax.scatter(tasks[:, 0], tasks[:, 1], s=6, c="k", label="test target")
        ax.set_title("chosen context - test target", fontsize=8)
        ax.legend(fontsize=6)
    for ax in axes:
        ax.set(xlim=(-reach, reach), ylim=(-reach, reach), aspect="equal")
        ax.tick_params(labelsize=6)
        ax.grid(alpha=0.3)
    bar = fig.colorbar(dots, ax=axes[len(maps) - 1], fraction=0.046, pad=0.04)  # one scale for every arm
    bar.set_label(f"mean final error ({unit})", fontsize=7)
    return runio.save_figure(fig, path)


def write(run_dir: str | Path, records: dict) -> Path | None:
    """run_dir/error_map.png from the run's records (name -> record or None: experts, meta,
    filter, baseline), or None where its targets are not 2-D."""
    unit = next((r.get("unit", "m") for r in records.values() if r), "m")
    maps = panels(records.get("experts"), records.get("meta"), records.get("filter"), records.get("baseline"))
    return plot(Path(run_dir) / NAME, maps, records.get("filter"), unit)
