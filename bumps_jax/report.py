"""The run's report: the paper's Tables 1 and 2 beside ours, figures, wall times, device, versions.

Reads whatever stages a run directory holds (prior/, experts/, meta/, filter/) and writes
`report.md` there; a missing stage is named, not skipped silently.
"""

from __future__ import annotations

import json
from pathlib import Path

from bumps_jax.filtering import PAPER_TABLE2

# The paper's Table 1 (SimSpark): accuracy mean, std; error mean, std (m).
PAPER_TABLE1 = {
    "experts": (0.89, 0.04, 0.57, 0.14),
    "meta_4x256": (0.84, 0.10, 0.72, 0.25),
    "meta_11x128": (0.84, 0.17, 0.68, 0.28),
}
STAGES = {
    "prior": "prior/kick_prior.json",
    "experts": "experts/experts.json",
    "meta": "meta/table1.json",
    "filter": "filter/table2.json",
}
# The committed GPU results, relative to the repository root (docs/results.md is built from them).
COMMITTED = {
    "prior": "results/kick_prior.json",
    "experts": "results/experts.json",
    "meta": "results/table1.json",
    "filter": "results/table2.json",
}


def _load(run_dir: Path, rel: str) -> dict | None:
    path = run_dir / rel
    return json.loads(path.read_text()) if path.exists() else None


def _f(x, digits=2) -> str:
    return "n/a" if x is None else f"{x:.{digits}f}"


def table1(rows: dict) -> list[str]:
    lines = [
        "| model | accuracy (ours) | accuracy (paper) | error m (ours) | error m (paper) | error m, all tasks (ours) |",
        "|---|---|---|---|---|---|",
    ]
    for name, paper in PAPER_TABLE1.items():
        r = rows.get(name)
        if r is None:
            paper_acc, paper_err = f"{paper[0]:.2f} +- {paper[1]:.2f}", f"{paper[2]:.2f} +- {paper[3]:.2f}"
            lines.append(f"| {name} | not run | {paper_acc} | | {paper_err} | |")
            continue
        lines.append(
            f"| {name} | {_f(r['accuracy_mean'])} +- {_f(r['accuracy_std'])} | {paper[0]:.2f} +- {paper[1]:.2f} "
            f"| {_f(r['error_mean_m'])} +- {_f(r['error_std_m'])} | {paper[2]:.2f} +- {paper[3]:.2f} "
            f"| {_f(r.get('error_mean_all_m', r['error_mean_m']))} |"
        )
    return lines


def table2(rows: dict) -> list[str]:
    lines = [
        "| variant | contexts | error m (ours) | error m (paper) | rel. error (ours) | rel. error (paper) |",
        "|---|---|---|---|---|---|",
    ]
    for name, (em, es, rm, rs) in PAPER_TABLE2.items():
        r = rows.get(name)
        ours = "not run" if r is None else f"{r['error_mean_m']:.2f} +- {r['error_std_m']:.2f}"
        rel = "" if r is None else f"{100 * r['rel_error_mean']:.1f}% +- {100 * r['rel_error_std']:.1f}"
        n = "" if r is None else r["n_contexts"]
        lines.append(f"| {name} | {n} | {ours} | {em:.2f} +- {es:.2f} | {rel} | {100 * rm:.1f}% +- {100 * rs:.1f} |")
    return lines


def build(run_dir: str | Path, files: dict | None = None, figures_dir: str = "*", title: str | None = None) -> str:
    """The report's markdown for `run_dir` (stage files `STAGES`, or `files` relative to it)."""
    run_dir = Path(run_dir)
    found = {name: _load(run_dir, rel) for name, rel in (files or STAGES).items()}
    first = next((v for v in found.values() if v), None)
    lines = [f"# {title or f'BUMPS on the simulated NAO: run `{run_dir.name}`'}", ""]
    if first is None:
        return "\n".join([*lines, "No stage has written results in this directory yet.", ""])
    presets = sorted({v["preset"] for v in found.values() if v})
    lines += [
        f"Preset: {', '.join(presets)}" + (" (CPU-sized numbers: they show the machinery, not the method)"
                                           if "tiny" in presets else ""),
        f"Device: {first['device']}; versions: "
        + ", ".join(f"{k} {v}" for k, v in first["versions"].items() if v),
        "",
        "## Stages",
        "",
        "| stage | wall time (s) | command |",
        "|---|---|---|",
    ]  # fmt: skip
    total = 0.0
    for name, payload in found.items():
        if payload is None:
            used = " (the committed `assets/kick_prior.json` was used)" if name == "prior" else ""
            lines.append(f"| {name} | not run{used} | |")
            continue
        total += payload["wall_s"]
        lines.append(f"| {name} | {payload['wall_s']:.0f} | `{payload['command']}` |")
    lines += [f"| **total** | **{total:.0f}** | |", ""]
    if found["prior"]:
        p = found["prior"]
        lines += [
            "## Kick prior",
            "",
            f"{p['target_m']:.0f} m prior over {p['n_reps']} noisy kicks: mean error {p['mean_error_m']:.2f} m, "
            f"valid {p['valid_fraction']:.2f}, fallen {p['fallen_fraction']:.2f}. Reachable: "
            f"{min(r['distance_m'] for r in p['sweep']):.1f} to {max(r['distance_m'] for r in p['sweep']):.1f} m.",
            "",
        ]
    rows1 = dict(found["meta"]["rows"]) if found["meta"] else {}
    if found["experts"] and "experts" not in rows1:
        rows1["experts"] = found["experts"]
    lines += ["## Table 1: experts and unfiltered meta-policies", "", *table1(rows1), ""]
    if found["experts"]:
        lines += [f"Experts: {found['experts']['env_steps']:,} PPO env steps each.", ""]
    rows2 = found["filter"]["rows"] if found["filter"] else {}
    lines += ["## Table 2: BUMPS after policy filtering", "", *table2(rows2), ""]
    figures = sorted(p.relative_to(run_dir).as_posix() for p in run_dir.glob(f"{figures_dir}/*.png"))
    if figures:
        lines += ["## Figures", ""] + [f"![{f}]({f})" for f in figures] + [""]
    return "\n".join(lines)


def write(run_dir: str | Path) -> Path:
    path = Path(run_dir) / "report.md"
    path.write_text(build(run_dir))
    return path


def write_committed(root: str | Path = ".") -> Path:
    """docs/results.md from the committed GPU results (results/, figures in docs/)."""
    root = Path(root)
    text = build(root, COMMITTED, figures_dir="docs", title="BUMPS on the simulated NAO: committed GPU results")
    path = root / "docs" / "results.md"
    note = (
        "The stages ran one by one on the GPU, not as one `make reproduce`; the experts' PPO budget was "
        "cut (see the experts row's env steps). Each file under results/ names the command that made it.\n\n"
    )
    head, _, rest = text.partition("\n\n")
    path.write_text(head + "\n\n" + note + rest.replace("](docs/", "]("))  # figures sit beside the report
    return path
