"""The command line: every stage has --help, overrides parse, bad keys fail with one clear line."""

import json

import pytest

from bumps_jax import cli


def test_every_stage_has_help(capsys):
    for stage in cli.STAGES:
        with pytest.raises(SystemExit) as exit_info:
            cli.main([stage, "--help"])
        assert exit_info.value.code == 0
        assert "--preset" in capsys.readouterr().out


def test_overrides_parse_json_values():
    assert cli.parse_overrides(["a.b=1", "c=[7.0, 8.0]", "d=name"]) == {"a.b": 1, "c": (7.0, 8.0), "d": "name"}
    with pytest.raises(SystemExit, match="key=value"):
        cli.parse_overrides(["novalue"])


def test_unknown_config_key_is_one_clear_line(tmp_path):
    with pytest.raises(SystemExit, match="error: unknown config key 'filter.nope'"):
        cli.main(["filter", "--run-dir", str(tmp_path), "--set", "filter.nope=1"])


def test_meta_train_without_experts_says_what_to_do(tmp_path):
    with pytest.raises(SystemExit, match="run train-experts first"):
        cli.main(["meta-train", "--run-dir", str(tmp_path)])


def test_pipeline_overrides_name_their_stage():
    stages = ("train-experts", "filter")
    split = cli.split_overrides({"experts.ppo.learning_rate": 1e-5, "filter.block": 8}, stages)
    assert split == {"train-experts": {"ppo.learning_rate": 1e-5}, "filter": {"block": 8}}
    with pytest.raises(SystemExit, match="start with a stage"):
        cli.split_overrides({"ppo.learning_rate": 1e-5}, stages)
    with pytest.raises(SystemExit, match="start with a stage"):
        cli.split_overrides({"meta.train.epochs": 5}, stages)  # meta-train is not in this pipeline


def test_video_without_a_filtered_run_says_what_to_do(tmp_path):
    with pytest.raises(SystemExit, match="run the filter stage first"):
        cli.main(["video", "--run-dir", str(tmp_path)])


def test_an_interrupted_stage_says_how_to_resume(tmp_path, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setitem(cli.STAGES, "filter", (interrupted, "stand-in"))
    with pytest.raises(SystemExit, match=f"interrupted: rerun the same command to resume {tmp_path}"):
        cli.main(["filter", "--run-dir", str(tmp_path)])


def test_pipeline_skips_finished_stages_and_counts_its_calls(tmp_path, monkeypatch):
    from bumps_jax import report

    ran = []

    def stage(name, fail=False):
        def run(run_dir, preset, overrides):
            ran.append(name)
            if fail:
                raise KeyboardInterrupt
            out = run_dir / cli.OUTPUTS[name]
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text("{}")

        return run, "stand-in"

    monkeypatch.setattr(cli, "_report", lambda *args: None)
    monkeypatch.setitem(cli.STAGES, "train-experts", stage("train-experts"))
    monkeypatch.setitem(cli.STAGES, "meta-train", stage("meta-train", fail=True))
    with pytest.raises(KeyboardInterrupt):
        cli._pipeline(tmp_path, "tiny", ("train-experts", "meta-train"))
    monkeypatch.setitem(cli.STAGES, "meta-train", stage("meta-train"))
    cli._pipeline(tmp_path, "tiny", ("train-experts", "meta-train"))
    assert ran == ["train-experts", "meta-train", "meta-train"]  # the finished stage is not rerun
    pipeline = json.loads((tmp_path / "pipeline.json").read_text())
    assert pipeline["calls"] == 2 and set(pipeline["stages"]) == {"train-experts", "meta-train"}
    assert "resumed across 2 calls" in report.pipeline_lines(pipeline)[0]
    assert "in one call" in report.pipeline_lines({**pipeline, "calls": 1})[0]


def test_a_killed_call_is_counted_up_to_its_stages_last_write(tmp_path, monkeypatch):
    import os
    import time

    from bumps_jax import report

    def killed(run_dir, preset, overrides):  # SIGKILL: no `finally` runs, the mark stays behind
        ckpt = run_dir / "meta" / "checkpoints" / "100"
        ckpt.parent.mkdir(parents=True)
        ckpt.write_text("")
        opened = json.loads((run_dir / "pipeline.json").read_text())["open"]
        os.utime(ckpt, (opened["started"] + 42.0,) * 2)  # its last write, 42 s after the start
        raise SystemExit(json.loads((run_dir / "pipeline.json").read_text()))

    monkeypatch.setattr(cli, "_report", lambda *args: None)
    monkeypatch.setitem(cli.STAGES, "meta-train", (killed, "stand-in"))
    with pytest.raises(SystemExit) as frozen:
        cli._pipeline(tmp_path, "tiny", ("meta-train",))
    (tmp_path / "pipeline.json").write_text(json.dumps(frozen.value.args[0]))  # as the kill left it

    def finish(run_dir, preset, overrides):
        (run_dir / cli.OUTPUTS["meta-train"]).write_text("{}")

    monkeypatch.setitem(cli.STAGES, "meta-train", (finish, "stand-in"))
    start = time.perf_counter()
    cli._pipeline(tmp_path, "tiny", ("meta-train",))
    pipeline = json.loads((tmp_path / "pipeline.json").read_text())
    assert "open" not in pipeline and pipeline["calls"] == 2 and pipeline["killed_calls"] == 1
    assert 42.0 <= pipeline["stages"]["meta-train"] <= 42.0 + time.perf_counter() - start
    assert "1 of them killed" in report.pipeline_lines(pipeline)[0]
    # A record that lost killed calls altogether is shown up by the stages' own times.
    assert "calls that were killed" in report.pipeline_lines(pipeline, stages_total_s=1000.0)[1]
    assert len(report.pipeline_lines(pipeline, stages_total_s=42.0)) == 2  # the line and a blank


def test_train_experts_starts_from_the_runs_own_prior(tmp_path, monkeypatch):
    from bumps_jax import experts, prior

    class Built(Exception):  # stops the stage once its config is made, before anything compiles
        pass

    def compile_programs(cfg, *args, **kwargs):
        raise Built(cfg.prior_path)

    def prior_path(overrides):
        with pytest.raises(Built) as built:
            cli._train_experts(tmp_path, "tiny", overrides)
        return built.value.args[0]

    monkeypatch.setattr(experts, "compile_programs", compile_programs)
    assert prior_path({}) == ""  # no kick-prior stage here (the demo): the committed asset
    own = tmp_path / "prior" / prior.RUN_PRIOR_JSON
    own.parent.mkdir()
    own.write_text("{}")
    assert prior_path({}) == str(own)
    assert prior_path({"prior_path": "elsewhere.json"}) == "elsewhere.json"
