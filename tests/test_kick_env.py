"""The MJX kick environment: shapes, determinism, noise, reward and metrics, bad inputs."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import scene

STAND = jnp.asarray(scene.stance_command())


@pytest.fixture(scope="module")
def episode(env, jit_env):
    """A whole standing-still episode: (final state, (rewards, dones, final errors) per step).

    Stepped from Python with the session's compiled step: a scan of its own would compile the
    physics again (~20 s on a CPU) for the same episode. `episode(rng, target)` plays each
    (rng, target) once and hands later asks the first episode (on a CPU each costs ~10 s);
    `episode.again(rng, target)` always plays it anew.
    """
    reset, step = jit_env
    played = {}

    def again(rng, target):
        state, trace = reset(rng, target), []
        for _ in range(env.n_steps):
            state = step(state, STAND)
            trace.append((state.reward, state.done, state.metrics["final_error"]))
        return state, tuple(jnp.stack(column) for column in zip(*trace, strict=True))

    def run(rng, target):
        key = (tuple(np.asarray(jax.random.key_data(rng)).ravel().tolist()), float(target))
        if key not in played:
            played[key] = again(rng, target)
        return played[key]

    run.again = again
    return run


def test_reset_and_step_shapes(env, jit_env):
    reset, step = jit_env
    state = reset(jax.random.PRNGKey(0), 12.0)
    assert state.obs.shape == (env.observation_size,) == (2,)
    assert env.action_size == 22
    np.testing.assert_allclose(state.obs, [0.0, (12.0 - 7.0) / 11.0], rtol=1e-6)
    nxt = step(state, STAND)
    assert nxt.obs.shape == (2,)
    assert float(nxt.obs[0]) == pytest.approx(1.0 / env.n_steps)
    assert np.isfinite(float(nxt.reward))
    assert not bool(nxt.done)
    for value in nxt.metrics.values():
        assert np.isfinite(np.asarray(value)).all()
    # A fresh state has the stepped state's types, weak or strong, so one compiled step serves both.
    kinds = lambda s: [(x.dtype, x.weak_type) for x in jax.tree.leaves(s)]  # noqa: E731
    assert kinds(state) == kinds(nxt)


def test_episode_ends_after_horizon_with_final_reward(env, episode):
    """Standing still never strikes the ball: invalid kick, error = distance from the ball's
    start to the target; the last reward adds the weighted final error to the step term."""
    last, (rewards, dones, errors) = episode(jax.random.PRNGKey(1), 10.0)
    dones = np.asarray(dones)
    assert np.all(dones[:-1] == 0.0) and dones[-1] == 1.0
    assert float(last.metrics["valid"]) == 0.0 and float(last.metrics["struck"]) == 0.0
    assert float(last.metrics["fallen"]) == 0.0
    assert float(last.metrics["final_error"]) == pytest.approx(10.0, abs=0.03)
    ball = np.asarray(last.pipeline_state.qpos[env.ids.ball_qpos : env.ids.ball_qpos + 2])
    step_term = -0.1 * np.linalg.norm(ball - np.asarray(last.info["target_xy"]))
    expected = step_term - 10.0 * float(last.metrics["final_error"])
    assert float(rewards[-1]) == pytest.approx(expected, rel=1e-4)
    # Before the end only the per-step term is paid; the ball stood still all along.
    assert float(rewards[-2]) == pytest.approx(step_term, rel=1e-3)


def test_a_rolling_ball_scores_its_resting_point(env, jit_env):
    """Give the ball a rolling velocity by hand: the metrics report where it will rest."""
    reset, step = jit_env
    state = reset(jax.random.PRNGKey(2), 12.0)
    v0 = 1.8
    data = state.pipeline_state
    qvel = data.qvel.at[env.ids.ball_qvel].set(v0).at[env.ids.ball_qvel + 4].set(v0 / scene.BALL_RADIUS)
    state = state.replace(pipeline_state=data.replace(qvel=qvel))
    state = step(step(state, STAND), STAND)
    m = state.metrics
    assert float(m["struck"]) == 1.0 and float(m["valid"]) == 1.0 and float(m["ball_rolling"]) == 1.0
    start_x = float(state.info["target_xy"][0]) - 12.0
    expected_x = start_x + (v0 - scene.BALL_REST_SPEED) / env.decel_rate
    assert float(m["rest_x"]) == pytest.approx(expected_x, abs=0.1)
    assert float(m["final_error"]) == pytest.approx(abs(expected_x - start_x - 12.0), abs=0.1)
    assert float(m["rel_error"]) == pytest.approx(float(m["final_error"]) / 12.0)


def test_same_rng_same_episode_bit_for_bit(episode):
    # The first is the episode test_episode_ends_after_horizon_with_final_reward played (played now
    # if that test did not run); the second is played again from the same rng.
    a, ra = episode(jax.random.PRNGKey(1), 10.0)
    b, rb = episode.again(jax.random.PRNGKey(1), 10.0)
    np.testing.assert_array_equal(a.pipeline_state.qpos, b.pipeline_state.qpos)
    np.testing.assert_array_equal(ra[0], rb[0])


def test_noise_differs_across_rngs(env, jit_env):
    reset, _ = jit_env
    s1, s2 = reset(jax.random.PRNGKey(4), 9.0), reset(jax.random.PRNGKey(5), 9.0)
    b = env.ids.ball_qpos
    assert not np.allclose(s1.pipeline_state.qpos[b : b + 2], s2.pipeline_state.qpos[b : b + 2])
    assert not np.allclose(s1.pipeline_state.qpos[env.ids.joint_qpos], s2.pipeline_state.qpos[env.ids.joint_qpos])
    assert float(s1.info["friction_scale"]) != float(s2.info["friction_scale"])
    assert float(s1.info["gain_scale"]) != float(s2.info["gain_scale"])
    ball_offset = np.abs(np.asarray(s1.pipeline_state.qpos[b : b + 2]) - np.asarray(s2.pipeline_state.qpos[b : b + 2]))
    assert ball_offset.max() <= 2 * env.config.noise.ball_xy + 1e-6


@pytest.fixture(scope="module")
def quiet_proprio_env():
    """An env with every noise source off and proprioception on, and its reset jitted: one
    compile (~13 s on a CPU) for the tests of both options. They do not interact: noise moves
    the start state, proprioception only adds to the observation."""
    noise_off = {f"noise.{k}": 0.0 for k in ("ball_xy", "joint_angle", "friction", "actuator_gain")}
    env = kick_env.KickEnv(config_overrides={**noise_off, "proprioception": True})
    return env, jax.jit(env.reset)


def test_no_noise_config_gives_identical_starts(quiet_proprio_env):
    _, reset = quiet_proprio_env
    s1, s2 = reset(jax.random.PRNGKey(4), 9.0), reset(jax.random.PRNGKey(5), 9.0)
    np.testing.assert_array_equal(s1.pipeline_state.qpos, s2.pipeline_state.qpos)


def test_vmapped_episodes_carry_their_own_targets(env):
    targets = jnp.array([7.0, 12.5, 18.0])
    states = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(6), 3), targets)
    np.testing.assert_allclose(states.info["target"], targets)
    np.testing.assert_allclose(states.obs[:, 1], (targets - 7.0) / 11.0, rtol=1e-6)


def test_brax_style_reset_draws_from_configured_tasks(env):
    state = jax.jit(env.reset)(jax.random.PRNGKey(7))
    assert min(abs(float(state.info["target"]) - t) for t in env.config.tasks) < 1e-5


def test_servo_target_moves_at_most_the_speed_limit(env, jit_env):
    reset, step = jit_env
    state = reset(jax.random.PRNGKey(8), 12.0)
    far = jnp.asarray(scene.STANCE).at[scene.JOINTS.index("llj3")].set(1.5)
    nxt = step(state, far)
    moved = np.abs(np.asarray(nxt.info["command"] - state.info["command"]))
    assert moved.max() == pytest.approx(scene.MAX_JOINT_SPEED * 0.02, rel=1e-5)


def test_actions_are_clipped_to_joint_limits(env, jit_env):
    reset, step = jit_env
    state = reset(jax.random.PRNGKey(9), 12.0)
    for _ in range(30):
        state = step(state, jnp.full((22,), 10.0, jnp.float32))  # strongly typed, as STAND: no recompile
    np.testing.assert_allclose(state.info["command"], env.ids.joint_range[:, 1], atol=1e-6)


def test_proprioception_option_adds_state(quiet_proprio_env):
    env, reset = quiet_proprio_env
    state = reset(jax.random.PRNGKey(0), 12.0)
    assert state.obs.shape == (env.observation_size,) == (52,)
    np.testing.assert_allclose(state.obs[46:49], [0.0, 0.0, -1.0], atol=0.05)  # gravity, torso frame


# -- bad input ---------------------------------------------------------------------------


def test_target_outside_range_is_refused(env):
    with pytest.raises(ValueError, match="25.0"):
        env.reset(jax.random.PRNGKey(0), 25.0)
    with pytest.raises(ValueError, match="outside the task range"):
        env.reset(jax.random.PRNGKey(0), float("nan"))


def test_traced_target_outside_range_is_clipped_and_flagged(env):
    state = jax.jit(env.reset)(jax.random.PRNGKey(0), 30.0)
    assert float(state.info["target"]) == 18.0
    assert float(state.metrics["target_clipped"]) == 1.0


def test_wrong_action_shape_is_refused(env, jit_env):
    reset, _ = jit_env
    state = reset(jax.random.PRNGKey(0), 12.0)
    with pytest.raises(ValueError, match=r"shape \(22,\)"):
        env.step(state, jnp.zeros(21))


def test_nan_action_holds_and_invalidates(env, jit_env):
    reset, step = jit_env
    state = reset(jax.random.PRNGKey(0), 12.0)
    nxt = step(state, STAND.at[3].set(jnp.nan))
    assert np.isfinite(np.asarray(nxt.info["command"])).all()
    assert float(nxt.info["command"][3]) == float(state.info["command"][3])
    assert float(nxt.metrics["valid"]) == 0.0


def test_physics_blowup_is_a_failed_kick(env, jit_env):
    reset, step = jit_env
    state = reset(jax.random.PRNGKey(0), 12.0)
    qvel = state.pipeline_state.qvel.at[:].set(1e6)
    state = state.replace(pipeline_state=state.pipeline_state.replace(qvel=qvel))
    nxt = step(state, STAND)
    assert float(nxt.metrics["blown_up"]) == 1.0
    assert float(nxt.metrics["valid"]) == 0.0
    assert float(nxt.metrics["final_error"]) == pytest.approx(12.0)
    assert np.isfinite(float(nxt.reward))


@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"task_range": (18.0, 7.0)}, "task_range"),
        ({"task_range": (7.0,)}, r"^env.task_range must be \(low, high\), got \(7.0,\)$"),
        ({"tasks": (20.0,)}, r"^env.tasks: target 20.0 m is outside the task range"),
        ({"tasks": ()}, "tasks is empty"),
        ({"tasks": (5.0,)}, "5.0"),
        ({"noise.friction": -0.1}, "noise.friction"),
        ({"ctrl_dt": 0.013}, "multiple of the physics step"),
    ],
)
def test_bad_config_is_refused_by_name(overrides, message):
    with pytest.raises(ValueError, match=message):
        kick_env.KickEnv(config_overrides=overrides)


def test_unknown_config_key_is_refused():
    with pytest.raises(ValueError, match="noise.frction"):
        kick_env.KickEnv(config_overrides={"noise.frction": 0.1})


def test_the_physics_step_sets_the_substeps_and_keeps_the_rolling_law():
    assert kick_env.KickEnv().n_substeps == 8  # the scene's 2.5 ms
    env = kick_env.KickEnv(config_overrides={"physics_dt": 0.005})
    assert env.n_substeps == 4 and env.mj_model.opt.timestep == 0.005
    # The rolling law is measured at the env's own step; it barely depends on it.
    assert env.decel_rate == pytest.approx(kick_env.KickEnv().decel_rate, rel=0.01)
    with pytest.raises(ValueError, match="physics_dt"):
        kick_env.KickEnv(config_overrides={"physics_dt": -0.001})
