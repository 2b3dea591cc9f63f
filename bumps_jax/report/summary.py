"""The run's report: the paper's Tables 1 and 2 beside ours, figures, wall times, device, versions.

Reads whatever stages a run directory holds (prior/, experts/, meta/, filter/) and writes
`report.md` there; a missing stage is named, not skipped silently.
"""

from __future__ import annotations

from pathlib import Path

from bumps_jax import records as env_records
from bumps_jax import runio
from bumps_jax.report import budgets, tables

STAGES = {
    "prior": "prior/kick_prior.json",
    "experts": "experts/experts.json",
    "meta": "meta/table1.json",
    "filter": "filter/table2.json",
}
# Besides the stages: the multi-task PPO baseline and the pipeline's own timing (`reproduce`).
EXTRAS = {"baseline": "baseline/baseline.json", "pipeline": "pipeline.json", "heldout": "heldout/heldout.json"}
# The committed GPU results, relative to the repository root (docs/results.md is built from them).
COMMITTED = {
    "prior": "results/kick_prior.json",
    "experts": "results/experts.json",
    "meta": "results/table1.json",
    "filter": "results/table2.json",
    "baseline": "results/baseline.json",
    "pipeline": "results/pipeline.json",
    "heldout": "results/heldout.json",
}
BENCH = "benchmarks/results/training.json"
SCALING = "benchmarks/results/scaling.json"
GAE = "benchmarks/results/experts_gae.json"  # `bench --skip ...` keeping only the experts' GAE comparison
PRIOR_ASSET = "assets/kick_prior.json"
SEEDS = "results/seeds.json"  # the headlines over training seeds (`publish --seed-runs`)
AT_BUDGET = f"results/{budgets.AT_BUDGET}"  # the kick's baseline at BUMPS' budget (`publish --baseline-at-budget`)


def load(run_dir: Path, rel: str) -> dict | None:
    """The JSON record at run_dir / rel, or None where there is none."""
    path = run_dir / rel
    return runio.read_json(path, "a record of the run") if path.exists() else None


def has_results(run_dir: Path) -> bool:
    """Whether any stage has written its record under run_dir."""
    stages = [*STAGES.values(), EXTRAS["baseline"], EXTRAS["heldout"]]
    return any((Path(run_dir) / rel).exists() for rel in stages)


def build(
    run_dir: str | Path,
    files: dict | None = None,
    figures_dir: str = "*",
    title: str | None = None,
    at_budget: dict | None = None,
) -> str:
    """The report's markdown for `run_dir` (stage files `STAGES`, or `files` relative to it;
    `at_budget`: a baseline record trained at BUMPS' budget, set beside the run's own)."""
    run_dir = Path(run_dir)
    found = {name: load(run_dir, rel) for name, rel in (files or {**STAGES, **EXTRAS}).items()}
    extras = {name: found.pop(name, None) for name in EXTRAS}
    # The held-out evaluation and the baseline are stages of the pipeline too; a row where they ran.
    ran = {name: extras[name] for name in ("heldout", "baseline") if extras[name]}
    first = next((v for v in [*found.values(), *ran.values()] if v), None)
    lines = [f"# {title or f'BUMPS on the simulated NAO: run `{run_dir.name}`'}", ""]
    if first is None:
        return "\n".join([*lines, "No stage has written results in this directory yet.", ""])
    presets = sorted({v["preset"] for v in [*found.values(), *ran.values()] if v})
    lines += [*preamble_lines(presets, first), "## Stages", ""]
    stage_lines, own_s = stages_table({**found, **ran})
    lines += stage_lines
    lines += mixed_steps_lines({**found, **ran})
    lines += pipeline_lines(extras["pipeline"], own_s)

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
    if found["experts"] and "starting_kicks" in found["experts"] and "starting_kicks" not in rows1:
        rows1["starting_kicks"] = found["experts"]["starting_kicks"]
    lines += ["## Table 1: experts and unfiltered meta-policies", "", *tables.table1_beside_paper(rows1), ""]
    if found["experts"]:
        lines += env_steps_lines(found["experts"])
    rows2 = found["filter"]["rows"] if found["filter"] else {}
    lines += ["## Table 2: BUMPS after policy filtering", "", *tables.table2_beside_paper(rows2), ""]
    if extras["heldout"]:
        lines += ["## Held-out targets (`evaluate --heldout`; no paper column: the paper has none)", ""]
        lines += [*differing_env_lines({"Tables 1-2": found["filter"] or found["meta"], "held-out": extras["heldout"]})]
        lines += [*tables.heldout_lines(extras["heldout"]), ""]
    lines += baseline_lines(extras["baseline"], found["experts"], rows2, at_budget)
    pictures = [*run_dir.glob(f"{figures_dir}/*.png"), *run_dir.glob(f"{figures_dir}/*.gif")]
    figures = sorted(p.relative_to(run_dir).as_posix() for p in pictures)
    if figures:
        lines += ["## Figures", ""] + [f"![{f}]({f})" for f in figures] + [""]
    return "\n".join(lines)


def preamble_lines(presets: list[str], first: dict) -> list[str]:
    """The report's preset and device lines (`first`: a stage's record, for device and versions)."""
    tiny = " (CPU-sized numbers: they show the machinery, not the method)" if "tiny" in presets else ""
    versions = ", ".join(f"{k} {v}" for k, v in first["versions"].items() if v)
    return [f"Preset: {', '.join(presets)}{tiny}", f"Device: {first['device']}; versions: {versions}", ""]


def stages_table(found: dict) -> tuple[list[str], dict[str, float]]:
    """The stages' table (wall time, physics, command; None: not run) and each run stage's own wall
    time (name -> s)."""
    lines = ["| stage | wall time (s) | physics (step, backend) | command |", "|---|---|---|---|"]
    own_s = {}
    for name, payload in found.items():
        if payload is None:
            used = " (the committed `assets/kick_prior.json` was used)" if name == "prior" else ""
            lines.append(f"| {name} | not run{used} | | |")
            continue
        own_s[name] = payload["wall_s"]
        lines.append(f"| {name} | {payload['wall_s']:.0f} | {physics_step(payload)} | `{payload['command']}` |")
    return [*lines, f"| **sum of the stages' own wall times** | **{sum(own_s.values()):.0f}** | | |", ""], own_s


def env_steps_lines(experts: dict) -> list[str]:
    """What the experts cost in env steps (their share of the prior, the starting kicks' tuning,
    PPO), per expert and in all, and how smooth their starting kicks are as a family."""
    n = len(experts["tasks_m"])
    parts = experts.get("env_steps_breakdown")
    if not parts:  # records older than the breakdown
        return [f"Experts: {experts['env_steps']:,} PPO env steps each.", ""]
    names = {"prior": "share of the kick prior", "tuning": "starting-kick tuning", "ppo": "PPO"}
    shown = ", ".join(f"{names.get(k, k)} {'not recorded' if v is None else f'{v:,}'}" for k, v in parts.items())
    total = sum(v for v in parts.values() if v is not None)
    lines = [f"Env steps per expert: {shown}; {total:,} in all. All {n} experts: {n * total:,} "
             f"(PPO {n * parts['ppo']:,})."]  # fmt: skip
    jump = experts.get("starting_kicks_smoothness")
    if jump:
        lines.append(tables.jump_line(jump))
    return [*lines, *tables.family_lines(experts), ""]


def physics_step(payload: dict | None) -> str:
    """A record's physics ("2.5 ms, jax"), or "not recorded" for records older than the env key."""
    payload = payload or {}
    env = payload.get("env") or {}
    dt = env.get("physics_dt", payload.get("physics_dt_s"))
    if not dt:
        return "not recorded"
    impl = env.get("impl")
    return f"{dt * 1e3:g} ms" + (f", {impl}" if impl else ", backend not recorded")


def mixed_steps_lines(payloads: dict) -> list[str]:
    """A warning when the records shown together ran under different physics (step or backend),
    naming the env keys that differ, and a note naming the records that carry no env config."""
    steps = {name: physics_step(p) for name, p in payloads.items() if p and physics_step(p) != "not recorded"}
    lines = []
    if len(set(steps.values())) >= 2:
        listed = ", ".join(f"{name} {step}" for name, step in steps.items())
        lines += [f"**These records ran under different physics ({listed}): they are not comparable.**", ""]
    lines += differing_env_lines(payloads)
    unknown = [name for name, p in payloads.items() if p and physics_step(p) == "not recorded"]
    if unknown and len(unknown) < sum(1 for p in payloads.values() if p):
        lines += [f"Physics not recorded for {', '.join(unknown)}: their comparison with the rest is unchecked.", ""]
    return lines


def differing_env_lines(payloads: dict) -> list[str]:
    """A warning line naming the env keys (`env_records.env_key`: physics and scoring) in which the
    records shown side by side differ; none where they agree or carry no env."""
    envs = {name: env_records.env_key(p["env"]) for name, p in payloads.items() if p and p.get("env")}
    if len(envs) < 2:
        return []
    (first, base), *rest = envs.items()
    keys = sorted({k for _, env in rest for k in env_records.differing_keys(base, env)})
    if not keys:
        return []
    names = ", ".join(envs)
    return [f"**Warning: {names} ran under different env configs (differing: {', '.join(f'env.{k}' for k in keys)}).**",
            ""]  # fmt: skip


def pipeline_lines(pipeline: dict | None, own_s: dict[str, float] | None = None) -> list[str]:
    """The pipeline record's line; `own_s` (name -> a stage's own wall time, kept with its
    checkpoints) shows up a record that missed calls killed before they could write it. Only the
    stages the record counts are compared: a stage run by its own command is not the pipeline's."""
    pipeline = pipeline or {}
    stages = pipeline.get("stages_s", pipeline.get("stages", {}))  # "stages" in records before the contract's name
    if not stages:  # none timed (a pipeline.json made afresh after every stage had finished)
        return []
    wall_s = pipeline.get("wall_s", sum(stages.values()))
    stages_total_s = sum((own_s or {}).get(name, 0.0) for name in stages)
    parts = ", ".join(f"{k} {v:.0f} s" for k, v in stages.items())
    calls = pipeline.get("calls")  # absent in records older than the count
    how = {None: "resumed across calls where a stage was cut", 1: "in one call"}.get(
        calls, f"resumed across {calls} calls, each stage's time added up"
    )
    killed = pipeline.get("killed_calls")
    if killed:
        how += f"; {killed} of them killed, each counted up to its stage's last write"
    launches = pipeline.get("launches")
    total = f"**{wall_s / 60:.1f} min** in all"
    if launches:  # several jobs per launched call, some side by side: the launches say the wall time
        how = "one call" if len(launches) == 1 else f"resumed across {len(launches)} calls"
        how += "; stages side by side add up to more than the wall time below"
        total = f"{wall_s / 60:.1f} min of stages, added up"
    lines = [
        f"The pipeline (`demo` or `reproduce`): {total} ({parts}; "
        f"on {pipeline.get('device', 'the device above')}, {how}).",
        *([f"Note: {pipeline['note']}"] if pipeline.get("note") else []),
    ]
    lines += launch_lines(launches)
    if stages_total_s and wall_s < 0.99 * stages_total_s:
        lines.append(
            f"This record is short of the stages' own {stages_total_s / 60:.1f} min: calls that were killed "
            "before they could write it are missing. The stages' times above are counted to their checkpoints."
        )
    return [*lines, ""]


def launch_lines(launches: list | None) -> list[str]:
    """The run's launched calls (`--processes`): wall time from start to end and their phases."""
    if not launches:
        return []

    def phase(p):
        return " beside ".join(f"{', '.join(b['stages'])} on {b['processes']}" for b in p)

    last = launches[-1]
    steps = "; then ".join(phase(p) for p in last["phases"])
    calls = "one call" if len(launches) == 1 else f"{len(launches)} calls, added up"
    done = "" if last["finished"] else " (the last call did not finish)"
    return [
        f"Launched as {last['processes']} processes ({steps}): **{sum(x['wall_s'] for x in launches) / 60:.1f} min** "
        f"from start to end ({calls}; process start-up and compiles included){done}."
    ]


def baseline_lines(
    baseline: dict | None, experts: dict | None, filtered: dict | None = None, at_budget: dict | None = None
) -> list[str]:
    lines = ["## Multi-task PPO baseline (the paper's Figure 1)", ""]
    if not baseline:
        return [*lines, "Not run (`make baseline`).", ""]
    lines += [
        "One contextual policy trained by PPO on targets drawn from U[7, 18] m, "
        f"{budgets.seeds_phrase(baseline['seeds'])}, "
        f"{baseline['env_steps']:,} env steps per seed: meta-test error {baseline['error_mean_m']:.2f} m over all "
        f"{len(baseline['eval_tasks'])} tasks, accuracy {baseline['accuracy_mean']:.2f} ({baseline['preset']} preset, "
        f"{baseline.get('device', 'device unknown')}, physics step {physics_step(baseline)}).",
    ]
    for arm in baseline.get("arms", []):
        curve = arm.get("error_curve")
        trend = f"; training episodes' error {curve['mean'][0]:.2f} -> {curve['mean'][-1]:.2f} m" if curve else ""
        lines.append(
            f"- learning rate {arm['learning_rate']:g}: meta-test error {arm['error_mean_m']:.2f} m, "
            f"accuracy {arm['accuracy_mean']:.2f}{trend}"
        )
    if "start" in baseline:
        start = baseline["start"]
        lines.append(
            f"Every seed started from the cloned 12 m kick: error {start['error_mean_all_m']:.2f} m, accuracy "
            f"{start['accuracy_mean']:.2f} on the same tasks (clone's BC loss {baseline['bc_final_loss']:.1e})."
        )
    if experts:
        total = experts["env_steps"] * len(experts["tasks_m"])
        lines.append(
            f"BUMPS's experts used {total:,} PPO env steps in all ({len(experts['tasks_m'])} experts of "
            f"{experts['env_steps']:,}); the baseline {baseline['seeds'] * baseline['env_steps']:,} over its seeds."
        )
    if at_budget:
        lines += at_budget_lines(at_budget, experts)
    if filtered:
        name, best = min(filtered.items(), key=lambda kv: kv[1]["error_mean_m"])
        beside = ""
        if at_budget:
            steps, theirs = baseline["env_steps"], at_budget["error_mean_m"]
            beside = f" ({steps:,} env steps a seed) and {theirs:.2f} m at BUMPS' budget"
        lines.append(
            f"Best BUMPS variant ({name}): {best['error_mean_m']:.2f} m against the baseline's "
            f"{baseline['error_mean_m']:.2f} m{beside} on the same meta-test tasks."
        )
    return [*lines, ""]


def at_budget_lines(b: dict, experts: dict | None) -> list[str]:
    """The baseline arm trained at BUMPS' whole budget (`budgets.AT_BUDGET`): its budget beside the
    experts', its meta-test error and its training curve."""
    total = budgets.experts_total(experts)
    spent = f" (BUMPS' experts: {total:,} in all)" if total else ""
    per_update = b["curve"]["env_steps"][0]
    curve = b.get("error_curve")
    trend = f"; training episodes' error {curve['mean'][0]:.2f} -> {curve['mean'][-1]:.2f} m" if curve else ""
    return [
        f"At BUMPS' budget (`{AT_BUDGET}`, `{b.get('command', '?')}`): "
        f"{budgets.seeds_phrase(b['seeds'])} of {b['env_steps_per_seed']:,} env steps{spent}, {per_update:,} a PPO "
        f"update, learning rate {b['learning_rate']:g}: meta-test error {b['error_mean_m']:.2f} m, accuracy "
        f"{b['accuracy_mean']:.2f}{trend} ({b.get('device', 'device unknown')}, physics step {physics_step(b)})."
    ]


def scale_out_line(scaling: dict) -> str:
    """One sentence for one `benchmarks/scaling.py` record: the experts' and the filtering's ratio
    of N devices to one at its main workload (a phase the run did not finish: "not measured"),
    then its other workloads."""
    n = str(scaling["devices"])
    nan = float("nan")
    # one process per device (Warp's way) or one process with a mesh of all (a record without a layout)
    how = {"processes": "one process per device, each its own copies",
           "distributed": "joined processes, one device each, sharing one batch"}.get(
        scaling.get("layout"), "one process, a mesh of all")  # fmt: skip
    filtering = (f"filtering {scaling['filter_rollouts_speedup']:.2f}x" if "filter_rollouts_speedup" in scaling
                 else "filtering not measured in this run")  # fmt: skip
    line = (
        f"Scale-out on {scaling['device']}, {scaling['date'][:10]}, physics {physics_step(scaling)}, {how} "
        f"(`{scaling['command']}`): experts {scaling['experts_env_steps_per_s'][n]:,.0f} env-steps/s on "
        f"{n} devices vs {scaling['experts_env_steps_per_s']['1']:,.0f} on one "
        f"({scaling['experts_env_steps_speedup']:.2f}x); {filtering}, at {scaling.get('workload', 1)} times the "
        "paper's work (copies of every expert; filtering repetitions), measured on one device and on all in one run."
    )
    others = [e for e in scaling.get("by_copies", []) if e["workload"] != scaling.get("workload")]
    if others:  # the same run at other workloads: the ratio depends on how full one device is
        parts = [
            f"{e['workload']} times, experts {e.get('experts_env_steps_speedup', nan):.2f}x, "
            f"filtering {e.get('filter_rollouts_speedup', nan):.2f}x"
            for e in others
        ]
        line += f" The same run at other workloads: {'; '.join(parts)}."
    return line


def scaling_records(root: Path) -> list[dict]:
    """The committed scale-out records: benchmarks/results/scaling.json, then any other run's
    scaling.json in a folder of its own under benchmarks/results/ (`scaling.py --out-dir`)."""
    paths = [root / SCALING, *sorted((root / SCALING).parent.glob("*/scaling.json"))]
    return [record for path in paths if (record := load(root, path)) is not None]


def speed_lines(bench: dict | None, scalings: list[dict] = (), gae: dict | None = None) -> list[str]:
    """The speed section from `make bench`'s record: one column per physics backend measured
    (a record from before the backends were measured side by side: one column); a sentence per
    scale-out record (`benchmarks/scaling.py`); with `gae`, the bench's record of the experts' PPO
    with GAE as a loop and unrolled (`ppo.unroll_gae`)."""
    if not bench:
        return []
    per = bench.get("backends") or {bench.get("env", {}).get("impl", "backend not recorded"): bench}
    names = sorted(per, key=lambda b: b == bench.get("backend"))  # the config's own backend last
    projected = ", ".join(bench.get("projections", [])) or "-"
    lines = [
        "## Speed (`make bench`)",
        "",
        f"On {bench['device']}, one device, {bench['date'][:10]}, physics step {physics_step(bench)}, side by side "
        f"in one run. Wall times computed from a rate are projections: {projected}.",
        "",
        "| measure | " + " | ".join(names) + " |",
        "|---|" + "---|" * len(names),
    ]
    g = bench.get

    def row(label, key, fmt, shared=False):
        values = [g(key) if shared else per[b].get(key) for b in names]
        if any(v is not None for v in values):
            lines.append(f"| {label} | " + " | ".join("-" if v is None else fmt.format(v) for v in values) + " |")

    first = per[names[-1]]
    row(f"physics steps/s (batch {first.get('scene_batch')})", "physics_steps_per_s", "{:,.0f}")
    row("physics steps/s (batch 8192)", "physics_steps_per_s_8192", "{:,.0f}")
    row("env steps/s (experts' batch)", "env_steps_per_s", "{:,.0f}")
    row("PPO env-steps/s, all experts in one program", "experts_env_steps_per_s", "{:,.0f}")
    row("filtering rollouts/s", "filter_rollouts_per_s", "{:,.0f}")
    row("high-sample-rate filtering (s)", "filter_high_sample_wall_s", "{:.1f}")
    lines += ["", f"On {bench.get('backend', names[-1])} only:", "", "| measure | value |", "|---|---|"]
    rows = [
        ("experts, Warp / JAX", g("experts_env_steps_warp_vs_jax"), "{:.2f}x"),
        ("PPO env-steps/s, Brax ppo.train, one task", g("brax_ppo_env_steps_per_s"), "{:,.0f}"),
        ("PPO env-steps/s, Brax ppo.train, the experts' total batch", g("brax_ppo_env_steps_per_s_total_batch"),
         "{:,.0f}"),
        ("ours / Brax, one task", g("experts_vs_brax"), "{:.1f}x"),
        ("ours / Brax at the total batch", g("experts_vs_brax_total_batch"), "{:.2f}x"),
        ("BC gradient steps/s (slower net)", g("bc_steps_per_s"), "{:,.0f}"),
        ("BC, both nets' full schedules, separate loops (s, projected)", g("bc_wall_s", g("bc_wall_projected_s")),
         "{:.0f}"),
        ("BC, both nets in one loop (s, projected)", g("bc_joint_wall_s", g("bc_joint_wall_projected_s")), "{:.0f}"),
    ]  # fmt: skip
    lines += [f"| {name} | {fmt.format(v)} |" for name, v, fmt in rows if v is not None]
    for scaling in scalings or ():
        lines += ["", scale_out_line(scaling)]
    if gae and gae.get("experts_gae_unrolled_vs_loop"):
        lines += [
            "",
            f"PPO's GAE (`ppo.unroll_gae`), the experts' chunk side by side on {gae['device']}, {gae['date'][:10]}, "
            f"physics step {physics_step(gae)}: {gae['experts_env_steps_per_s_gae_loop']:,.0f} env-steps/s as a "
            f"device loop, {gae['experts_env_steps_per_s_gae_unrolled']:,.0f} unrolled "
            f"({gae['experts_gae_unrolled_vs_loop']:.2f}x); the experts' PPO projected "
            f"{gae['experts_ppo_projected_s_gae_loop']:.0f} s -> {gae['experts_ppo_projected_s_gae_unrolled']:.0f} s "
            f"(`{GAE}`)."
            + (
                " The tables above are older than it: their PPO ran GAE as the loop."
                if bench["date"] < gae["date"]
                else ""
            ),
        ]
    return [*lines, ""]


def stages_elsewhere(pipeline: dict | None) -> list[str]:
    """The paper run's stages that the committed pipeline record did not run (all of them without a
    pipeline record): their committed records were made by a stage command or an earlier run."""
    ran = (pipeline or {}).get("stages_s", {})
    return [stage for stage in COMMITTED if stage != "pipeline" and stage not in ran]


def provenance_note(root: Path, pipeline: dict | None) -> str:
    """Which command made the committed records: one reproduce, or the stages the pipeline record
    ran plus each other stage's record's own command and date."""
    if not pipeline:
        return "The stages ran one by one. Each file under results/ names the command that made it.\n\n"
    overrides = ", ".join(f"`{k}={v}`" for k, v in pipeline.get("overrides", {}).items()) or "none"
    records = {s: record for s in stages_elsewhere(pipeline) if (record := load(root, COMMITTED[s]))}
    if not records:
        return (
            f"Made by one `python -m bumps_jax reproduce --preset paper` (overrides: {overrides}) and published with "
            "`python -m bumps_jax publish`. Each file under results/ names the command that made it.\n\n"
        )
    same = all(
        r.get("env") == pipeline.get("env") and r.get("preset") == pipeline.get("preset") for r in records.values()
    )
    others = "; ".join(f"{s}: `{r.get('command', '?')}` ({str(r.get('date', '?'))[:10]})" for s, r in records.items())
    return (
        f"Made by `{pipeline.get('command', '?')}` (stages {', '.join(pipeline.get('stages_s', {}))}; overrides: "
        f"{overrides}) and published with `python -m bumps_jax publish`. The pipeline did not run the other stages; "
        f"their records ({'the same' if same else 'ANOTHER'} preset and env config) were made by {others}. Each file "
        "under results/ names the command that made it.\n\n"
    )


def write_committed(root: str | Path = ".") -> Path:
    """docs/results.md from the committed GPU results (results/, figures in docs/)."""
    root = Path(root)
    text = build(
        root,
        COMMITTED,
        figures_dir="docs",
        title="BUMPS on the simulated NAO: committed GPU results",
        at_budget=load(root, AT_BUDGET),
    )
    path = root / "docs" / "results.md"
    path.parent.mkdir(parents=True, exist_ok=True)
    note = provenance_note(root, load(root, COMMITTED["pipeline"]))
    speed = speed_lines(load(root, BENCH), scaling_records(root), load(root, GAE))
    head, _, rest = text.partition("\n\n")
    body = rest.replace("](docs/", "](")  # figures sit beside the report
    steps = "\n" + "\n".join(budgets.section(root))
    seeds = "\n".join(seeds_lines(load(root, SEEDS)))
    path.write_text(head + "\n\n" + note + seeds + body + steps + ("\n" + "\n".join(speed) + "\n" if speed else ""))
    return path


def seeds_lines(record: dict | None) -> list[str]:
    """The headlines over training seeds (`publish --seed-runs`): each row's mean, std and every seed's value."""
    if not record:
        return []
    runs = record["runs"]
    names = [f"seed {sorted(set(r['seeds'].values()))[0]}" for r in runs]
    lines = [
        f"## Over {record['n_seeds']} training seeds",
        "",
        "The same config run once per training seed (every stage's training randomness; the published run's "
        f"stages below are the first's). Error in m; `{SEEDS}`, each run's records under `results/seeds/`.",
        "",
        "| row | mean +- std | " + " | ".join(names) + " |",
        "|---|---|" + "---|" * len(names),
    ]
    for name, r in record["rows"].items():
        lines.append(
            f"| {name} | {r['mean']:.3f} +- {r['std']:.3f} | " + " | ".join(f"{v:.3f}" for v in r["per_seed"]) + " |"
        )
    return [*lines, "", ""]
