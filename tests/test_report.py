"""The report puts our numbers beside the paper's and names stages that did not run."""

import json
import re
from pathlib import Path

import pytest

from bumps_jax import config, runio
from bumps_jax.report import publish, published, tables
from bumps_jax.report import readme as readme_table
from bumps_jax.report import summary as report
from bumps_jax.tasks.ant_goal import table as ant_table
from bumps_jax.tasks.cheetah_vel import table as cheetah_table

ROOT = Path(__file__).resolve().parent.parent


def _common(preset="tiny", **env):
    return {
        **runio.provenance(
            preset, 12.0, config.resolved_env(config.make_config("tiny", env)), command="python -m bumps_jax demo"
        )
    }


def test_report_fills_tables_and_names_missing_stages(tmp_path):
    (tmp_path / "meta").mkdir()
    rows = {
        name: {"accuracy_mean": 0.9, "accuracy_std": 0.05, "error_mean_m": 0.5, "error_std_m": 0.1,
               "error_mean_all_m": 0.6}
        for name in ("experts", "meta_4x256", "meta_11x128")
    }  # fmt: skip
    (tmp_path / "meta" / "table1.json").write_text(json.dumps({**_common(), "rows": rows}))
    text = report.build(tmp_path)
    assert "CPU-sized numbers" in text
    assert "| meta_4x256 | 0.90 +- 0.05 | 0.84 +- 0.10 | 0.50 +- 0.10 | 0.72 +- 0.25 | 0.60 |" in text
    assert "| filter | not run | | |" in text
    assert "| filtered_ensemble |  | not run | 0.40 +- 0.11 |  | 3.3% +- 1.1 |" in text


def test_report_counts_the_experts_env_steps_and_shows_their_starting_kicks(tmp_path):
    row = {"accuracy_mean": 0.5, "accuracy_std": 0.1, "error_mean_m": 1.25, "error_std_m": 0.5,
           "error_mean_all_m": 1.5}  # fmt: skip
    experts = {**_common(), "tasks_m": [7.0, 7.5], "env_steps": 1000, "accuracy_mean": 1.0, "accuracy_std": 0.0,
               "error_mean_m": 0.3, "error_std_m": 0.1, "error_mean_all_m": 0.3, "starting_kicks": row,
               "env_steps_breakdown": {"prior": 300, "tuning": 50, "ppo": 1000},
               "starting_kicks_smoothness": {"jump": 1.5, "param": "back_knee", "between_m": [7.0, 7.5]},
               "starting_kicks_midpoints": {**row, "targets_above_2m": 0,
                                            "per_task": [{"target_m": 7.25, "error_mean_m": 1.5}]}}  # fmt: skip
    runio.write_json(tmp_path / "experts" / "experts.json", experts)
    text = report.build(tmp_path)
    assert "| starting kicks (before PPO) | 0.50 +- 0.10 | - | 1.25 +- 0.50 | - | 1.50 |" in text
    assert "share of the kick prior 300, starting-kick tuning 50, PPO 1,000; 1,350 in all." in text
    assert "All 2 experts: 2,700 (PPO 2,000)." in text
    assert "neighbouring tasks' starting kicks: 1.50 scale units of `back_knee`, 7 -> 7.5 m." in text
    midpoints = "mixed 50/50): error 1.50 m over 1 midpoints, 0 above 2 m, the worst 1.50 m at 7.25 m."
    assert midpoints in text
    # experts.md says the same under the experts' row.
    md = tables.experts_markdown({**experts, "rel_error_mean": 0.03, "tasks_above_threshold": 2, "n_tasks": 2,
                                  "n_reps": 2, "per_task": []})  # fmt: skip
    assert "starting kicks (before PPO): accuracy 0.50 +- 0.10, error 1.25 +- 0.50 m (1.50 m over all tasks)." in md
    assert "1.50 scale units of `back_knee`, 7 -> 7.5 m." in md and midpoints in md
    runs = {"kept": 1, "fresh_costs": [0.61, 0.4, 0.55]}  # `tune.restarts` = 3
    assert "Tuning runs" not in md
    md = tables.experts_markdown({**experts, "rel_error_mean": 0.03, "tasks_above_threshold": 2, "n_tasks": 2,
                                  "n_reps": 2, "per_task": [], "starting_kicks_tuning_runs": runs})  # fmt: skip
    assert "Tuning runs' mean fresh cost: 0.610, 0.400, 0.550; kept run 2 of 3." in md
    mixed = {**runs, "kept": None, "runs_kept": [1, 3, 0, 3], "polish_improved": 2}  # `tune.keep` = "task"
    assert tables.tuning_runs_line(mixed) == (
        "Tuning runs' mean fresh cost: 0.610, 0.400, 0.550; each task kept its cheapest kick: run 1 for 1, "
        "run 3 for 2, its start for 1; the polish improved 2 of 4."
    )
    chained = {**runs, "kept": None, "runs_kept": [1, 1, 0, 3], "keep": "chain"}  # `tune.keep` = "chain"
    assert tables.tuning_runs_line(chained) == (
        "Tuning runs' mean fresh cost: 0.610, 0.400, 0.550; each task kept its kicks chosen together with the "
        "neighbour leash: run 1 for 2, run 3 for 1, its start for 1."
    )
    runio.write_json(tmp_path / "experts" / "experts.json", {**experts, "starting_kicks_tuning_runs": runs})
    assert "Tuning runs' mean fresh cost: 0.610, 0.400, 0.550; kept run 2 of 3." in report.build(tmp_path)
    # A prior record that does not say how it was made leaves its share unknown, not zero.
    runio.write_json(tmp_path / "experts" / "experts.json",
                     {**experts, "env_steps_breakdown": {"prior": None, "tuning": 50, "ppo": 1000}})  # fmt: skip
    assert "share of the kick prior not recorded, starting-kick tuning 50, PPO 1,000; 1,050 in all" in report.build(
        tmp_path
    )


def test_empty_run_dir_says_so(tmp_path):
    assert "No stage has written results" in report.build(tmp_path)


def test_a_run_of_the_baseline_alone_is_reported_as_its_task(tmp_path):
    """A run directory holding only another task's baseline: its task's report, its stage named."""
    committed = json.loads((ROOT / "results" / "cheetah_vel" / "baseline.json").read_text())
    runio.write_json(tmp_path / "baseline" / "baseline.json", {**committed, "wall_s": 517.0})
    text = publish.write_report(tmp_path).read_text()
    assert text.startswith(f"# BUMPS on cheetah_vel: run `{tmp_path.name}`") and "No stage has written" not in text
    assert re.search(r"\| baseline \| 517 \|", text) and "| experts | not run |" in text


def test_a_kick_run_of_the_baseline_alone_is_reported_with_its_baseline(tmp_path):
    """The kick's report of a run holding only its baseline (one seed): the stage's row and its
    section, not 'no stage has written results'; `report` accepts the directory."""
    committed = json.loads((ROOT / "results" / "baseline.json").read_text())
    runio.write_json(tmp_path / "baseline" / "baseline.json", {**committed, "seeds": 1, "wall_s": 1957.0})
    assert report.has_results(tmp_path)
    text = publish.write_report(tmp_path).read_text()
    assert text.startswith(f"# BUMPS on the simulated NAO: run `{tmp_path.name}`") and "No stage has" not in text
    assert re.search(r"\| baseline \| 1957 \|", text) and "| experts | not run |" in text
    assert f"U[7, 18] m, 1 seed, {committed['env_steps']:,} env steps per seed: meta-test error" in text


def _paper_run(tmp_path):
    """A run directory with every stage's results, a pipeline record and a baseline."""
    run = tmp_path / "run"
    for sub in ("prior", "experts", "meta", "filter", "baseline"):
        (run / sub).mkdir(parents=True)
    common = _common("paper")
    sweep = [{"strength": 1.0, "distance_m": 5.8, "valid_fraction": 1.0},
             {"strength": 1.5, "distance_m": 21.4, "valid_fraction": 1.0}]  # fmt: skip
    prior = {**common, "target_m": 12.0, "n_reps": 100, "mean_error_m": 0.68, "valid_fraction": 1.0,
             "fallen_fraction": 0.0, "sweep": sweep}  # fmt: skip
    (run / "prior" / "kick_prior.json").write_text(json.dumps(prior))
    experts = {**common, "tasks_m": [7.0, 7.5], "env_steps": 1000, "wall_s": 10.0, "accuracy_mean": 1.0,
               "accuracy_std": 0.0, "error_mean_m": 0.8, "error_std_m": 0.3, "per_task": []}  # fmt: skip
    (run / "experts" / "experts.json").write_text(json.dumps(experts))
    row = {"accuracy_mean": 0.9, "accuracy_std": 0.05, "error_mean_m": 0.5, "error_std_m": 0.1, "error_mean_all_m": 0.6}
    (run / "meta" / "table1.json").write_text(json.dumps({**common, "rows": {"meta_4x256": row}}))
    row2 = {"error_mean_m": 0.9, "error_std_m": 0.4, "rel_error_mean": 0.07, "rel_error_std": 0.02, "n_contexts": 110}
    (run / "filter" / "table2.json").write_text(json.dumps({**common, "rows": {"filtered_ensemble": row2}}))
    (run / "filter" / "context_map.png").write_bytes(b"\x89PNG fake")
    baseline = {**common, "seeds": 6, "env_steps": 2000, "error_mean_m": 3.5, "accuracy_mean": 0.8,
                "eval_tasks": [7.1, 7.2]}  # fmt: skip
    (run / "baseline" / "baseline.json").write_text(json.dumps(baseline))
    pipeline = {**common, "stages_s": {"prior": 5.0, "experts": 60.0, "meta": 10.0, "filter": 10.0, "baseline": 5.0},
                "wall_s": 90.0,
                "overrides": {"experts.ppo.total_env_steps": "1000"}}  # fmt: skip
    (run / "pipeline.json").write_text(json.dumps(pipeline))
    return run


def test_a_launched_run_leads_with_its_wall_time_not_the_sum_of_its_stages():
    launch = {
        "processes": 4,
        "wall_s": 1130.0,
        "finished": True,
        "phases": [
            [{"stages": ["prior"], "processes": 4}],
            [{"stages": ["experts", "meta"], "processes": 3}, {"stages": ["baseline"], "processes": 1}],
        ],
    }
    pipeline = {"stages_s": {"prior": 210.0, "experts": 557.0, "meta": 266.0, "baseline": 878.0}, "wall_s": 1911.0,
                "calls": 3, "device": "d", "launches": [launch]}  # fmt: skip
    text = "\n".join(report.pipeline_lines(pipeline))
    assert "31.9 min of stages, added up (prior 210 s" in text and "**31.9" not in text
    assert "one call; stages side by side add up to more than the wall time below" in text
    assert ("Launched as 4 processes (prior on 4; then experts, meta on 3 beside baseline on 1): **18.8 min** from "
            "start to end (one call;") in text  # fmt: skip


def test_report_shows_pipeline_time_and_baseline(tmp_path):
    text = report.build(_paper_run(tmp_path))
    assert "**1.5 min** in all (prior 5 s, experts 60 s, meta 10 s, filter 10 s, baseline 5 s" in text
    # The baseline ran as a stage of the pipeline: its row in the stages' table, counted in the sum.
    assert "\n| baseline | " in text.split("## Stages")[1].split("**sum")[0]
    assert "6 seeds, 2,000 env steps per seed: meta-test error 3.50 m" in text
    assert "BUMPS's experts used 2,000 PPO env steps in all (2 experts of 1,000); the baseline 12,000" in text
    assert "Best BUMPS variant (filtered_ensemble): 0.90 m against the baseline's 3.50 m" in text
    assert "| filtered_ensemble | 110 | 0.90 +- 0.40 | 0.40 +- 0.11 | 7.0% +- 2.0 |" in text


def test_publish_copies_a_run_and_rebuilds_results_md(tmp_path):
    run = _paper_run(tmp_path)
    (run / "prior" / "kick_prior_asset.json").write_text('{"params": "the run\'s own prior"}')
    (run / "prior" / "kick_prior_timing.json").write_text('{"wall_s": 1.0}')
    root = tmp_path / "repo"
    written = {p.relative_to(root).as_posix() for p in publish.publish(run, root)}
    assert {"results/kick_prior.json", "results/experts.json", "results/table1.json", "results/table2.json",
            "results/baseline.json", "results/pipeline.json", "docs/context_map.png",
            "docs/results.md", "assets/kick_prior.json", "benchmarks/results/kick_prior.json"} <= written  # fmt: skip
    # The committed asset becomes the prior this run's experts started from.
    assert (root / "assets" / "kick_prior.json").read_text() == '{"params": "the run\'s own prior"}'
    text = (root / "docs" / "results.md").read_text()
    assert "one `python -m bumps_jax reproduce --preset paper`" in text
    assert "`experts.ppo.total_env_steps=1000`" in text
    assert "![docs/context_map.png](context_map.png)" in text
    # The prior is the run's own, not whatever an older run left in results/.
    assert "12 m prior over 100 noisy kicks: mean error 0.68 m" in text


def test_results_md_names_the_stages_a_partial_pipeline_did_not_run(tmp_path):
    run = _paper_run(tmp_path)
    record = json.loads((run / "pipeline.json").read_text())
    record.update(
        stages_s={"experts": 60.0, "meta": 10.0, "filter": 10.0}, command="python -m bumps_jax reproduce --stages x"
    )
    (run / "pipeline.json").write_text(json.dumps(record))
    prior = json.loads((run / "prior" / "kick_prior.json").read_text())
    (run / "prior" / "kick_prior.json").write_text(
        json.dumps({**prior, "command": "make kick-prior", "date": "2026-01-02T00"})
    )
    root = tmp_path / "repo"
    publish.publish(run, root)
    text = (root / "docs" / "results.md").read_text()
    assert "one `python -m bumps_jax reproduce" not in text
    assert "The pipeline did not run the other stages; their records (the same preset and env config)" in text
    assert "prior: `make kick-prior` (2026-01-02)" in text
    assert "baseline: `python -m bumps_jax demo`" in text


def test_publish_refuses_an_empty_run(tmp_path):
    import pytest

    (tmp_path / "run").mkdir()
    with pytest.raises(ValueError, match="no stage results"):
        publish.publish(tmp_path / "run", tmp_path / "repo")


def test_records_of_different_physics_are_flagged(tmp_path):
    (tmp_path / "experts").mkdir()
    (tmp_path / "baseline").mkdir()
    experts_record = {**_common("paper"), "tasks_m": [7.0], "env_steps": 75, "accuracy_mean": 1.0, "accuracy_std": 0.0,
                      "error_mean_m": 0.4, "error_std_m": 0.1, "error_mean_all_m": 0.4, "wall_s": 5.0}  # fmt: skip
    (tmp_path / "experts" / "experts.json").write_text(json.dumps(experts_record))
    text = report.build(tmp_path)
    assert "| experts | 5 | 2.5 ms, warp |" in text and "not comparable" not in text
    baseline = {**_common("paper", **{"env.physics_dt": 0.005}), "seeds": 1, "env_steps": 75, "eval_tasks": [7.1],
                "error_mean_m": 2.0, "accuracy_mean": 1.0}  # fmt: skip
    (tmp_path / "baseline" / "baseline.json").write_text(json.dumps(baseline))
    text = report.build(tmp_path)
    assert "different physics (experts 2.5 ms, warp, baseline 5 ms, warp): they are not comparable" in text
    assert "physics step 5 ms, warp)." in text
    assert report.physics_step({"physics_dt_s": 0.005}) == "5 ms, backend not recorded"
    assert report.physics_step({"device": "cpu"}) == "not recorded"


def test_readme_results_table_is_the_committed_records():
    """Every number of README's results table is its record's, rounded as shown; the table is
    exactly what `publish` generates from results/*.json."""
    readme = (ROOT / "README.md").read_text()
    start, end = (
        readme.index(readme_table.README_BEGIN),
        readme.index(readme_table.README_END) + len(readme_table.README_END),
    )
    assert readme[start:end] == readme_table.readme_table(ROOT)
    rows, over_seeds = {}, {}
    for line in readme[start:end].splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) == 6 and cells[5].startswith("`results/"):  # with the seeds' column
            over_seeds[cells[0]] = cells[1]
            cells = [cells[0], *cells[2:]]
        if len(cells) == 5 and cells[4].startswith("`results/"):
            rows[cells[0]] = (cells[1], json.loads((ROOT / cells[4].strip("`")).read_text()))
    assert len(rows) >= 6, rows

    def numbers(text):
        return [float(x) for x in re.findall(r"\d+\.\d+", text)]

    if (ROOT / "results" / "seeds.json").exists():  # each headline's mean and std over the seeds
        seeds = json.loads((ROOT / "results" / "seeds.json").read_text())["rows"]
        assert numbers(over_seeds["experts on their own tasks (accuracy; error)"]) == [
            round(seeds["experts"][k], 2) for k in ("mean", "std")
        ]
        (label, cell), *_ = [(k, v) for k, v in over_seeds.items() if k.startswith("BUMPS filtered")]
        names = label.removeprefix("BUMPS filtered: ").removesuffix(" (error)").split(" / ")
        assert numbers(cell) == [round(seeds[n][k], 2) for n in names for k in ("mean", "std")]
        assert over_seeds[next(k for k in over_seeds if k.endswith("noisy kicks"))] == "-"

    ours, record = rows["experts on their own tasks (accuracy; error)"]
    assert numbers(ours) == [round(record[k], 2) for k in ("accuracy_mean", "error_mean_m", "error_std_m")]
    for net in ("4x256", "11x128"):
        ours, record = rows[f"meta-policy {net}, unfiltered (accuracy; error)"]
        row = record["rows"][f"meta_{net}"]
        assert numbers(ours)[:2] == [round(row["accuracy_mean"], 2), round(row["error_mean_m"], 2)]
    (label, (ours, record)), *_ = [(k, v) for k, v in rows.items() if k.startswith("BUMPS filtered")]
    names = label.removeprefix("BUMPS filtered: ").removesuffix(" (error)").split(" / ")
    assert numbers(ours) == [round(record["rows"][n]["error_mean_m"], 2) for n in names]
    ours, record = next(v for k, v in rows.items() if k.endswith("noisy kicks"))
    assert numbers(ours) == [round(record["mean_error_m"], 2), round(record["valid_fraction"], 2)]
    ours, record = next(v for k, v in rows.items() if k.startswith("multi-task PPO baseline"))
    start_error = record["start"]["error_mean_all_m"]
    assert numbers(ours) == [round(x, 2) for x in (start_error, record["error_mean_m"], record["accuracy_mean"])]


def test_records_of_different_env_configs_name_the_differing_keys(tmp_path):
    (tmp_path / "experts").mkdir()
    (tmp_path / "meta").mkdir()
    row = {"accuracy_mean": 0.9, "accuracy_std": 0.05, "error_mean_m": 0.5, "error_std_m": 0.1}
    experts = {**_common("paper"), "tasks_m": [7.0], "env_steps": 75, **row, "wall_s": 5.0}
    (tmp_path / "experts" / "experts.json").write_text(json.dumps(experts))
    meta = {**_common("paper", **{"env.noise.friction": 0.2, "env.impl": "jax"}), "rows": {"meta_4x256": row}}
    (tmp_path / "meta" / "table1.json").write_text(json.dumps(meta))
    text = report.build(tmp_path)
    assert "experts, meta ran under different env configs (differing: env.impl, env.noise.friction)" in text


def test_cheetah_rows_are_the_records_and_replace_only_their_block(tmp_path):
    env = {"episode_steps": 200, "task_range": [0.0, 3.0], "ctrl_dt": 0.05, "reward": {"velocity": 1.0, "ctrl": 0.05}}
    net = {"error_mean_m": 0.4, "n_tasks": 30}
    records = {
        "experts": {"env": env, "tasks_m": [0.0, 1.5, 3.0], "env_steps_total": 1000},
        "table1": {
            "env": env,
            "rows": {"experts": {"error_mean_m": 0.3, "n_tasks": 3}, "meta_4x256": net},
            "eval": {"repetitions": 20},
            "dataset_pairs": 600,
        },  # fmt: skip
        "table2": {"env": env, "rows": {"filtered_4x256": {"error_mean_m": 0.25, "rollouts": 600, "n_tasks": 30}}},
        "baseline": {
            "env": env,
            "error_mean_m": 0.05,
            "seeds": 2,
            "per_seed": [{"error_mean_m": 0.04}, {"error_mean_m": 0.06}],
            "eval_tasks": [1.0] * 30,
            "eval_repetitions": 20,
            "env_steps_per_seed": 3000,
        },  # fmt: skip
    }
    for name, record in records.items():
        runio.write_json(tmp_path / cheetah_table.RECORDS[name], record)
    rows = cheetah_table.rows(tmp_path)
    # Speed terms: -200 steps x each record's mean speed error; the env steps are the records' own.
    assert "4x256: -80 (mean speed error 0.40 m/s)" in rows[0] and "over 30 test velocities" in rows[0]
    assert "3,000: 3 experts x 1,000 (PPO, the family's shared start included), then 600 env steps" in rows[0]
    assert "filtered_4x256: -50 (0.25 m/s; 20 selection rollouts per task)" in rows[1]
    assert "speed term -10 (mean speed error 0.050 m/s, mean of 2 seeds: 0.040, 0.060)" in rows[2]
    doc = tmp_path / cheetah_table.BLOCKS.doc
    doc.parent.mkdir(parents=True)
    doc.write_text(f"before\n{cheetah_table.BLOCKS.begin}\nstale row\n{published.END}\nafter\n")
    cheetah_table.BLOCKS.write(tmp_path)
    assert doc.read_text() == f"before\n{cheetah_table.BLOCKS.block(tmp_path)}\nafter\n"
    assert "stale" not in doc.read_text()
    doc.write_text("no markers\n")
    with pytest.raises(ValueError, match="has no generated rows"):
        cheetah_table.BLOCKS.write(tmp_path)


def test_committed_cheetah_rows_are_the_committed_records():
    text = Path(cheetah_table.BLOCKS.doc).read_text()
    assert cheetah_table.BLOCKS.block() in text
    # README's sentences on the run are generated from the same records, each number its record's.
    readme = (ROOT / "README.md").read_text()
    assert cheetah_table.BLOCKS.readme_block(ROOT) in readme
    lines = cheetah_table.readme_lines(ROOT)
    baseline = json.loads((ROOT / "results" / "cheetah_vel" / "baseline.json").read_text())
    seeds = json.loads((ROOT / "results" / "cheetah_vel" / "seeds.json").read_text())
    assert len(lines) == 4 and f"errs {baseline['error_mean_m']:.2f} m/s" in lines[3]
    assert f"baseline ({baseline['device']})" in lines[3]  # its run's device: it may not be the stages'
    pipe = json.loads((ROOT / "results" / "cheetah_vel" / "pipeline.json").read_text())
    assert f"({', '.join(pipe['stages_s'])};" in lines[0]  # the stages its time counts
    # The headlines over seeds: each row's mean, then every seed's value.
    assert f"Over {seeds['n_seeds']} training seeds" in lines[2]
    per_seed = ", ".join(f"{v:.2f}" for v in seeds["rows"]["experts"]["per_seed"])
    assert f"experts {seeds['rows']['experts']['mean']:.2f} +- " in lines[2] and f"({per_seed})" in lines[2]


def test_span_names_one_value_where_the_ends_round_alike():
    assert published.span([0.301, 0.304, 0.2996]) == "0.30"
    assert published.span([0.29, 0.351]) == "0.29-0.35"
    assert published.span([1.2345, 1.2349], digits=3) == "1.234-1.235"


def test_readme_cheetah_sentences_follow_their_records(tmp_path):
    import shutil

    shutil.copytree(ROOT / "results" / "cheetah_vel", tmp_path / "results" / "cheetah_vel")
    path = tmp_path / "results" / "cheetah_vel" / "baseline.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), "error_mean_m": 0.777}))
    blocks = cheetah_table.BLOCKS
    (tmp_path / "README.md").write_text(f"a\n{blocks.readme_begin}\nold\n{blocks.readme_end}\nb\n")
    cheetah_table.BLOCKS.write_readme(tmp_path)
    text = (tmp_path / "README.md").read_text()
    assert "errs 0.78 m/s" in text and "old" not in text and text.startswith("a\n") and text.endswith("b\n")
    (tmp_path / "results" / "cheetah_vel" / "pipeline.json").unlink()
    assert not any("stage time" in line for line in cheetah_table.readme_lines(tmp_path))
    shutil.rmtree(tmp_path / "results")
    assert "No HalfCheetah-Vel run is published yet" in cheetah_table.BLOCKS.readme_block(tmp_path)


def test_ant_rows_are_returns_over_seeds_from_their_records(tmp_path):
    env = {"goal_radius": 3.0, "episode_steps": 200, "ctrl_dt": 0.05}

    def spread(*values):
        return {"mean": sum(values) / len(values), "std": 1.0, "per_seed": list(values)}

    records = {
        "experts": {"tasks_m": [[0.0, 0.0], [1.0, 0.0]], "env_steps_total": 1000},
        "table1": {"env": env, "cloning": {"env_steps_total": 600}, "eval": {"repetitions": 20}},
        "table2": {"env": env, "tasks": [[3.0, 4.0]] * 30,
                   "rows": {"filtered_4x256": {"rollouts": 600, "n_tasks": 30, "error_mean_m": 1.0}}},
        "baseline": {"env": env, "seeds": 2, "per_seed": [{"return_mean": -600.0}, {"return_mean": -620.0}],
                     "error_mean_m": 1.9, "start": {"error_mean_m": 2.8}, "eval_tasks": [[1.0, 0.0]] * 30,
                     "eval_repetitions": 20, "env_steps_per_seed": 2000},
    }  # fmt: skip
    for name, record in records.items():
        runio.write_json(tmp_path / ant_table.RECORDS[name], record)
    assert ant_table.rows(tmp_path) == [] and ant_table.readme_lines(tmp_path) == []  # no seeds.json yet
    runio.write_json(tmp_path / ant_table.SEEDS, {
        "n_seeds": 2, "unit": "m", "device": "GPU", "env": {"impl": "warp"}, "wall_s": 120.0,
        "rows": {"experts": spread(0.5, 1.5), "meta_4x256": spread(1.0, 2.0), "meta_11x128": spread(1.2, 2.2),
                 "filtered_4x256": spread(0.8, 1.8)},
        "returns": {"meta_4x256": spread(-300.0, -500.0), "meta_11x128": spread(-310.0, -510.0),
                    "filtered_4x256": spread(-280.0, -480.0)},
    })  # fmt: skip
    rows = ant_table.rows(tmp_path)
    assert "meta_4x256: -400 +- 1 (-300, -500) (final distance 1.50 m)" in rows[0]
    assert "2,000: 2 experts x 1,000 (PPO, the family's centre included), then 600 env steps" in rows[0]
    assert "filtered_4x256: -380 +- 1 (-280, -480) (final distance 1.30 m)" in rows[1] and "20 per goal" in rows[1]
    assert "| -610 (seeds: -600, -620; final distance 1.90 m)" in rows[2] and "2,000 per seed" in rows[2]
    lines = ant_table.readme_lines(tmp_path)
    assert lines[0].startswith("The paper preset's 2 training seeds on GPU (warp) took 120 s of stage time")
    assert lines[1].startswith("Its 30 test goals lie 5.00 m from the start on average")
    assert "filtered_4x256, the best filtered variant on the mean, 1.30 +- 1.00 m (0.80, 1.80)" in lines[2]
    assert "ends 1.90 m from its goals, 2.80 m at its start" in lines[3]
    assert lines[4].startswith("Mean episode returns of PEARL's reward: filtered_4x256 -380, the baseline -610")


def test_committed_ant_rows_and_readme_lines_are_the_committed_records():
    assert ant_table.BLOCKS.block(ROOT) in (ROOT / ant_table.BLOCKS.doc).read_text()
    assert ant_table.BLOCKS.readme_block(ROOT) in (ROOT / "README.md").read_text()
    seeds = json.loads((ROOT / ant_table.SEEDS).read_text())
    assert seeds["n_seeds"] >= 2 and set(seeds["returns"]) >= {"meta_4x256", "filtered_ensemble"}


def test_the_speed_section_reads_the_gae_record_and_says_which_is_older():
    bench = {**_common("paper"), "date": "2026-11-23T10:00:00+00:00", "experts_env_steps_per_s": 250_000.0}
    gae = {**_common("paper"), "date": "2026-11-24T10:00:00+00:00", "experts_env_steps_per_s_gae_loop": 300_000.0,
           "experts_env_steps_per_s_gae_unrolled": 450_000.0, "experts_gae_unrolled_vs_loop": 1.5,
           "experts_ppo_projected_s_gae_loop": 900.0, "experts_ppo_projected_s_gae_unrolled": 600.0}  # fmt: skip
    text = "\n".join(report.speed_lines(bench, [], gae))
    assert "300,000 env-steps/s as a device loop, 450,000 unrolled (1.50x)" in text
    assert "projected 900 s -> 600 s" in text and "The tables above are older than it" in text
    assert "older than it" not in "\n".join(report.speed_lines({**bench, "date": gae["date"]}, None, gae))
    assert "unroll_gae" not in "\n".join(report.speed_lines(bench, [], None))


def test_the_scale_out_line_names_its_physics():
    bench = {**_common("paper"), "date": "2026-11-23T10:00:00+00:00", "experts_env_steps_per_s": 250_000.0}
    scaling = {**_common("paper"), "env": {"physics_dt": 0.0025, "impl": "jax"}, "devices": 2, "workload": 8,
               "experts_env_steps_per_s": {"1": 100_000.0, "2": 190_000.0}, "experts_env_steps_speedup": 1.9,
               "filter_rollouts_speedup": 1.95, "command": "python benchmarks/scaling.py --devices 2"}  # fmt: skip
    text = "\n".join(report.speed_lines(bench, [scaling]))
    assert "physics 2.5 ms, jax" in text and "190,000 env-steps/s on 2 devices vs 100,000 on one (1.90x)" in text
    assert "one process, a mesh of all" in text and "filtering 1.95x" in text
    assert "one process per device" in "\n".join(report.speed_lines(bench, [{**scaling, "layout": "processes"}]))
    # a run cut off before its filtering half says so, and each record gets its own sentence
    cut = {k: v for k, v in scaling.items() if k != "filter_rollouts_speedup"}
    text = "\n".join(report.speed_lines(bench, [scaling, {**cut, "workload": 32}]))
    assert text.count("Scale-out on") == 2 and "filtering not measured in this run, at 32 times" in text
    runs = [{"workload": 2, "experts_env_steps_speedup": 1.55, "filter_rollouts_speedup": 1.94},
            {"workload": 8, "experts_env_steps_speedup": 1.9, "filter_rollouts_speedup": 1.95}]  # fmt: skip
    text = "\n".join(report.speed_lines(bench, [{**scaling, "by_copies": runs}]))
    assert "The same run at other workloads: 2 times, experts 1.55x, filtering 1.94x." in text


def test_readme_findings_are_the_committed_records(tmp_path):
    """README's findings are exactly what `publish` generates from results/*.json, and they come
    from the records: another run's numbers give other sentences; a missing record drops its own."""
    import shutil

    readme = (ROOT / "README.md").read_text()
    start = readme.index(readme_table.FINDINGS_BEGIN)
    end = readme.index(readme_table.FINDINGS_END) + len(readme_table.FINDINGS_END)
    assert readme[start:end] == readme_table.findings_block(ROOT)
    assert len(readme_table.findings(ROOT)) == 7  # the seeds' spread, then one per record
    shutil.copytree(ROOT / "results", tmp_path / "results")
    path = tmp_path / "results" / "table1.json"
    table1 = json.loads(path.read_text())
    table1["rows"]["meta_4x256"]["error_mean_all_m"] = 0.777
    table1["rows"]["meta_4x256"]["per_task"][0]["error_mean_m"] = 2.5
    path.write_text(json.dumps(table1))
    (tmp_path / "results" / "baseline.json").unlink()
    lines = readme_table.findings(tmp_path)
    unfiltered = next(line for line in lines if line.startswith("- Unfiltered"))
    assert ": 0.78 / " in unfiltered and "not all within the paper's 0.72 / 0.68 m" in unfiltered
    assert "worst meta-test task 2.50 / " in unfiltered
    assert len(lines) == 6 and not any(line.startswith("- Baseline") for line in lines)


def _at_budget_run(tmp_path, per_seed: int, task: str = "kick"):
    """A run holding only a baseline of one seed at `per_seed` env steps (the committed kick
    baseline's record otherwise), and a repository copy with the committed records and README."""
    import shutil

    root = tmp_path / "repo"
    shutil.copytree(ROOT / "results", root / "results")
    shutil.copyfile(ROOT / "README.md", root / "README.md")
    record = json.loads((ROOT / "results" / "baseline.json").read_text())
    updates = len(record["curve"]["env_steps"])
    step = 441_600  # 5,888 episodes of 75 steps an update
    curve = {**record["curve"], "env_steps": [step * (i + 1) for i in range(updates)]}
    command = "python -m bumps_jax reproduce --stages baseline --set baseline.seeds=1"
    record.update(seeds=1, env_steps=per_seed, env_steps_per_seed=per_seed, error_mean_m=0.301, curve=curve,
                  task=task, command=command)  # fmt: skip
    run = tmp_path / "run"
    runio.write_json(run / "baseline" / "baseline.json", record)
    return run, root


def _experts_total():
    """The committed kick experts' env steps in all, and the nearest whole number of updates of 441,600."""
    experts = json.loads((ROOT / "results" / "experts.json").read_text())
    total = len(experts["tasks_m"]) * sum(experts["env_steps_breakdown"].values())
    return total, round(total / 441_600) * 441_600


def test_a_baseline_at_bumps_budget_is_published_beside_the_presets_own(tmp_path):
    total, nearest = _experts_total()
    run, root = _at_budget_run(tmp_path, nearest)
    written = {p.relative_to(root).as_posix() for p in publish.publish_at_budget(run, "kick", root)}
    assert written == {"results/baseline_at_budget.json", "docs/baseline_at_budget_curve.png", "docs/results.md",
                       "README.md"}  # fmt: skip
    assert json.loads((root / "results" / "baseline_at_budget.json").read_text())["env_steps_per_seed"] == nearest
    text = (root / "docs" / "results.md").read_text()
    assert "At BUMPS' budget (`results/baseline_at_budget.json`, `python -m bumps_jax reproduce --stages" in text
    assert f"1 seed of {nearest:,} env steps (BUMPS' experts: {total:,} in all), 441,600 a PPO update" in text
    assert "meta-test error 0.30 m" in text
    assert "env steps a seed) and 0.30 m at BUMPS' budget on the same meta-test tasks." in text
    assert f"| baseline | multi-task PPO at BUMPS' experts' budget, per seed (1 seed) | {nearest:,} |" in text
    assert "![docs/baseline_at_budget_curve.png](baseline_at_budget_curve.png)" in text
    drawn = (root / "docs" / "baseline_at_budget_curve.png").read_bytes()  # drawn from the record
    assert drawn.startswith(b"\x89PNG") and len(drawn) > 10_000
    readme = (root / "README.md").read_text()
    assert f"| multi-task PPO baseline at BUMPS' budget (1 seed, {nearest / 1e6:.2f} M steps each), error |" in readme
    best = min(r["error_mean_m"] for r in json.loads((ROOT / "results" / "table2.json").read_text())["rows"].values())
    side = "below" if 0.301 < best else "above"  # the committed best filtered variant against the fixture's 0.301 m
    assert (f"at BUMPS' budget ({nearest / 1e6:.0f} M env steps, 1 seed) the baseline errs 0.30 m, {side} the best "
            f"BUMPS variant's {best:.2f} m (`results/baseline_at_budget.json`; docs/results.md") in readme  # fmt: skip
    # The paper preset's own baseline stays where it was.
    assert (root / "results" / "baseline.json").read_text() == (ROOT / "results" / "baseline.json").read_text()


def test_a_baseline_off_bumps_budget_or_of_another_task_is_refused_before_any_copy(tmp_path):
    run, root = _at_budget_run(tmp_path, 12_000_000)
    total, nearest = _experts_total()
    refused = (rf"ran 12,000,000 env steps per seed, not BUMPS' experts' {total:,} within one update "
               rf"\(441,600\): train it with baseline.ppo.total_env_steps={nearest}")  # fmt: skip
    with pytest.raises(ValueError, match=refused):
        publish.publish_at_budget(run, "kick", root)
    run, root = _at_budget_run(tmp_path / "other", nearest, task="cheetah_vel")
    committed = sorted((p.relative_to(root), p.read_bytes()) for p in root.rglob("*") if p.is_file())
    with pytest.raises(ValueError, match="cheetah_vel"):
        publish.publish_at_budget(run, "kick", root)
    assert sorted((p.relative_to(root), p.read_bytes()) for p in root.rglob("*") if p.is_file()) == committed


def test_the_at_budget_baseline_is_named_below_above_or_level_with_the_best_bumps_variant():
    best = ("filtered_ensemble", {"error_mean_m": 0.354})
    assert readme_table.than_best(0.272, best) == ", below the best BUMPS variant's 0.35 m"
    assert readme_table.than_best(0.412, best) == ", above the best BUMPS variant's 0.35 m"
    assert readme_table.than_best(0.351, best) == ", level with the best BUMPS variant's 0.35 m"
    assert readme_table.than_best(0.272, None) == ""


def test_a_tasks_report_leaves_out_the_stages_it_does_not_have(tmp_path, monkeypatch):
    # A task without a baseline stage was reported with "| baseline | not run |", as if it had one.
    import dataclasses

    from bumps_jax.report import task_report

    committed = json.loads((ROOT / "results" / "cheetah_vel" / "experts.json").read_text())
    runio.write_json(tmp_path / "experts" / "experts.json", committed)
    cheetah = task_report.tasks.get("cheetah_vel")
    assert "| baseline | not run |" in publish.write_report(tmp_path).read_text()
    lean = dataclasses.replace(cheetah, stages=("experts", "meta", "filter"))
    monkeypatch.setattr(task_report.tasks, "get", lambda name: lean if name == "cheetah_vel" else cheetah)
    text = publish.write_report(tmp_path).read_text()
    assert "| experts |" in text and "| meta | not run |" in text and "| baseline |" not in text
