"""The scene benchmark measures on the env's own backend, with Warp's contact pool sized to the
batch; a pool too small for the batch is refused rather than timed. The bench's own sections' wiring."""

import pytest

from benchmarks import scene_bench
from bumps_jax import config
from bumps_jax.tasks.kick import env as kick_env


def test_rates_run_on_the_envs_backend_with_a_pool_sized_to_the_batch():
    env_cfg = config.make_config("tiny").env
    assert env_cfg.impl == "warp"
    env = scene_bench.sized_env(env_cfg, 8)
    assert env.config.warp_contacts == kick_env.CONTACTS_PER_EPISODE * 8
    assert kick_env.resolved(env.config) | {"warp_contacts": 0} == kick_env.resolved(env_cfg) | {"warp_contacts": 0}
    assert scene_bench.physics_rate(env.mj_model, 8, n_steps=5, repeats=1, env_cfg=env.config) > 0
    starved = kick_env.make_config(env_cfg, {"warp_contacts": 1})  # one slot for 8 standing robots
    with pytest.raises(ValueError, match="batch 8: Warp's contact pool \\(1 slots\\) overflowed"):
        scene_bench.physics_rate(env.mj_model, 8, n_steps=5, repeats=1, env_cfg=starved)


def test_the_scaled_experts_workload_gets_a_contact_pool_to_match():
    from benchmarks import bench

    paper = config.make_config("paper")
    cut = bench.expert_config(paper, updates=1, workload=8)  # refused before the pool was scaled
    assert len(cut.experts.tasks) == 8 * len(paper.experts.tasks)
    assert cut.env.warp_contacts == 8 * paper.env.warp_contacts
    assert bench.expert_config(paper, updates=1).env.warp_contacts == paper.env.warp_contacts


def test_a_bench_of_some_sections_writes_its_own_record_and_refuses_a_path_for_a_name(tmp_path, capsys):
    import json

    from benchmarks import bench

    skip = ["--skip", "experts", "gae", "brax", "filter", "scene", "tuning"]
    bench.main(["--preset", "tiny", "--backends", "jax", *skip, "--out-dir", str(tmp_path), "--record", "bc_probe"])
    assert [p.name for p in tmp_path.iterdir()] == ["bc_probe.json"]  # not training.json
    record = json.loads((tmp_path / "bc_probe.json").read_text())
    assert record["bc_stacked_batched_steps_per_s"] > 0 and record["preset"] == "tiny"
    for bad in ("../training", "bc.json", "a/b"):
        with pytest.raises(SystemExit):
            bench.parse_args(["--record", bad, "--out-dir", str(tmp_path)])
        assert f"--record {bad!r}" in capsys.readouterr().err


def test_the_tuning_projection_counts_every_run():
    """bench's tuning section projects the preset's generations for K runs one after another
    against the K runs in one batch."""
    from benchmarks import bench

    paper = config.make_config("paper")
    proj = bench.tuning_projection(paper, 1.0, 2.0, 4)
    generations = paper.experts.tune.generations
    assert proj["tuning_projected_s"] == 4 * generations and proj["tuning_batched_projected_s"] == 2 * generations
    assert proj["tuning_batched_vs_sequential"] == 2.0
