"""Experts started from another run's prior (experiments/experts_from_prior.py): the asset made
from a prior stage's record, where it is placed, and what is refused; nothing trained."""

from pathlib import Path

import numpy as np
import pytest

from bumps_jax import config, runio
from bumps_jax.tasks import registry
from bumps_jax.tasks.kick import keyframes as kick_model
from experiments import experts_from_prior

ROOT = Path(__file__).resolve().parents[1]
PUBLISHED = ROOT / "results/kick_prior.json"  # the published seed 0's prior stage record


def args(tmp_path, prior=PUBLISHED, seed=0):
    return experts_from_prior.parse_args(["--prior", str(prior), "--against", str(ROOT / "results/experts.json"),
                                          "--run-dir", str(tmp_path / "run"), "--seed", str(seed),
                                          "--out", str(tmp_path / "out.json")])  # fmt: skip


def test_the_placed_asset_is_what_the_experts_start_from_and_holds_the_records_prior(tmp_path):
    cfg = config.make_config("paper", {"task": "kick"})
    a = args(tmp_path, prior=PUBLISHED, seed=2)
    path = experts_from_prior.place(a, cfg)
    run = tmp_path / "run" / "seed2"
    assert registry.get("kick").expert_start.inputs(cfg, run) == {"prior": path}  # loads under the paper env
    stage = runio.read_json(PUBLISHED, "the published prior")
    placed = kick_model.load_record(path, env_cfg=cfg.env)
    np.testing.assert_array_equal(placed["anchors"], np.float32([stage["anchors"][n] for n in kick_model.ANCHORS]))
    np.testing.assert_array_equal(placed["params"], np.float32(stage["anchors"]["main"]))
    assert placed["sweep"] == stage["sweep"] and placed["episodes"] == stage["episodes"]
    assert placed["evaluation"]["mean_error"] == stage["mean_error_m"]
    assert experts_from_prior.place(a, cfg) == path  # the same prior again: a resumed run


def test_another_prior_or_a_prior_stage_in_the_run_folder_is_refused(tmp_path):
    cfg = config.make_config("paper", {"task": "kick"})
    experts_from_prior.place(args(tmp_path, prior=PUBLISHED), cfg)
    other = ROOT / "results/pipeline_4gpu/kick_prior.json"
    with pytest.raises(ValueError, match=r"holds another prior than --prior .*: use a new --run-dir$"):
        experts_from_prior.place(args(tmp_path, prior=other), cfg)
    runio.write_json(tmp_path / "run" / "seed1" / "prior" / "kick_prior.json", {"mean_error_m": 0.3})
    with pytest.raises(ValueError, match=r"seed 1 has a prior stage of its own"):
        experts_from_prior.place(args(tmp_path, prior=other, seed=1), cfg)


def test_a_record_that_is_no_prior_stages_is_one_line_before_any_work(tmp_path):
    runio.write_json(tmp_path / "bare.json", {"mean_error_m": 0.3})
    with pytest.raises(SystemExit, match=r"not a kick prior stage's record \(it needs anchors"):
        experts_from_prior.main(["--prior", str(tmp_path / "bare.json"), "--against",
                                 str(ROOT / "results/experts.json"), "--run-dir", str(tmp_path / "run"),
                                 "--out", str(tmp_path / "out.json")])  # fmt: skip
    assert not (tmp_path / "run").exists()
    with pytest.raises(SystemExit, match=r"not a kick experts record"):
        experts_from_prior.main(["--prior", str(PUBLISHED), "--against", str(tmp_path / "bare.json"),
                                 "--run-dir", str(tmp_path / "run"), "--out", str(tmp_path / "out.json")])  # fmt: skip


def test_a_prior_made_under_other_prior_settings_is_refused_naming_the_setting(tmp_path):
    stage = runio.read_json(PUBLISHED, "the published prior")
    for key, value, named in (("generations", 3, "prior.generations 3"),
                              ("extremes", {"short": {"target_m": 5.5}, "long": {"target_m": 21.0}},
                               "prior.extremes.short 5.5")):  # fmt: skip
        with pytest.raises(ValueError, match=rf"made with {named}, this preset has"):
            experts_from_prior.asset(
                {**stage, key: value}, PUBLISHED, config.make_config("paper", {"task": "kick"}).prior
            )


def test_a_run_folder_that_cannot_be_made_is_one_line(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(SystemExit, match=r"--run-dir .* is not writable"):
        experts_from_prior.main(["--prior", str(PUBLISHED), "--against", str(ROOT / "results/experts.json"),
                                 "--run-dir", str(tmp_path / "file" / "run"),
                                 "--out", str(tmp_path / "out.json")])  # fmt: skip
