"""Our rows of Ant-Goal's comparison with the published meta-RL results
(docs/ant_goal_published.md) and README's sentences on the run, regenerated between their markers
by `publish --task ant_goal` from the committed records in results/ant_goal/.

The published numbers are returns of PEARL's reward, which ours is (`docs/ant_goal.md`): our
records keep each policy's mean episode return (`return_mean`) beside the torso's final distance
to the goal, and the headlines over training seeds both (results/ant_goal/seeds.json)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bumps_jax.report import published
from bumps_jax.report.summary import load

SEEDS = "results/ant_goal/seeds.json"  # the headlines over training seeds (`report.seeds`)
RECORDS = {name: f"results/ant_goal/{name}.json" for name in ("experts", "table1", "table2", "baseline")}
NETS = ("meta_4x256", "meta_11x128")


def version(env: dict) -> str:
    """The env-version cell of our rows: the goals' disc and the episode."""
    return (f"ours: goals on a disc of radius {env['goal_radius']:g} m, {env['episode_steps']} steps of "
            f"{env['ctrl_dt']:g} s (`docs/ant_goal.md`)")  # fmt: skip


def over_seeds(seeds: dict, name: str) -> str:
    """A row's mean return over the seeds with every seed's, then its mean final distance."""
    ret, err = seeds["returns"][name], seeds["rows"][name]
    return f"{published.seeds_cell(ret, '', 0)} (final distance {err['mean']:.2f} m)"


def rows(root: str | Path = ".") -> list[str]:
    """Markdown table rows (the doc's six columns) for BUMPS unfiltered, BUMPS filtered and our
    multi-task PPO: returns over the training seeds where seeds.json holds them; every number a record's."""
    rec = {name: load(Path(root), rel) for name, rel in RECORDS.items()}
    experts, t1, t2, base = rec["experts"], rec["table1"], rec["table2"], rec["baseline"]
    seeds = load(Path(root), SEEDS)
    if not (experts and t1 and t2 and seeds and "returns" in seeds):
        return []
    n = len(experts["tasks_m"])
    per_expert, cloning = experts["env_steps_total"], t1["cloning"]["env_steps_total"]
    training = (f"{n * per_expert:,}: {n} experts x {per_expert:,} (PPO, the family's centre included), then "
                f"{cloning:,} env steps of episodes for cloning")  # fmt: skip
    episodes = (f"over {len(t2['tasks'])} test goals x {t1['eval']['repetitions']} episodes, mean of "
                f"{seeds['n_seeds']} training seeds")  # fmt: skip
    nets = "; ".join(f"{net}: {over_seeds(seeds, net)}" for net in NETS)
    out = [
        f"| BUMPS unfiltered (context = goal) | {nets}; {episodes} | none: the goal is the context | {training} "
        f"| {version(t1['env'])} | `{SEEDS}` |",
    ]
    filtered = [name for name in t2["rows"] if name in seeds["returns"]]
    per_task = {name: t2["rows"][name]["rollouts"] / t2["rows"][name]["n_tasks"] for name in filtered}
    out.append(
        f"| BUMPS filtered (a context chosen per test goal by rollouts of candidates) | "
        f"{'; '.join(f'{name}: {over_seeds(seeds, name)}' for name in filtered)}; fresh episodes, not the "
        f"selection's | the selection rollouts of the test goal, {t2['env']['episode_steps']} steps each (seed 0: "
        f"{', '.join(f'{per_task[name]:.0f}' for name in filtered)} per goal) | as unfiltered | {version(t2['env'])} "
        f"| `{SEEDS}` |"
    )
    if base:
        returns = [s["return_mean"] for s in base["per_seed"]]
        score = (f"{np.mean(returns):.0f} (seeds: {', '.join(f'{r:.0f}' for r in returns)}; final distance "
                 f"{base['error_mean_m']:.2f} m)")  # fmt: skip
        out.append(published.baseline_row(base, score, "goal", "test goals", version(base["env"]), RECORDS["baseline"]))
    return out


def readme_lines(root: str | Path = ".") -> list[str]:
    """README's sentences on the published Ant-Goal runs: the headlines over seeds, the baseline,
    how far the goals lie; every number a record's; none without the records."""
    root = Path(root)
    experts, t2, base = (load(root, RECORDS[k]) for k in ("experts", "table2", "baseline"))
    seeds = load(root, SEEDS)
    if not (experts and t2 and seeds):
        return []
    away = float(np.linalg.norm(np.asarray(t2["tasks"], np.float64), axis=1).mean())
    out = [f"The paper preset's {seeds['n_seeds']} training seeds on {seeds['device']} ({seeds['env']['impl']}) took "
           f"{seeds['wall_s']:.0f} s of stage time in all (`{SEEDS}`).",
           f"Its {len(t2['tasks'])} test goals lie {away:.2f} m from the start on average (the experts are scored "
           f"on their own {len(experts['tasks_m'])} training goals); an error is the torso's final distance to the "
           "goal.", published.seeds_sentence(seeds, SEEDS)]  # fmt: skip
    if base:
        total = experts["env_steps_total"] * len(experts["tasks_m"])
        out.append(f"The multi-task PPO baseline ({base['seeds']} seeds of {base['env_steps_per_seed'] / 1e6:.1f} M "
                   f"env steps; the {len(experts['tasks_m'])} experts: {total / 1e6:.1f} M in all) ends "
                   f"{base['error_mean_m']:.2f} m from its goals, {base['start']['error_mean_m']:.2f} m at its start "
                   "(`results/ant_goal/baseline.json`).")  # fmt: skip
    if base and "returns" in seeds:
        best = published.best_filtered(seeds["rows"])
        out.append(f"Mean episode returns of PEARL's reward: {best} {seeds['returns'][best]['mean']:.0f}, the "
                   f"baseline {np.mean([s['return_mean'] for s in base['per_seed']]):.0f}; the published ones "
                   "beside them in `docs/ant_goal_published.md`.")  # fmt: skip
    return out


BLOCKS = published.Blocks(task="ant_goal", title="Ant-Goal", doc="docs/ant_goal_published.md", columns=6,
                          rows=rows, readme_lines=readme_lines)  # fmt: skip
