"""The strike-height search (experiments/strike_search.py): its geometry and its argument checks."""

import mujoco
import numpy as np
import pytest

from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model
from bumps_jax.tasks.kick import scene
from experiments import strike_search


def test_strike_height_of_the_stance_is_the_foot_top_below_the_ball_centre():
    # Standing, the kicking foot's box (2 cm tall, sole on the floor) is behind the ball: the
    # point of it nearest the ball's centre is its top front edge, 2 cm up, so 4.2 - 2 cm below.
    # C MuJoCo's data has the fields the measure reads, and its forward pass is instant on a CPU.
    env = kick_env.KickEnv()
    data = mujoco.MjData(env.mj_model)
    data.qpos[:] = np.asarray(env._qpos0)
    mujoco.mj_forward(env.mj_model, data)
    height = strike_search.strike_height(env)(data)
    assert float(height) == pytest.approx(0.02 - scene.BALL_RADIUS, abs=2e-3)


def test_start_kicks_are_inside_the_parameter_bounds():
    starts = strike_search.start_kicks()
    assert {"default", "prior_main", "prior_short", "prior_long"} <= set(starts)
    for params in starts.values():
        assert np.all(params >= kick_model.PARAM_LOW - 1e-6) and np.all(params <= kick_model.PARAM_HIGH + 1e-6)


def test_a_physics_step_that_does_not_divide_the_control_step_is_named(capsys):
    with pytest.raises(SystemExit):
        strike_search.main(["--physics-dt", "0.003"])
    assert "0.003" in capsys.readouterr().err
