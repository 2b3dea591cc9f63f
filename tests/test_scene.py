"""The MJCF model against SimSpark's numbers, the stance, the servo limits and the ball law."""

import mujoco
import numpy as np
import pytest

from bumps_jax.envs import physics
from bumps_jax.tasks.kick import ball, scene

# SimSpark's joint table (degrees): name -> (low, high).
LIMITS_DEG = {
    "hj1": (-120, 120), "hj2": (-45, 45),
    "laj1": (-120, 120), "laj2": (-1, 95), "laj3": (-120, 120), "laj4": (-90, 1),
    "raj1": (-120, 120), "raj2": (-95, 1), "raj3": (-120, 120), "raj4": (-1, 90),
    "llj1": (-90, 1), "llj2": (-25, 45), "llj3": (-25, 100), "llj4": (-130, 1), "llj5": (-45, 75),
    "llj6": (-45, 25),
    "rlj1": (-90, 1), "rlj2": (-45, 25), "rlj3": (-25, 100), "rlj4": (-130, 1), "rlj5": (-45, 75),
    "rlj6": (-25, 45),
}  # fmt: skip


@pytest.fixture(scope="module")
def model():
    return scene.load_model()


def test_joint_names_order_and_limits(model):
    hinge_names = [
        mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
        for j in range(model.njnt)
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE
    ]
    assert hinge_names == list(scene.JOINTS) == list(LIMITS_DEG)
    ids = scene.scene_ids(model)
    np.testing.assert_allclose(np.rad2deg(ids.joint_range), np.array(list(LIMITS_DEG.values())), atol=1e-6)


def test_joint_axes_follow_simspark_frame(model):
    # SimSpark (x right, y forward) -> MuJoCo (x forward, y left): x_mj = y_rsg, y_mj = -x_rsg.
    def axis(name):
        return model.jnt_axis[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)]

    np.testing.assert_allclose(axis("llj3"), [0, -1, 0])  # rsg (1, 0, 0)
    np.testing.assert_allclose(axis("llj2"), [1, 0, 0])  # rsg (0, 1, 0)
    np.testing.assert_allclose(axis("llj1"), [0, 0.7071, -0.7071], atol=1e-4)  # rsg (-.7071, 0, -.7071)
    np.testing.assert_allclose(axis("rlj1"), [0, 0.7071, 0.7071], atol=1e-4)


def test_total_mass_is_simspark_nao(model):
    ids = scene.scene_ids(model)
    robot_mass = model.body_mass.sum() - model.body_mass[ids.ball_body]
    assert abs(robot_mass - 4.6071) / 4.6071 < 0.01


def test_ball_radius_and_mass(model):
    ids = scene.scene_ids(model)
    assert model.geom_size[ids.ball_geom][0] == pytest.approx(0.042)
    assert model.body_mass[ids.ball_body] == pytest.approx(0.026)


def test_actuators_are_torque_limited_position_servos(model):
    assert model.nu == 22
    np.testing.assert_allclose(model.actuator_forcerange, np.tile([-10.0, 10.0], (22, 1)))
    assert np.all(model.actuator_forcelimited)
    ids = scene.scene_ids(model)
    np.testing.assert_allclose(model.actuator_ctrlrange, ids.joint_range)


def test_only_listed_contacts_exist(model):
    # All geoms opt out of default collisions; only the explicit pairs collide.
    assert np.all(model.geom_contype == 0) and np.all(model.geom_conaffinity == 0)
    names = {mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_PAIR, i) for i in range(model.npair)}
    assert {"l_foot_floor", "r_foot_floor", "ball_floor", "ball_l_foot"} <= names


def test_stance_holds_for_five_seconds(model):
    data = scene.mj_data_for(model)
    ids = scene.scene_ids(model)
    start = data.xpos[ids.torso_body].copy()
    for _ in range(int(5.0 / model.opt.timestep)):
        mujoco.mj_step(model, data)
    drift = np.linalg.norm(data.xpos[ids.torso_body] - start)
    assert drift < 0.02, f"torso drifted {drift:.4f} m"
    assert data.xpos[ids.torso_body][2] > 0.3


def test_servo_respects_speed_and_torque_limits(model):
    """A target 90 deg away, fed through the env's rate limiter: the joint never exceeds
    SimSpark's speed limit by more than the servo's overshoot, the motor never 10 N m."""
    data = scene.mj_data_for(model)
    ids = scene.scene_ids(model)
    j = scene.JOINTS.index("laj1")  # a free-swinging arm: the fastest joint there is
    command = scene.STANCE.copy()
    goal = command.copy()
    goal[j] += np.deg2rad(90)
    top_speed, top_force = 0.0, 0.0
    ids_range = ids.joint_range
    n_substeps = round(0.02 / model.opt.timestep)  # one 20 ms control step
    for _ in range(40):
        ramp = physics.servo_ramp(
            command, goal, ids_range[:, 0], ids_range[:, 1], scene.MAX_JOINT_SPEED * 0.02, n_substeps
        )
        command = ramp[-1]
        for ctrl in ramp:
            data.ctrl[:] = ctrl
            mujoco.mj_step(model, data)
            top_speed = max(top_speed, abs(data.qvel[ids.joint_qvel[j]]))
            top_force = max(top_force, np.abs(data.actuator_force).max())
    assert top_force <= 10.0 + 1e-6
    assert top_speed <= 1.05 * scene.MAX_JOINT_SPEED, top_speed
    assert data.qpos[ids.joint_qpos[j]] == pytest.approx(goal[j], abs=np.deg2rad(3))


def _roll(model, qvel_ball, z=scene.BALL_RADIUS, seconds=2.0):
    data = mujoco.MjData(model)
    data.qpos[:3] = [0.0, 0.0, z]
    data.qpos[3:7] = [1.0, 0.0, 0.0, 0.0]
    data.qvel[:6] = qvel_ball
    speeds = []
    for _ in range(int(seconds / model.opt.timestep)):
        mujoco.mj_step(model, data)
        speeds.append(np.linalg.norm(data.qvel[:2]))
    return data, np.array(speeds)


def test_rolling_law_is_exponential_decay():
    full = scene.load_model()
    ball = scene.ball_only_model()
    c = scene.rolling_decel_rate()
    assert c == pytest.approx(scene.damping_decel_rate(full), rel=0.005)
    v0 = 2.0
    _, speeds = _roll(ball, [v0, 0, 0, 0, v0 / scene.BALL_RADIUS, 0], seconds=5.0)
    t = np.arange(1, len(speeds) + 1) * ball.opt.timestep
    np.testing.assert_allclose(speeds, v0 * np.exp(-c * t), rtol=0.01)


BALL_STARTS = {
    "rolling": ([2.0, 0.3, 0.0, -0.3 / 0.042, 2.0 / 0.042, 0.0], 0.042),
    "sliding": ([2.5, 0.0, 0.0, 0.0, 0.0, 0.0], 0.042),
    "backspin": ([2.5, 0.0, 0.0, 0.0, -20.0, 0.0], 0.042),
    "airborne": ([2.0, -0.2, 1.0, 0.0, 10.0, 0.0], 0.10),
}


def _full_scene_ball(kind):
    model = scene.load_model()
    ids = scene.scene_ids(model)
    data = scene.mj_data_for(model)
    qvel, z = BALL_STARTS[kind]
    data.qpos[ids.ball_qpos : ids.ball_qpos + 3] = [0.3, 0.06, z]
    data.qvel[ids.ball_qvel : ids.ball_qvel + 6] = qvel
    mujoco.mj_forward(model, data)
    return model, ids, data


def _ball_world_state(data, ids):
    q, v = ids.ball_qpos, ids.ball_qvel
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, data.qpos[q + 3 : q + 7])
    angvel = rot.reshape(3, 3) @ data.qvel[v + 3 : v + 6]  # body frame -> world
    return data.qpos[q : q + 3].copy(), data.qvel[v : v + 3].copy(), angvel


def _simulate_to_rest(model, ids, data):
    for _ in range(int(60.0 / model.opt.timestep)):
        mujoco.mj_step(model, data)
        if np.linalg.norm(data.qvel[ids.ball_qvel : ids.ball_qvel + 3]) < scene.BALL_REST_SPEED:
            return data.qpos[ids.ball_qpos : ids.ball_qpos + 2].copy()
    pytest.fail("the ball never came to rest")


@pytest.mark.parametrize("kind", list(BALL_STARTS))
def test_rest_point_matches_full_simulation_once_ball_rolls(kind):
    """The closed form against the full scene (robot included) simulated until the ball rests.

    Whatever the ball did when struck (slide, backspin, a hop), 0.5 s later it rolls, as it
    does at the end of a kick phase; from there the shortcut must be right within 5 cm.
    """
    model, ids, data = _full_scene_ball(kind)
    for _ in range(int(0.5 / model.opt.timestep)):
        mujoco.mj_step(model, data)
    pos, vel, angvel = _ball_world_state(data, ids)
    assert bool(ball.rolling(vel, angvel))
    expected = np.asarray(ball.rest_point(pos, vel, angvel, scene.rolling_decel_rate()))
    rest = _simulate_to_rest(model, ids, data)
    assert np.linalg.norm(rest - expected) < 0.05, (kind, rest, expected)


@pytest.mark.parametrize("kind", ["sliding", "backspin", "airborne"])
def test_rest_point_of_a_ball_not_yet_rolling_is_flagged(kind):
    """Right at the strike the shortcut is only approximate: `rolling` says so, and the
    error stays bounded (measured: 7, 17 and 20 cm)."""
    model, ids, data = _full_scene_ball(kind)
    pos, vel, angvel = _ball_world_state(data, ids)
    assert not bool(ball.rolling(vel, angvel))
    expected = np.asarray(ball.rest_point(pos, vel, angvel, scene.rolling_decel_rate()))
    rest = _simulate_to_rest(model, ids, data)
    assert np.linalg.norm(rest - expected) < 0.3, (kind, rest, expected)
