"""The paper's numbers, and the markdown of every table the project prints or writes.

Each table is rendered once, here, from the records the stages write; the paper's columns sit
beside ours wherever the paper reported the same row.
"""

from __future__ import annotations

from bumps_jax.algo.evaluate import ACCURACY_THRESHOLD
from bumps_jax.envs import base as task_env

# The paper's Table 1 (SimSpark): accuracy mean, std; error mean, std (m).
PAPER_TABLE1 = {
    "experts": (0.89, 0.04, 0.57, 0.14),
    "meta_4x256": (0.84, 0.10, 0.72, 0.25),
    "meta_11x128": (0.84, 0.17, 0.68, 0.28),
}
# The paper's Table 2: error mean, std (m); relative error mean, std.
PAPER_TABLE2 = {
    "filtered_4x256": (0.45, 0.10, 0.038, 0.011),
    "filtered_11x128": (0.43, 0.13, 0.036, 0.013),
    "filtered_ensemble": (0.40, 0.11, 0.033, 0.011),
    "high_sample_rate_4x256": (0.40, 0.09, 0.033, 0.009),
}
TABLE2_COLUMNS = ("error_mean_m", "error_std_m", "rel_error_mean", "rel_error_std")
# Rows the paper did not report, and how the tables name them.
ROW_LABELS = {"starting_kicks": "starting kicks (before PPO)"}


def num(x, digits: int = 2, scale: float = 1.0, suffix: str = "") -> str:
    """A number for a table; 'n/a' for None (e.g. an error mean over no task)."""
    return "n/a" if x is None else f"{scale * x:.{digits}f}{suffix}"


def pm(mean, std, digits: int = 2, scale: float = 1.0, suffix: str = "") -> str:
    return f"{num(mean, digits, scale, suffix)} +- {num(std, digits, scale)}"


def experts_markdown(record: dict) -> str:
    """The experts' row of Table 1 and their per-task numbers."""
    lines = [
        "| model | accuracy | error mean (m) | error std (m) | rel. error |",
        "|---|---|---|---|---|",
        f"| single-task experts | {pm(record['accuracy_mean'], record['accuracy_std'])} "
        f"| {num(record['error_mean_m'])} | {num(record['error_std_m'])} "
        f"| {num(record['rel_error_mean'], 1, 100, '%')} |",
        "",
        f"{record['tasks_above_threshold']}/{record['n_tasks']} tasks above accuracy {ACCURACY_THRESHOLD} "
        f"(the error columns count only those); {record['n_reps']} kicks per task, "
        f"{record['env_steps']} PPO env steps per expert.",
        "",
        *starting_kicks_lines(record),
        "| target (m) | accuracy | error mean (m) | error std (m) |",
        "|---|---|---|---|",
        *per_task_rows(record["per_task"]),
    ]
    return "\n".join(lines) + "\n"


def per_task_rows(per_task: list[dict], target_format: str = ".1f", digits: int = 2) -> list[str]:
    """An experts record's per-task rows: target (a vector context's as `(x, y)`), accuracy, error
    mean and std (`digits` each)."""
    return [
        f"| {task_env.format_context(row['target_m'], target_format)} | {row['accuracy']:.2f} "
        f"| {num(row['error_mean_m'], digits)} "
        f"| {num(row['error_std_m'], digits)} |"
        for row in per_task
    ]


def starting_kicks_lines(record: dict) -> list[str]:
    """What the experts' PPO started from, scored as the experts are (an experts record's
    "starting_kicks"), and its jump between neighbouring tasks; nothing for older records."""
    kicks, jump = record.get("starting_kicks"), record.get("starting_kicks_smoothness")
    lines = []
    if kicks:
        lines.append(
            f"{ROW_LABELS['starting_kicks']}: accuracy {pm(kicks['accuracy_mean'], kicks['accuracy_std'])}, error "
            f"{pm(kicks['error_mean_m'], kicks['error_std_m'])} m ({num(kicks['error_mean_all_m'])} m over all tasks)."
        )
    if jump:
        lines.append(jump_line(jump))
    lines += family_lines(record)
    return [*lines, ""] if lines else []


def jump_line(jump: dict) -> str:
    """One sentence on an experts record's "starting_kicks_smoothness" (`kick_model.largest_jump`)."""
    return (
        f"Largest jump between neighbouring tasks' starting kicks: {jump['jump']:.2f} scale units of "
        f"`{jump['param']}`, {jump['between_m'][0]:g} -> {jump['between_m'][1]:g} m."
    )


def family_lines(record: dict) -> list[str]:
    """An experts record's sentences on the kicks halfway between neighbouring starting kicks and
    on the tuning's runs (`tune.restarts` > 1), where it has them: for experts.md and the report."""
    lines = []
    if record.get("starting_kicks_midpoints"):
        lines.append(midpoints_line(record["starting_kicks_midpoints"]))
    if record.get("starting_kicks_tuning_runs"):
        lines.append(tuning_runs_line(record["starting_kicks_tuning_runs"]))
    return lines


def tuning_runs_line(runs: dict) -> str:
    """One sentence on an experts record's "starting_kicks_tuning_runs" (`tune.restarts` > 1)."""
    costs, n = ", ".join(f"{c:.3f}" for c in runs["fresh_costs"]), len(runs["fresh_costs"])
    if "runs_kept" not in runs:
        return f"Tuning runs' mean fresh cost: {costs}; kept run {runs['kept'] + 1} of {n}."
    counts = [runs["runs_kept"].count(k) for k in range(n + 1)]
    kept = ", ".join(f"run {k} for {c}" for k, c in enumerate(counts) if k and c)
    how = "kicks chosen together with the neighbour leash" if runs.get("keep") == "chain" else "cheapest kick"
    line = f"Tuning runs' mean fresh cost: {costs}; each task kept its {how}: {kept}, its start for {counts[0]}"
    if "polish_improved" in runs:
        line += f"; the polish improved {runs['polish_improved']} of {len(runs['runs_kept'])}"
    return line + "."


def midpoints_line(mid: dict) -> str:
    """One sentence on an experts record's "starting_kicks_midpoints"."""
    worst = max(mid["per_task"], key=lambda t: t["error_mean_m"])
    return (
        f"Halfway between neighbouring starting kicks (their trajectories mixed 50/50): error "
        f"{num(mid['error_mean_all_m'])} m over {len(mid['per_task'])} midpoints, {mid['targets_above_2m']} "
        f"above 2 m, the worst {worst['error_mean_m']:.2f} m at {worst['target_m']:g} m."
    )


def table1_markdown(rows: dict) -> str:
    """Table 1 of one run: experts and unfiltered meta-policies (rows: name -> `evaluate.table_row`)."""
    lines = [
        "| policy | accuracy | error (acc > 0.7) m | error (all tasks) m | tasks > 0.7 |",
        "|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        lines.append(
            f"| {ROW_LABELS.get(name, name)} | {pm(r['accuracy_mean'], r['accuracy_std'])} "
            f"| {pm(r['error_mean_m'], r['error_std_m'])} "
            f"| {num(r.get('error_mean_all_m'))} | {r.get('tasks_above_threshold', '-')}/{r.get('n_tasks', '-')} |"
        )
    return "# Table 1: experts and unfiltered meta-policies\n\n" + "\n".join(lines) + "\n"


def table1_beside_paper(rows: dict) -> list[str]:
    """Table 1 lines with the paper's columns beside ours (the report's form)."""
    lines = [
        "| model | accuracy (ours) | accuracy (paper) | error m (ours) | error m (paper) | error m, all tasks (ours) |",
        "|---|---|---|---|---|---|",
    ]
    for name, paper in PAPER_TABLE1.items():
        r = rows.get(name)
        if r is None:
            lines.append(f"| {name} | not run | {pm(paper[0], paper[1])} | | {pm(paper[2], paper[3])} | |")
            continue
        lines.append(
            f"| {name} | {pm(r['accuracy_mean'], r['accuracy_std'])} | {pm(paper[0], paper[1])} "
            f"| {pm(r['error_mean_m'], r['error_std_m'])} | {pm(paper[2], paper[3])} "
            f"| {num(r.get('error_mean_all_m', r['error_mean_m']))} |"
        )
        if name == "experts" and "starting_kicks" in rows:  # what PPO started from, beside what it made
            r = rows["starting_kicks"]
            lines.append(
                f"| {ROW_LABELS['starting_kicks']} | {pm(r['accuracy_mean'], r['accuracy_std'])} | - "
                f"| {pm(r['error_mean_m'], r['error_std_m'])} | - | {num(r.get('error_mean_all_m'))} |"
            )
    return lines


def table2_beside_paper(rows: dict) -> list[str]:
    """Table 2 lines, every paper variant, ours beside (the report's form)."""
    lines = [
        "| variant | contexts | error m (ours) | error m (paper) | rel. error (ours) | rel. error (paper) "
        "| at selection m (ours) | selection rollouts |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, (em, es, rm, rs) in PAPER_TABLE2.items():
        r = rows.get(name)
        ours = "not run" if r is None else pm(r["error_mean_m"], r["error_std_m"])
        rel = "" if r is None else pm(r["rel_error_mean"], r["rel_error_std"], 1, 100, "%")
        n = "" if r is None else r["n_contexts"]
        sel = " | " if r is None else f"{num(r.get('selection_error_m'))} | {r.get('rollouts', '')}"
        lines.append(f"| {name} | {n} | {ours} | {pm(em, es)} | {rel} | {pm(rm, rs, 1, 100, '%')} | {sel} |")
    return lines


def table2_markdown(rows: dict) -> str:
    """Table 2: BUMPS after policy filtering, beside the paper (rows: name -> `filtering` row)."""
    lines = [
        "# Table 2: BUMPS after policy filtering (this run vs the paper)",
        "",
        "| variant | contexts | error m | paper error m | rel. error | paper rel. error | at selection m "
        "| selection rollouts |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        p = PAPER_TABLE2.get(name)
        paper_err = pm(p[0], p[1]) if p else "-"
        paper_rel = pm(p[2], p[3], 1, 100, "%") if p else "-"
        lines.append(
            f"| {name} | {r['n_contexts']} | {pm(r['error_mean_m'], r['error_std_m'])} | {paper_err} "
            f"| {pm(r['rel_error_mean'], r['rel_error_std'], 1, 100, '%')} | {paper_rel} "
            f"| {num(r.get('selection_error_m'))} | {r.get('rollouts', '-')} |"
        )
    return "\n".join(lines) + "\n\n" + SELECTION_NOTE + "\n"


def heldout_lines(record: dict) -> list[str]:
    """The held-out table (no paper column: the paper has no held-out set)."""
    lines = [
        f"{len(record['targets_m'])} targets off the 0.1 m grid, {record['repetitions']} fresh kicks each "
        f"(noise seed {record['seed']}); error: mean over every target of its mean final error.",
        "",
        "| policy | accuracy | error m (all targets) | rel. error | selection error m |",
        "|---|---|---|---|---|",
    ]
    for name, r in record["rows"].items():
        lines.append(
            f"| {name} | {pm(r['accuracy_mean'], r['accuracy_std'])} | {pm(r['error_mean_m'], r['error_std_m'])} "
            f"| {num(r['rel_error_mean'], 1, 100, '%')} | {num(r.get('selection_error_m'))} |"
        )
    return lines


# Under Table 2: what its selection column means.
SELECTION_NOTE = (
    "At selection: the chosen contexts' mean score on the selection rollouts; the error columns are "
    "fresh rollouts of the same choices. The gap between the two is what the noisy selection overrated."
)


# -- another contextual task's tables (no paper columns: the paper ran the kick only) -----------


def task_experts_markdown(record: dict) -> str:
    """The experts of a task other than the kick: their row and per-task numbers, errors in the
    record's `unit` (its keys keep the kick's `_m` names)."""
    unit = record.get("unit", "m")
    lines = [
        f"| model | valid | error mean ({unit}) | error std ({unit}) |",
        "|---|---|---|---|",
        f"| single-task experts | {pm(record['accuracy_mean'], record['accuracy_std'])} "
        f"| {num(record['error_mean_m'])} | {num(record['error_std_m'])} |",
        "",
        f"{record['n_reps']} episodes per task; env steps per expert: "
        + ", ".join(
            f"{k} {v:,}"
            for k, v in record.get("env_steps_breakdown", {"ppo": record["env_steps"]}).items()
            if v is not None
        )
        + ".",  # fmt: skip
        "",
        f"| target ({unit}) | valid | error mean ({unit}) | error std ({unit}) |",
        "|---|---|---|---|",
        *per_task_rows(record["per_task"], ".3g", 3),
    ]
    return "\n".join(lines) + "\n"


def task_table1_markdown(rows: dict, unit: str) -> str:
    """Table 1 of a task other than the kick: experts (on their training targets) and unfiltered
    meta-policies (on the test targets), errors in `unit`."""
    lines = [
        f"| policy | valid | error, valid tasks ({unit}) | error, all tasks ({unit}) | tasks |",
        "|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        lines.append(
            f"| {ROW_LABELS.get(name, name)} | {pm(r['accuracy_mean'], r['accuracy_std'])} "
            f"| {pm(r['error_mean_m'], r['error_std_m'], 3)} | {num(r.get('error_mean_all_m'), 3)} "
            f"| {r.get('n_tasks', '-')} |"
        )
    note = "The experts run on their own training targets; the meta-policies on the test targets, context = target."
    return "# Table 1: experts and unfiltered meta-policies\n\n" + "\n".join(lines) + "\n\n" + note + "\n"


def task_table2_markdown(rows: dict, unit: str) -> str:
    """Table 2 of a task other than the kick: the meta-policies after policy filtering, errors in `unit`."""
    lines = [
        "# Table 2: after policy filtering",
        "",
        f"| variant | contexts | error ({unit}) | at selection ({unit}) | valid | selection rollouts |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        lines.append(
            f"| {name} | {r['n_contexts']} | {pm(r['error_mean_m'], r['error_std_m'], 3)} "
            f"| {num(r.get('selection_error_m'), 3)} | {num(r.get('accuracy_mean'))} | {r.get('rollouts', '-')} |"
        )
    return "\n".join(lines) + "\n\n" + SELECTION_NOTE + "\n"
