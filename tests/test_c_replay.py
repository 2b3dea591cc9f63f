"""The C MuJoCo replay (benchmarks/c_replay.py): its control step, determinism and scoring. Where
the Warp env rests the prior's kicks against this replay: test_engines.py."""

import numpy as np
import pytest

from benchmarks import c_replay
from bumps_jax import config
from bumps_jax.tasks.kick import ball, scene
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model


@pytest.fixture(scope="module")
def quiet_cfg():
    cfg = config.make_config("tiny")
    return config.make_config("tiny", {f"env.noise.{k}": 0.0 for k in cfg.env.noise})


@pytest.fixture(scope="module")
def main_kick():
    cfg = config.make_config("tiny")
    return kick_model.load_record(kick_model.ASSET, env_cfg=cfg.env)["params"]


@pytest.fixture(scope="module")
def quiet_env(quiet_cfg):
    return kick_env.KickEnv(quiet_cfg.env)


@pytest.fixture(scope="module")
def main_outcome(quiet_env, main_kick):
    return c_replay.replay(quiet_env, c_replay.kick_actions(quiet_env, main_kick))


def test_control_step_and_substeps_come_from_the_env():
    env = kick_env.KickEnv(config.make_config("tiny", {"env.physics_dt": 0.005}).env)
    assert env.n_substeps == 4
    calls = []
    sim = c_replay.Replay(env, on_substep=lambda model, data, step: calls.append((step, data.time)))
    assert sim.model.opt.timestep == pytest.approx(0.005)
    sim.step(np.asarray(scene.stance_command()))
    sim.step(np.asarray(scene.stance_command()))
    assert [s for s, _ in calls] == [0] * 4 + [1] * 4
    assert sim.data.time == pytest.approx(2 * env.config.ctrl_dt)
    assert calls[3][1] == pytest.approx(env.config.ctrl_dt)


def test_replay_is_deterministic_and_agrees_with_itself_split_into_parts(quiet_env, main_kick, main_outcome):
    actions = c_replay.kick_actions(quiet_env, main_kick)
    again = c_replay.replay(quiet_env, actions)
    assert again.distance == main_outcome.distance and again.lateral == main_outcome.lateral
    sim = c_replay.Replay(quiet_env, on_substep=lambda *_: None)  # a hook that only looks changes nothing
    for part in (actions[:30], actions[30:]):
        for action in part:
            sim.step(action)
    split = sim.outcome()
    np.testing.assert_array_equal(split.ball_pos, main_outcome.ball_pos)
    np.testing.assert_array_equal(split.ball_vel, main_outcome.ball_vel)
    assert split.distance == main_outcome.distance


def test_resting_point_is_the_envs_closed_form_of_its_final_ball_state(quiet_env, main_outcome):
    o = main_outcome
    rest = np.asarray(ball.rest_point(o.ball_pos, o.ball_vel, o.ball_angvel, quiet_env.decel_rate))
    assert (o.rest_x, o.rest_y) == (float(rest[0]), float(rest[1]))
    start = c_replay.Replay(quiet_env).ball_start
    assert o.distance == pytest.approx(o.rest_x - start[0]) and o.lateral == pytest.approx(o.rest_y - start[1])
    assert o.valid and o.struck and not o.fallen and not o.blown_up


def test_ball_offset_moves_the_start_not_the_scoring_origin(quiet_env):
    nominal = c_replay.Replay(quiet_env)
    moved = c_replay.Replay(quiet_env, ball_offset=(0.01, -0.02))
    q = moved.ids.ball_qpos
    np.testing.assert_allclose(moved.data.qpos[q : q + 2] - nominal.data.qpos[q : q + 2], [0.01, -0.02])
    np.testing.assert_array_equal(moved.ball_start, nominal.ball_start)
    standing = moved.outcome()  # the ball has not moved since its start
    assert standing.distance == pytest.approx(0.01, abs=1e-6) and standing.lateral == pytest.approx(-0.02, abs=1e-6)


def test_iterations_set_on_a_copy(quiet_env):
    model = c_replay.scene_model(quiet_env, iterations=7)
    assert model.opt.iterations == 7
    assert quiet_env.mj_model.opt.iterations != 7


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"iterations": 0}, "iterations"),
        ({"iterations": 2.5}, "iterations"),
        ({"ball_offset": (0.0, float("nan"))}, "ball_offset"),
        ({"actions": np.zeros((75, 21))}, "actions"),
        ({"actions": np.zeros((0, 22))}, "actions"),
    ],
)
def test_bad_arguments_are_named(quiet_env, kwargs, message):
    args = {"actions": np.tile(scene.stance_command(), (2, 1)), **kwargs}
    with pytest.raises(ValueError, match=message):
        c_replay.replay(quiet_env, **args)


def test_a_model_at_another_physics_step_is_refused(quiet_env):
    other = kick_env.KickEnv(config.make_config("tiny", {"env.physics_dt": 0.005}).env)
    with pytest.raises(ValueError, match="timestep"):
        c_replay.scene_model(quiet_env, model=other.mj_model)
