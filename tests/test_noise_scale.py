"""The noise-scaling replay (experiments/noise_scale.py): its overrides and argument checks."""

import pytest

from bumps_jax import config
from bumps_jax.tasks.kick import env as kick_env
from experiments import noise_scale


def test_scaled_noise_multiplies_every_source_and_builds_an_env():
    cfg = config.make_config("tiny")
    noise = cfg.env.noise
    half = noise_scale.scaled_noise(cfg.env, 0.5)
    assert set(half) == {f"env.noise.{k}" for k in noise}
    for key, value in noise.items():
        assert half[f"env.noise.{key}"] == pytest.approx(0.5 * value)
    assert all(v == 0.0 for v in noise_scale.scaled_noise(cfg.env, 0.0).values())
    env = kick_env.KickEnv(config.make_config("tiny", half).env)
    assert env.config.noise.ball_xy == pytest.approx(0.5 * noise.ball_xy)
    assert cfg.env.noise.ball_xy == pytest.approx(noise.ball_xy)  # the run's own config is untouched


def test_summarise_reads_the_envs_distance_and_lateral():
    metrics = {
        "final_error": [[0.5, 1.5]],
        "distance": [[11.0, 13.0]],
        "lateral": [[0.25, -0.75]],
        "valid": [[1.0, 0.0]],
    }
    (row,) = noise_scale.summarise(metrics, [12.0])
    assert row == {
        "target_m": 12.0,
        "error_mean_m": 1.0,
        "distance_mean_m": 12.0,
        "distance_std_m": 1.0,
        "lateral_mean_m": -0.25,
        "valid_fraction": 0.5,
    }


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--scales", "-1"], "-1"),
        (["--repetitions", "1"], "repetitions"),
        (["--run-dir", "no/such/run"], "no/such/run"),
    ],
)
def test_bad_arguments_are_named(argv, message, capsys):
    with pytest.raises(SystemExit):
        noise_scale.main(argv)
    assert message in capsys.readouterr().err


def test_a_run_of_another_config_is_refused(tmp_path, capsys):
    (tmp_path / "experts" / "final_params").mkdir(parents=True)
    with pytest.raises(SystemExit):
        noise_scale.main(["--run-dir", str(tmp_path), "--preset", "tiny"])  # its experts dir holds no manifest
    assert str(tmp_path / "experts") in capsys.readouterr().err
