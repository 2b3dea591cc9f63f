"""The run directory never mixes configs: manifests, --force, resume bookkeeping, inputs checked first.

The stages here are stand-ins (no simulation): what is tested is the runner around them.
"""

import json
import os
import signal
import time
import types
from pathlib import Path

import pytest

from bumps_jax import config, resumable, runio
from bumps_jax.pipeline import runner as pipeline
from bumps_jax.report import publish
from bumps_jax.report import summary as report


def fake_stage(name, log, upstream=None, fail=False):
    """A stage module that records its calls and writes its output (reading `upstream`'s, if any)."""

    def inputs(cfg, run_dir):
        if upstream is None:
            return {}
        path = Path(run_dir) / upstream / "out.json"
        runio.read_json(path, f"run {upstream} first")
        return {upstream: path}

    def run(cfg, run_dir, say=print):
        log.append(name)
        if fail:
            raise KeyboardInterrupt
        record = {"stage": name, "seed": cfg.experts.seed, "n": len(log)}
        return runio.write_json(Path(run_dir) / name / "out.json", record) and record

    return types.SimpleNamespace(OUTPUT="out.json", inputs=inputs, run=run)


@pytest.fixture
def stages(monkeypatch):
    log = []
    modules = {"experts": fake_stage("experts", log), "meta": fake_stage("meta", log, upstream="experts")}
    monkeypatch.setattr(pipeline, "stage_module", lambda name, task="kick": modules[name])
    monkeypatch.setattr(
        publish, "write_report", lambda run_dir: runio.write_text(Path(run_dir) / "report.md", "report\n")
    )
    return log, modules


def cfg(**overrides):
    return config.make_config("tiny", overrides)


def test_a_rerun_with_other_overrides_is_refused_naming_the_keys(tmp_path, stages):  # issue: defect 1
    log, _ = stages
    pipeline.run_stage("experts", cfg(), tmp_path)
    pipeline.run_stage("experts", cfg(), tmp_path)  # same config: up to date, not rerun
    assert log == ["experts"]
    other = cfg(**{"experts.ppo.learning_rate": 1e-3, "experts.seed": 7})
    with pytest.raises(pipeline.StaleRunError) as err:
        pipeline.run_stage("experts", other, tmp_path)
    assert "experts.ppo.learning_rate" in str(err.value) and "experts.seed" in str(err.value)
    assert "--force" in str(err.value) and "--run-dir" in str(err.value)
    assert json.loads((tmp_path / "experts" / "out.json").read_text())["seed"] == 0  # untouched
    pipeline.run_stage("experts", other, tmp_path, force=True)
    assert log == ["experts", "experts"]
    assert json.loads((tmp_path / "experts" / "out.json").read_text())["seed"] == 7


def test_a_damaged_record_of_a_finished_stage_says_how_to_redo_it(tmp_path, stages):
    log, _ = stages
    pipeline.run_stage("experts", cfg(), tmp_path)
    record = tmp_path / "experts" / "out.json"
    record.write_text('{"broken')
    with pytest.raises(ValueError) as err:
        pipeline.run_stage("experts", cfg(), tmp_path)
    message = str(err.value)
    assert "\n" not in message and str(record) in message and "cannot read it as JSON" in message
    assert "remove it and rerun to redo the stage" in message and log == ["experts"]
    record.unlink()  # as told: the stage is redone
    pipeline.run_stage("experts", cfg(), tmp_path)
    assert log == ["experts", "experts"] and json.loads(record.read_text())["stage"] == "experts"
    record.write_text("[]")  # the report names the file too
    with pytest.raises(ValueError, match=f"{record}: expected a JSON object"):
        report.load(tmp_path, "experts/out.json")


def test_a_damaged_manifest_or_timing_record_is_named_as_such(tmp_path, stages):
    log, _ = stages
    pipeline.run_pipeline(["experts"], cfg(), tmp_path)
    manifest, timing = tmp_path / "experts" / pipeline.MANIFEST, tmp_path / "pipeline.json"
    kept = manifest.read_text()
    manifest.write_text("xx")  # damaged, not "a run of another version"
    with pytest.raises(pipeline.StaleRunError, match=rf"{manifest} is damaged \(not JSON\): use a new --run-dir"):
        pipeline.run_stage("experts", cfg(), tmp_path)
    manifest.write_text(kept)
    timing.write_text("xx")
    with pytest.raises(ValueError, match=f"{timing}: cannot read it as JSON .*remove it to count them afresh"):
        pipeline.run_pipeline(["experts"], cfg(), tmp_path)
    timing.unlink()  # as told; every stage is done, so the new record times none
    pipeline.run_pipeline(["experts"], cfg(), tmp_path)
    assert log == ["experts"] and json.loads(timing.read_text()) == {"stages_s": {}}
    assert report.pipeline_lines(json.loads(timing.read_text())) == []  # no timing line, and no KeyError


def test_a_manifest_of_another_schema_is_refused_in_one_line(tmp_path, stages):
    """A stage manifest without `MANIFEST_SCHEMA` (an older version's, whose config tree had other
    keys) or with another is refused whole, in one line naming the file, the schemas and the two
    ways on, even where its config would otherwise match; --force recomputes it."""
    log, _ = stages
    pipeline.run_stage("experts", cfg(), tmp_path)
    manifest = tmp_path / "experts" / pipeline.MANIFEST
    current = json.loads(manifest.read_text())
    assert current["schema"] == pipeline.MANIFEST_SCHEMA == 3
    for schema, named in ((None, "no schema"), (1, "schema 1"), ("2", "schema '2'")):
        older = dict(current)
        if schema is None:
            del older["schema"]
        else:
            older["schema"] = schema
        manifest.write_text(json.dumps(older))
        with pytest.raises(pipeline.StaleRunError) as err:
            pipeline.run_stage("experts", cfg(), tmp_path)
        message = str(err.value)
        assert "\n" not in message and str(manifest) in message and named in message
        assert f"this version writes schema {pipeline.MANIFEST_SCHEMA}" in message
        assert "--run-dir" in message and "--force" in message
        assert log == ["experts"]  # refused before any work
    pipeline.run_stage("experts", cfg(), tmp_path, force=True)
    assert log == ["experts", "experts"]
    assert json.loads(manifest.read_text())["schema"] == pipeline.MANIFEST_SCHEMA
    current["config"]["experts"]["seed"] = 9  # the current schema, a key changed: refused by name
    manifest.write_text(json.dumps(current))
    with pytest.raises(pipeline.StaleRunError, match="experts.seed"):
        pipeline.run_stage("experts", cfg(), tmp_path)


def test_a_run_resumes_under_other_warp_buffer_sizes(tmp_path, stages):
    """Warp's buffer sizes change no physics: a stage made under one pool size is up to date
    under another (a smaller GPU, a larger batch); a physics key still makes it stale."""
    log, _ = stages
    pipeline.run_stage("experts", cfg(), tmp_path)
    pool = cfg().env.warp_contacts
    bigger = cfg(**{"env.warp_contacts": 2 * pool, "env.warp_constraints_per_world": 96})
    pipeline.run_stage("experts", bigger, tmp_path)
    assert log == ["experts"]
    with pytest.raises(pipeline.StaleRunError, match="env.physics_dt"):
        pipeline.run_stage("experts", cfg(**{"env.warp_contacts": 2 * pool, "env.physics_dt": 0.005}), tmp_path)


def test_publishing_checks_every_stage_the_run_holds_against_the_config(tmp_path, stages):
    """`publish` first checks the run's stages against the config it names (`check_current`):
    stages the run lacks are skipped; one made with another config stops it, naming the key."""
    pipeline.run_stage("experts", cfg(), tmp_path)
    pipeline.check_current(cfg(), tmp_path, ("experts", "meta", "filter"))
    with pytest.raises(pipeline.StaleRunError, match="experts.seed"):
        pipeline.check_current(cfg(**{"experts.seed": 7}), tmp_path, ("experts", "meta"))


def test_a_stage_whose_inputs_changed_is_refused(tmp_path, stages):  # defect 3
    log, _ = stages
    pipeline.run_stage("experts", cfg(), tmp_path)
    pipeline.run_stage("meta", cfg(), tmp_path)
    # The experts are replaced by another run's: the meta outputs were made from the old ones.
    runio.write_json(tmp_path / "experts" / "out.json", {"stage": "experts", "another": "run"})
    with pytest.raises(pipeline.StaleRunError, match="inputs.experts"):
        pipeline.run_stage("meta", cfg(), tmp_path)
    assert log == ["experts", "meta"]


def test_force_recomputes_every_later_stage(tmp_path, stages):
    log, _ = stages
    pipeline.run_pipeline(("experts", "meta"), cfg(), tmp_path)
    changed = cfg(**{"experts.seed": 3})
    with pytest.raises(pipeline.StaleRunError):  # refused before any stage runs
        pipeline.run_pipeline(("experts", "meta"), changed, tmp_path)
    assert log == ["experts", "meta"]
    pipeline.run_pipeline(("experts", "meta"), changed, tmp_path, force=True)
    assert log == ["experts", "meta", "experts", "meta"]
    assert json.loads((tmp_path / "pipeline.json").read_text())["overrides"] == {"experts.seed": 3}


def test_a_stage_that_changes_records_removes_the_report_made_from_them(tmp_path, stages):
    """--force on an earlier stage removes the later stages and the run's report (and its error map)
    with them, so no report shows a table whose record is gone; an up-to-date stage leaves it."""
    log, _ = stages
    pipeline.run_pipeline(("experts", "meta"), cfg(), tmp_path)
    report_md, figure = tmp_path / "report.md", tmp_path / "error_map.png"
    figure.write_bytes(b"png")
    said = []
    pipeline.run_stage("experts", cfg(), tmp_path, say=said.append)
    assert report_md.exists() and figure.exists() and said == [f"== experts: up to date ({tmp_path}/experts/out.json)"]
    pipeline.run_stage("experts", cfg(**{"experts.seed": 3}), tmp_path, force=True, say=lambda *a, **k: said.extend(a))
    assert not (tmp_path / "meta").exists() and not report_md.exists() and not figure.exists()
    removed = "removed (made before the records this stage writes; the report command writes it anew)"
    assert f"== report.md, error_map.png: {removed}" in said
    pipeline.run_stage("meta", cfg(**{"experts.seed": 3}), tmp_path)  # a new stage: no report to remove, none written
    assert log == ["experts", "meta", "experts", "meta"] and not report_md.exists()
    pipeline.run_pipeline(("experts", "meta"), cfg(**{"experts.seed": 3}), tmp_path)  # written anew at the end
    assert report_md.read_text() == "report\n"


def test_a_finished_stage_notes_a_change_of_its_tasks_code_and_stands(tmp_path, stages, monkeypatch):
    """A task's code edited since a stage ran (its folder's .py files): the stage is still up to
    date, its record kept, with one more line naming the folder, and --force redoes it; a
    manifest without the task's code (an older version's) gets no note, and --force leaves it."""
    log, _ = stages
    code = tmp_path / "code"
    (code / "sub").mkdir(parents=True)
    (code / "env.py").write_text("REWARD_SCALE = 1.0\n")
    (code / "sub" / "helpers.py").write_text("")
    monkeypatch.setattr(pipeline.tasks, "code_folder", lambda task: ("bumps_jax/tasks/kick/", code))
    run = tmp_path / "run"
    pipeline.run_stage("experts", cfg(), run)
    manifest = run / "experts" / pipeline.MANIFEST
    assert json.loads(manifest.read_text())["task_source"] == pipeline.task_source("kick")
    said = []
    pipeline.run_stage("experts", cfg(), run, say=said.append)
    (code / "notes.txt").write_text("not code")  # neither a file but .py nor a compiled one counts
    (code / "__pycache__").mkdir()
    (code / "__pycache__" / "env.cpython-311.pyc").write_bytes(b"\0")
    pipeline.run_stage("experts", cfg(), run, say=said.append)
    assert said == [f"== experts: up to date ({run}/experts/out.json)"] * 2
    (code / "env.py").write_text("REWARD_SCALE = 100.0\n")
    said.clear()
    assert pipeline.run_stage("experts", cfg(), run, say=said.append)["n"] == 1  # its record, not redone
    assert said == [
        f"== experts: up to date ({run}/experts/out.json)",
        "   note: bumps_jax/tasks/kick/ changed since this stage ran (its record stands; --force redoes it)",
    ]
    pipeline.run_stage("experts", cfg(), run, force=True, say=lambda *a, **k: None)  # as the note says
    assert json.loads(manifest.read_text())["task_source"] == pipeline.task_source("kick") and log == ["experts"] * 2
    pipeline.run_stage("experts", cfg(), run, force=True, say=lambda *a, **k: None)  # the same code: nothing to redo
    (code / "env.py").write_text("REWARD_SCALE = 1.0\n")
    older = json.loads(manifest.read_text())
    del older["task_source"]
    manifest.write_text(json.dumps(older))
    said.clear()
    pipeline.run_stage("experts", cfg(), run, force=True, say=said.append)
    assert said == [f"== experts: up to date ({run}/experts/out.json)"] and log == ["experts"] * 2


def test_a_tasks_code_digest_covers_its_python_files_by_path():
    """The digest of each registered task's folder: its .py files' paths and contents, so a file
    renamed or moved changes it as an edit does."""
    for task in pipeline.tasks.TASKS:
        shown, folder = pipeline.tasks.code_folder(task)
        assert shown == f"bumps_jax/tasks/{task}/" and (folder / "task.py").is_file()
        source = pipeline.task_source(task)
        assert source["path"] == shown and len(source["sha256"]) == 16
    assert len({pipeline.task_source(t)["sha256"] for t in pipeline.tasks.TASKS}) == len(pipeline.tasks.TASKS)


def test_the_pipeline_never_reports_up_to_date_over_stale_outputs(tmp_path, stages):  # defect 4
    log, _ = stages
    pipeline.run_pipeline(("experts", "meta"), cfg(), tmp_path)
    with pytest.raises(pipeline.StaleRunError, match=r"experts\.tasks"):
        pipeline.run_pipeline(("experts", "meta"), cfg(**{"experts.tasks": (9.0,)}), tmp_path)
    assert log == ["experts", "meta"]


def test_outputs_without_a_manifest_are_not_reused(tmp_path, stages):
    runio.write_json(tmp_path / "experts" / "out.json", {"made": "by an older version"})
    with pytest.raises(pipeline.StaleRunError, match="without a manifest"):
        pipeline.run_stage("experts", cfg(), tmp_path)


def test_a_missing_input_is_named_before_any_work(tmp_path, stages):  # defect 7
    log, _ = stages
    with pytest.raises(ValueError, match=r"experts/out.json: no such file \(run experts first\)"):
        pipeline.run_stage("meta", cfg(), tmp_path)
    (tmp_path / "experts").mkdir()
    (tmp_path / "experts" / "out.json").write_text('{"trunc')
    with pytest.raises(ValueError, match=r"experts/out.json: cannot read it as JSON"):
        pipeline.run_stage("meta", cfg(), tmp_path)
    assert log == []


def test_an_unwritable_run_directory_fails_at_once(tmp_path, stages):  # defects 6, 7
    log, _ = stages
    with pytest.raises(ValueError, match="is not writable"):
        pipeline.run_stage("experts", cfg(), Path("/dev/null/run"))
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(ValueError, match="is not writable"):
        pipeline.run_stage("experts", cfg(), blocker / "run")
    assert log == []


def test_pipeline_skips_finished_stages_and_counts_its_calls(tmp_path, stages, monkeypatch):
    log, modules = stages
    monkeypatch.setitem(modules, "meta", fake_stage("meta", log, upstream="experts", fail=True))
    with pytest.raises(KeyboardInterrupt):
        pipeline.run_pipeline(("experts", "meta"), cfg(), tmp_path)
    monkeypatch.setitem(modules, "meta", fake_stage("meta", log, upstream="experts"))
    pipeline.run_pipeline(("experts", "meta"), cfg(), tmp_path)
    assert log == ["experts", "meta", "meta"]  # the finished stage is not rerun
    record = json.loads((tmp_path / "pipeline.json").read_text())
    assert record["calls"] == 2 and set(record["stages_s"]) == {"experts", "meta"}
    assert record["env"]["physics_dt"] == 0.0025 and record["env"]["impl"] == "warp"
    assert record["wall_s"] == pytest.approx(sum(record["stages_s"].values()), abs=1e-3)
    assert record["overrides"] == {}
    assert "resumed across 2 calls" in report.pipeline_lines(record)[0]
    assert "in one call" in report.pipeline_lines({**record, "calls": 1})[0]


def test_a_stage_made_anew_counts_its_own_time_not_its_predecessors(tmp_path, stages):
    """--force recomputes the experts and removes the meta stage: neither adds its time to the
    seconds the replaced outputs took."""
    pipeline.run_pipeline(("experts", "meta"), cfg(), tmp_path)
    path = tmp_path / "pipeline.json"
    record = json.loads(path.read_text())
    record["stages_s"] = {"experts": 1000.0, "meta": 500.0}
    path.write_text(json.dumps(record))
    pipeline.run_pipeline(("experts", "meta"), cfg(**{"experts.seed": 7}), tmp_path, force=True)
    record = json.loads(path.read_text())
    assert record["stages_s"]["experts"] < 100.0 and record["stages_s"]["meta"] < 100.0


def test_ctrl_c_in_a_stage_without_chunks_ends_the_call_after_that_stage(tmp_path, stages, monkeypatch):
    """SIGINT inside a stage never raises there (it crashed a Warp callback): the stage finishes,
    its time is counted, the call ends as interrupted, and the next call goes on from the next stage."""
    log, modules = stages
    inner = modules["experts"].run

    def pressed_during(cfg, run_dir, say=print):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the handler has run: no KeyboardInterrupt here
        return inner(cfg, run_dir, say)

    monkeypatch.setattr(modules["experts"], "run", pressed_during)
    before = signal.getsignal(signal.SIGINT)
    said = []
    with pytest.raises(resumable.Interrupted):
        pipeline.run_pipeline(("experts", "meta"), cfg(), tmp_path, say=lambda *a, **k: said.append(a[0]))
    assert signal.getsignal(signal.SIGINT) is before
    assert log == ["experts"] and (tmp_path / "experts" / "out.json").exists()
    assert any("stopping after this chunk, or at the end of this stage" in line for line in said)
    record = json.loads((tmp_path / "pipeline.json").read_text())
    assert "open" not in record and "experts" in record["stages_s"]
    pipeline.run_pipeline(("experts", "meta"), cfg(), tmp_path, say=lambda *a, **k: None)
    assert log == ["experts", "meta"]


def test_a_killed_call_is_counted_up_to_its_stages_last_write(tmp_path, stages, monkeypatch):
    import os
    import time

    log, modules = stages

    def killed(cfg, run_dir, say=print):  # SIGKILL: no `finally` runs, the mark stays behind
        ckpt = Path(run_dir) / "experts" / "checkpoints" / "100"
        ckpt.parent.mkdir(parents=True)
        ckpt.write_text("")
        opened = json.loads((Path(run_dir) / "pipeline.json").read_text())["open"]
        os.utime(ckpt, (opened["experts"] + 42.0,) * 2)  # its last write, 42 s after the start
        raise SystemExit(json.loads((Path(run_dir) / "pipeline.json").read_text()))

    monkeypatch.setattr(modules["experts"], "run", killed)
    with pytest.raises(SystemExit) as frozen:
        pipeline.run_pipeline(("experts",), cfg(), tmp_path)
    (tmp_path / "pipeline.json").write_text(json.dumps(frozen.value.args[0]))  # as the kill left it
    monkeypatch.setattr(modules["experts"], "run", fake_stage("experts", log).run)
    start = time.perf_counter()
    pipeline.run_pipeline(("experts",), cfg(), tmp_path)
    record = json.loads((tmp_path / "pipeline.json").read_text())
    assert "open" not in record and record["calls"] == 2 and record["killed_calls"] == 1
    assert 42.0 <= record["stages_s"]["experts"] <= 42.0 + time.perf_counter() - start
    assert "1 of them killed" in report.pipeline_lines(record)[0]
    assert "calls that were killed" in report.pipeline_lines(record, {"experts": 1000.0, "meta": 5000.0})[1]
    # A stage the record does not count (run by its own command) is not compared.
    assert not any("calls that were killed" in line for line in report.pipeline_lines(record, {"baseline": 5000.0}))


def test_side_by_side_calls_share_the_record_and_leave_each_others_marks(tmp_path, stages):
    # Another command is running the baseline now (its mark is open): this call neither counts it
    # as killed nor drops its time when it writes its own stages.
    (tmp_path / "pipeline.json").write_text(json.dumps({"stages_s": {"baseline": 5.0}, "open": {"baseline": 1.0e9}}))
    pipeline.run_pipeline(("experts", "meta"), cfg(), tmp_path, say=lambda *a, **k: None)
    record = json.loads((tmp_path / "pipeline.json").read_text())
    assert record["open"] == {"baseline": 1.0e9} and "killed_calls" not in record
    assert record["stages_s"]["baseline"] == 5.0 and {"experts", "meta"} <= set(record["stages_s"])


def test_schedule_runs_the_baseline_beside_the_experts_once_the_prior_is_made():
    every = ("prior", "experts", "meta", "filter", "heldout", "baseline")
    assert pipeline.schedule(every, 4) == [
        [(("prior",), 4)],
        [(("experts", "meta", "filter", "heldout"), 3), (("baseline",), 1)],
    ]
    assert pipeline.schedule(every, 8)[1] == [(("experts", "meta", "filter", "heldout"), 6), (("baseline",), 2)]
    assert pipeline.schedule(("meta", "baseline"), 2) == [[(("meta",), 1), (("baseline",), 1)]]
    assert pipeline.schedule(every, 1) == [[(every, 1)]]  # one process: one after another
    assert pipeline.schedule(("prior", "baseline"), 4) == [[(("prior", "baseline"), 4)]]  # nothing beside it


def test_publishing_refuses_a_run_with_a_stage_unfinished(tmp_path, stages):
    """A run stopped before its last stage is not published: the committed record of that stage
    would stay from an older run beside the new ones, and the report would set them side by side."""
    from bumps_jax.pipeline import commands
    from bumps_jax.tasks import registry as tasks

    log, modules = stages
    for name in tasks.get("kick").stages:
        modules.setdefault(name, fake_stage(name, log))
    for name in ("prior", "experts", "meta", "filter", "heldout"):
        pipeline.run_stage(name, cfg(), tmp_path)
    (tmp_path / "baseline").mkdir()  # started, stopped before its record
    assert pipeline.unfinished(tmp_path, tasks.get("kick").stages, "kick") == ["baseline"]
    refusal = r"not published: .* has not finished baseline \(no baseline/out.json\)"
    with pytest.raises(ValueError, match=refusal) as err:
        commands.publish(cfg(), tmp_path, None)
    assert "\n" not in str(err.value)  # one line, before anything is read or written
    pipeline.run_stage("baseline", cfg(), tmp_path)
    assert pipeline.unfinished(tmp_path, tasks.get("kick").stages, "kick") == []


def test_a_launch_is_recorded_with_its_wall_time_and_phases(tmp_path, stages):
    pipeline.run_pipeline(("experts", "meta"), cfg(), tmp_path, say=lambda *a, **k: None)
    phases = pipeline.schedule(("experts", "meta", "baseline"), 3)
    pipeline.record_launch(tmp_path, 3, phases, 90.0, finished=False)
    record = pipeline.record_launch(tmp_path, 3, phases, 30.0, finished=True)  # a resumed call
    assert [x["wall_s"] for x in record["launches"]] == [90.0, 30.0] and record["launches"][1]["finished"]
    assert record["launches"][0]["phases"] == [[
        {"stages": ["experts", "meta"], "processes": 2},
        {"stages": ["baseline"], "processes": 1},
    ]]  # fmt: skip
    (line,) = report.launch_lines(record["launches"])
    assert line.startswith("Launched as 3 processes (experts, meta on 2 beside baseline on 1): **2.0 min**")
    assert "2 calls, added up" in line and "did not finish" not in line


def test_ctrl_c_in_a_stage_that_then_runs_to_its_end_says_so(tmp_path, stages, monkeypatch):
    # Ctrl-C during filtering: the stage ran its remaining variants, wrote its record, and the run
    # then said "rerun the same command to resume ... the stage in flight's last chunk".
    import os
    import signal

    log, modules = stages
    run = modules["experts"].run

    def pressed_during(cfg, run_dir, say=print):
        os.kill(os.getpid(), signal.SIGINT)  # asks the stage to stop; it has no chunks, so it ends
        return run(cfg, run_dir, say)

    monkeypatch.setattr(modules["experts"], "run", pressed_during)
    with pytest.raises(resumable.Interrupted, match=r"^the experts stage ran to its end before it could stop \("):
        pipeline.run_stage("experts", cfg(), tmp_path, say=lambda *a, **k: None)
    assert (tmp_path / "experts" / "out.json").exists() and log == ["experts"]


@pytest.mark.parametrize("task", ["kick", "point_goal"])
def test_publishing_refuses_a_run_of_another_preset_than_the_papers(tmp_path, task):
    """The committed results are the paper preset's: a tiny run (a demo) of any task, or a tiny
    seed's run beside a paper one, is refused in one line before anything is read or written."""
    from bumps_jax.pipeline import commands

    tiny, paper = tmp_path / "demo", tmp_path / "paper"
    runio.write_json(tiny / "pipeline.json", {"preset": "tiny", "overrides": {"task": task}})
    runio.write_json(paper / "pipeline.json", {"preset": "paper", "overrides": {"task": task}})
    args = types.SimpleNamespace(seed_runs=[], baseline_at_budget=False, records_only=False)
    before = sorted(p.name for p in tmp_path.rglob("*"))
    for run, seeds in ((tiny, []), (paper, [str(tiny)])):
        with pytest.raises(
            ValueError, match=r"^not published: .*demo is a tiny run; the committed results are the paper"
        ):
            commands.publish(
                config.make_config("tiny", {"task": task}),
                run,
                types.SimpleNamespace(**{**vars(args), "seed_runs": seeds}),
            )
    assert sorted(p.name for p in tmp_path.rglob("*")) == before
    with pytest.raises(ValueError, match="no run directory"):
        commands.publish(config.make_config("tiny", {"task": task}), tmp_path / "none", args)
