"""The noise-scaling replay (experiments/noise_scale.py): its overrides and argument checks."""

import pytest

from bumps_jax import kick_env
from experiments import noise_scale


def test_scaled_noise_multiplies_every_source_and_builds_an_env():
    noise = kick_env.default_config().noise
    half = noise_scale.scaled_noise(0.5)
    assert set(half) == {f"noise.{k}" for k in noise}
    for key, value in noise.items():
        assert half[f"noise.{key}"] == pytest.approx(0.5 * value)
    assert all(v == 0.0 for v in noise_scale.scaled_noise(0.0).values())
    assert kick_env.KickEnv(config_overrides=half).config.noise.ball_xy == pytest.approx(0.5 * noise.ball_xy)


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
