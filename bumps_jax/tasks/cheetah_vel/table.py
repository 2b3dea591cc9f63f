"""Our rows of HalfCheetah-Vel's comparison with the published meta-RL results
(docs/cheetah_vel_published.md) and README's sentence on the run, regenerated between their
markers by `publish --task cheetah_vel` from the committed records in results/cheetah_vel/.

The published columns are returns; our records keep the mean speed error |v - v*| over an episode
(m/s). A return is -sum over the steps of (w |v - v*| + ctrl |a|^2), w the env's `reward.velocity`,
so -steps x w x error is the return's speed term: the return without its control cost, an upper
bound on the return, on the same footing as the doc's reference points, which also leave the
control cost out."""

from __future__ import annotations

from pathlib import Path

from bumps_jax.report import published
from bumps_jax.report.summary import load

SEEDS = "results/cheetah_vel/seeds.json"  # the headlines over training seeds (`report.seeds`)
RECORDS = {name: f"results/cheetah_vel/{name}.json" for name in ("experts", "table1", "table2", "baseline")}


def speed_term(error: float, steps: int, weight: float) -> str:
    """The return's speed term of a mean speed error over an episode of `steps` steps, each step's
    reward weighing the speed error by `weight`."""
    return f"{-steps * weight * error:.0f}"


def rows(root: str | Path = ".") -> list[str]:
    """Markdown table rows (the doc's six columns) for BUMPS unfiltered, BUMPS filtered and our
    multi-task PPO, from whichever of the records exist; every number is a record's."""
    rec = {name: load(Path(root), rel) for name, rel in RECORDS.items()}
    experts, t1, t2, base = rec["experts"], rec["table1"], rec["table2"], rec["baseline"]
    first = next((r for r in rec.values() if r), None)
    if first is None:
        return []
    steps, weight = int(first["env"]["episode_steps"]), float(first["env"]["reward"]["velocity"])
    lo, hi = first["env"]["task_range"]
    version = f"ours: U[{lo:g}, {hi:g}] m/s, {steps} steps of {first['env']['ctrl_dt']:g} s (`docs/cheetah_vel.md`)"
    training = "not recorded"
    if experts and t1:
        n = len(experts["tasks_m"])
        cloning = t1.get("cloning", {}).get("env_steps_total", t1["dataset_pairs"])
        training = (
            f"{n * experts['env_steps_total']:,}: {n} experts x {experts['env_steps_total']:,} (PPO, the family's "
            f"shared start included), then {cloning:,} env steps of episodes for behaviour cloning"
        )
    out = []
    if t1:
        nets = {net: r for net, r in t1["rows"].items() if net != "experts"}
        n_tasks = max((r["n_tasks"] for r in nets.values()), default=0)
        cells = [
            f"{net.removeprefix('meta_')}: {speed_term(r['error_mean_m'], steps, weight)} (mean speed error "
            f"{r['error_mean_m']:.2f} m/s)"
            for net, r in nets.items()
        ]
        out.append(
            f"| BUMPS unfiltered (context = target) | speed term {'; '.join(cells)}; over {n_tasks} test "
            f"velocities x {t1['eval']['repetitions']} episodes | none: the target is the context | {training} "
            f"| {version} | `{RECORDS['table1']}` |"
        )
    if t2:
        cells = []
        for name, r in t2["rows"].items():
            per_task = r["rollouts"] / r["n_tasks"]
            cells.append(
                f"{name}: {speed_term(r['error_mean_m'], steps, weight)} ({r['error_mean_m']:.2f} m/s; "
                f"{per_task:.0f} selection rollouts per task)"
            )
        out.append(
            f"| BUMPS filtered (a context chosen per test velocity by rollouts of candidates) | speed term "
            f"{'; '.join(cells)}; fresh episodes, not the selection's | the selection rollouts of the test "
            f"task, {steps} steps each (listed per variant) | as unfiltered | {version} | `{RECORDS['table2']}` |"
        )
    if base:
        seeds = ", ".join(f"{s['error_mean_m']:.3f}" for s in base["per_seed"])
        score = (f"speed term {speed_term(base['error_mean_m'], steps, weight)} (mean speed error "
                 f"{base['error_mean_m']:.3f} m/s, mean of {base['seeds']} seeds: {seeds})")  # fmt: skip
        out.append(published.baseline_row(base, score, "target", "test velocities", version, RECORDS["baseline"]))
    return out


def readme_lines(root: str | Path = ".") -> list[str]:
    """README's sentences on the published HalfCheetah-Vel run (stage time, the nets unfiltered and
    filtered beside their experts, the baseline), every number a record's; none without a record."""
    root = Path(root)
    rec = {name: load(root, rel) for name, rel in {**RECORDS, "pipeline": "results/cheetah_vel/pipeline.json"}.items()}
    experts, t1, t2, base, pipe = (rec[k] for k in ("experts", "table1", "table2", "baseline", "pipeline"))
    out = []
    if pipe:
        stage_s = sum(pipe["stages_s"].values())
        stages = ", ".join(pipe["stages_s"])
        out.append(f"The paper preset's run on one {pipe['device']} ({pipe['env']['impl']}) took {stage_s:.0f} s "
                   f"of stage time ({stages}; `results/cheetah_vel/pipeline.json`).")  # fmt: skip
    if experts and t1 and t2:
        unit = experts.get("unit", "m/s")
        nets = [n for n in ("meta_4x256", "meta_11x128") if n in t1["rows"]]
        filtered = [r["error_mean_m"] for r in t2["rows"].values()]
        unfiltered = " / ".join(f"{t1['rows'][n]['error_mean_all_m']:.2f}" for n in nets)
        out.append(f"On its {len(t2['tasks'])} test velocities the meta-policies err {unfiltered} {unit} unfiltered "
                   f"and {published.span(filtered)} {unit} filtered, beside their experts' own "
                   f"{experts['error_mean_all_m']:.2f} {unit}.")  # fmt: skip
        seeds = load(root, SEEDS)
        if seeds:
            out.append(seeds_sentence(seeds))
        if base:
            total = experts.get("env_steps_total", experts["env_steps"]) * len(experts["tasks_m"])
            out.append(f"The multi-task PPO baseline ({base['device']}), with {base['env_steps_per_seed'] / 1e6:.0f} M "
                       f"env steps per seed (the {len(experts['tasks_m'])} experts: {total / 1e6:.0f} M in all), errs "
                       f"{base['error_mean_m']:.2f} {unit} (`results/cheetah_vel/report.md`).")  # fmt: skip
    return out


def seeds_sentence(seeds: dict) -> str:
    """The headlines over training seeds, and how many experts ran flipped on their backs per seed."""
    flipped = ", ".join(f"{r['flipped_experts']} of {r['n_experts']}" for r in seeds["runs"])
    return f"{published.seeds_sentence(seeds, SEEDS)} Experts flipped on their backs, per seed: {flipped}."


BLOCKS = published.Blocks(task="cheetah_vel", title="HalfCheetah-Vel", doc="docs/cheetah_vel_published.md",
                          columns=6, rows=rows, readme_lines=readme_lines)  # fmt: skip
