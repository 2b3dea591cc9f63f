"""The HalfCheetah-Vel env: shapes, the reward against a hand computation and C MuJoCo, the episode
end, batches of targets, bad inputs."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from bumps_jax.tasks.cheetah_vel import env as cheetah_env

TARGETS = (0.0, 1.5, 3.0)
# Two commands beyond the motors' [-1, 1]: the env clips them, and the control cost is paid on the clipped ones.
ACTION = np.array([1.5, -0.3, 0.2, -2.0, 0.7, 0.0], np.float32)


def open_loop(i: int) -> jax.Array:
    """A fixed gait-like command sequence: (6,) at step i."""
    return jnp.asarray(np.sin(0.3 * i + np.arange(6)), jnp.float32)


@pytest.fixture(scope="module")
def cheetah():
    """The env on MJX-JAX (the cheaper backend to compile on a CPU), observing the torso position too."""
    return cheetah_env.CheetahVelEnv(config_overrides={"impl": "jax", "torso_position": True})


@pytest.fixture(scope="module")
def batch_step(cheetah):
    """The vmapped reset and step over len(TARGETS) episodes: the one physics program of this
    file's MJX-JAX tests (each costs about 20 s to compile on a CPU), so every check reads episodes
    of a batch."""
    return jax.jit(jax.vmap(cheetah.reset)), jax.jit(jax.vmap(cheetah.step))


@pytest.fixture(scope="module")
def batch_episode(cheetah, batch_step):
    """Whole episodes at TARGETS: (states after each step (T, B, ...), first state).

    Stepped from Python with the one jitted step: a scan of its own would compile the physics again.
    """
    reset, step = batch_step
    keys = jax.random.split(jax.random.PRNGKey(3), len(TARGETS))
    state = first = reset(keys, jnp.asarray(TARGETS))
    trace = []
    for i in range(cheetah.n_steps):
        state = step(state, jnp.broadcast_to(open_loop(i), (len(TARGETS), 6)))
        trace.append(state)
    return jax.tree.map(lambda *xs: np.stack(xs), *trace), first


@pytest.fixture(scope="module")
def action_step(batch_step):
    """One step at ACTION from fresh states at TARGETS: (before, after), batched."""
    reset, step = batch_step
    before = reset(jax.random.split(jax.random.PRNGKey(1), len(TARGETS)), jnp.asarray(TARGETS))
    return before, step(before, jnp.broadcast_to(jnp.asarray(ACTION), (len(TARGETS), 6)))


def episode(tree, b: int):
    """Episode b of a batched state (or of a batch's trace at one step)."""
    return jax.tree.map(lambda a: np.asarray(a)[b], tree)


def c_mujoco_step(env, data, ctrl):
    """One control step of C MuJoCo from MJX data (its solver warm start too): (qpos, torso xpos,
    contacts) after n_substeps physics steps."""
    d = mujoco.MjData(env.mj_model)
    d.qpos[:], d.qvel[:], d.ctrl[:] = np.asarray(data.qpos), np.asarray(data.qvel), ctrl
    d.qacc_warmstart[:] = np.asarray(data.qacc_warmstart)
    for _ in range(env.n_substeps):
        mujoco.mj_step(env.mj_model, d)
    return d.qpos.copy(), d.xpos[env.torso_body].copy(), d.ncon


def assert_step_matches_c_mujoco(env, before, after, action, label) -> int:
    """`after` is C MuJoCo's control step from `before` at the clipped `action`; returns its contacts."""
    qpos, torso, ncon = c_mujoco_step(env, before.pipeline_state, np.clip(np.asarray(action), -1.0, 1.0))
    np.testing.assert_allclose(after.pipeline_state.qpos, qpos, atol=1e-4, err_msg=label)
    np.testing.assert_allclose(after.obs[-3:], torso, atol=1e-4, err_msg=label)
    return ncon


def assert_steps_match_c_mujoco(env, reset, step, n_steps=12):
    """Each of the first `n_steps` control steps of an episode (the feet touch the floor from
    about step 6) is C MuJoCo's step from the same state."""
    state = reset(jax.random.PRNGKey(1), 2.0)
    contacts = 0
    for i in range(n_steps):
        after = step(state, open_loop(i))
        contacts += assert_step_matches_c_mujoco(env, state, after, open_loop(i), f"step {i}")
        state = after
    assert contacts > 0, "no step touched the floor: the comparison says nothing about contacts"
    assert float(state.metrics["overflow"]) == 0.0


def test_reset_and_step_shapes(cheetah, action_step):
    assert (cheetah.observation_size, cheetah.action_size, cheetah.n_steps) == (20, 6, 200)
    assert (cheetah.n_substeps, cheetah.physics_dt, cheetah.dt) == (5, 0.01, 0.05)
    states, nexts = action_step
    assert states.obs.shape == (len(TARGETS), 20) and nexts.obs.shape == (len(TARGETS), 20)
    for b, target in enumerate(TARGETS):
        state, nxt = episode(states, b), episode(nexts, b)
        data = state.pipeline_state
        # PEARL's observation: qpos without the root x, qvel, the torso's world position.
        expected = np.concatenate([data.qpos[1:], data.qvel, data.xpos[cheetah.torso_body]])
        np.testing.assert_allclose(state.obs, expected)
        # Gym's reset noise: qpos within +-0.1 of the model's, qvel of std 0.1.
        assert np.all(np.abs(data.qpos - cheetah.mj_model.qpos0) <= 0.1 + 1e-6)
        assert float(state.info["target"]) == target and float(state.done) == 0.0
        assert int(nxt.info["step"]) == 1 and float(nxt.done) == 0.0
        for value in (nxt.obs, nxt.reward, *nxt.metrics.values()):
            assert np.isfinite(np.asarray(value)).all()
    # The episodes start apart: each has its own reset noise.
    assert not np.allclose(states.obs[0], states.obs[1])
    # A fresh state has the stepped state's keys and types, so one compiled step serves both.
    kinds = lambda s: [(x.dtype, x.weak_type) for x in jax.tree.leaves(s)]  # noqa: E731
    assert kinds(states) == kinds(nexts) and sorted(states.metrics) == sorted(nexts.metrics)


def test_step_reward_by_hand(cheetah, action_step):
    """reward = -|dx / 0.05 - target| - 0.05 * |clip(a)|^2 from the states before and after, each
    episode against its own target; the physics is five C MuJoCo steps at the clipped command."""
    clipped = np.clip(ACTION, -1.0, 1.0)
    for b, target in enumerate(TARGETS):
        before, after = episode(action_step[0], b), episode(action_step[1], b)
        x0, x1 = float(before.pipeline_state.qpos[0]), float(after.pipeline_state.qpos[0])
        velocity = (x1 - x0) / 0.05
        run, ctrl = -abs(velocity - target), -0.05 * float(np.sum(clipped**2))
        assert float(after.reward) == pytest.approx(run + ctrl, rel=1e-5, abs=1e-5)
        m = after.metrics
        assert float(m["forward_vel"]) == pytest.approx(velocity, rel=1e-5, abs=1e-5)
        assert float(m["reward_velocity"]) == pytest.approx(run, rel=1e-5, abs=1e-5)
        assert float(m["reward_ctrl"]) == pytest.approx(ctrl, rel=1e-6)
        assert float(m["return"]) == pytest.approx(float(after.reward), rel=1e-6)
        assert float(m["mean_vel_error"]) == pytest.approx(abs(velocity - target), rel=1e-5, abs=1e-5)
        qpos, torso, _ = c_mujoco_step(cheetah, before.pipeline_state, clipped)
        np.testing.assert_allclose(after.pipeline_state.qpos, qpos, atol=1e-5)
        np.testing.assert_allclose(after.obs[-3:], torso, atol=1e-5)


def test_physics_is_c_mujoco_in_contact(cheetah, batch_episode):
    """Each of the first 12 control steps of every episode of the batch (the feet touch the floor
    from about step 6) is C MuJoCo's step from the same state: a vmapped episode is a single one."""
    trace, first = batch_episode
    for b in range(len(TARGETS)):
        contacts, state = 0, episode(first, b)
        for i in range(12):
            after = episode(jax.tree.map(lambda a, i=i: a[i], trace), b)
            contacts += assert_step_matches_c_mujoco(cheetah, state, after, open_loop(i), f"episode {b}, step {i}")
            state = after
        assert contacts > 0, "no step touched the floor: the comparison says nothing about contacts"


def test_episode_ends_at_200_steps_over_a_batch_of_targets(cheetah, batch_episode):
    trace, first = batch_episode
    dones = trace.done  # (T, B)
    assert dones.shape == (200, len(TARGETS)) and trace.obs.shape == (200, len(TARGETS), 20)
    assert np.all(dones[:-1] == 0.0) and np.all(dones[-1] == 1.0)
    np.testing.assert_array_equal(trace.info["truncation"], dones)
    np.testing.assert_allclose(first.info["target"], TARGETS)
    # The episode's score: the return and the mean velocity error over its 200 steps.
    final = jax.tree.map(lambda a: a[-1], trace.metrics)
    np.testing.assert_allclose(final["return"], trace.reward.sum(axis=0), rtol=1e-4)
    np.testing.assert_allclose(final["mean_vel_error"], trace.metrics["vel_error"].mean(axis=0), rtol=1e-4)
    # The pipeline's score (task_env): final_error is that mean velocity error, every episode valid;
    # the per-step velocities score the same episodes against any other target (policy filtering).
    np.testing.assert_allclose(final["final_error"], final["mean_vel_error"])
    np.testing.assert_array_equal(final["valid"], 1.0)
    np.testing.assert_allclose(final["forward_vels"], trace.metrics["forward_vel"].T, rtol=1e-6)
    np.testing.assert_allclose(final["mean_forward_vel"], trace.metrics["forward_vel"].mean(axis=0), rtol=1e-4)
    against = cheetah.error_against(jax.tree.map(np.asarray, final), np.asarray(TARGETS)[:, None])  # (3, B)
    np.testing.assert_allclose(np.diag(against), final["mean_vel_error"], rtol=1e-4)
    expected = np.abs(trace.metrics["forward_vel"][:, None, :] - np.asarray(TARGETS)[None, :, None]).mean(axis=0)
    np.testing.assert_allclose(against, expected, rtol=1e-4)
    # Every step, every episode: its reward scores its own target.
    targets = np.asarray(TARGETS)[None, :]
    run = -np.abs(trace.metrics["forward_vel"] - targets)
    np.testing.assert_allclose(trace.metrics["reward_velocity"], run, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(trace.reward, run + trace.metrics["reward_ctrl"], rtol=1e-5, atol=1e-5)
    assert np.isfinite(trace.obs).all() and float(trace.metrics["overflow"].max()) == 0.0


def test_warp_matches_c_mujoco():
    """MuJoCo Warp (the default backend) steps as C MuJoCo does, in contact too."""
    env = cheetah_env.CheetahVelEnv(config_overrides={"impl": "warp", "warp_contacts": 16, "torso_position": True})
    assert env.max_episodes == 1
    assert_steps_match_c_mujoco(env, jax.jit(env.reset), jax.jit(env.step))


def test_model_options():
    """Gym's contacts (every capsule on the floor) or Brax's (torso and shins pass through), and
    the observation without the torso position (Gym's HalfCheetah, ProMP: 17)."""
    assert cheetah_env.colliding_geoms(cheetah_env.load_model(all_contacts=True)) == 8
    assert cheetah_env.colliding_geoms(cheetah_env.load_model(all_contacts=False)) == 5
    model = cheetah_env.load_model()
    assert model.body_mass.sum() == pytest.approx(cheetah_env.TOTAL_MASS)
    # C MuJoCo's broad phase reads the per-body masks the compiler derives from the geoms'.
    np.testing.assert_array_equal(model.body_contype[1:], 1)
    env = cheetah_env.CheetahVelEnv(config_overrides={"impl": "jax", "torso_position": False, "all_contacts": False})
    assert env.observation_size == 17 and env.context_observation_size == 18
    obs = jnp.zeros((4, 17))
    np.testing.assert_allclose(env.with_context(obs, 1.5)[:, -1], 0.5)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"impl": "torch"}, "env.impl must be one of"),
        ({"episode_steps": 0}, "env.episode_steps must be a positive integer"),
        ({"task_range": (3.0, 0.0)}, "env.task_range must be finite with low < high"),
        ({"ctrl_dt": 0.055}, "not a multiple of the physics step"),
        ({"reward.ctrl": -0.05}, "env.reward.ctrl must be a finite weight"),
        ({"reset_noise": float("inf")}, "env.reset_noise must be a finite number >= 0, got inf"),
        ({"rewards.ctrl": 0.05}, "unknown config key 'rewards.ctrl'"),
    ],
)
def test_bad_config_raises(overrides, message):
    with pytest.raises(ValueError, match=message):
        cheetah_env.CheetahVelEnv(config_overrides={"impl": "jax", **overrides})


def test_target_outside_range_raises(cheetah):
    with pytest.raises(ValueError, match="target 3.5 m/s is outside the task range"):
        cheetah.reset(jax.random.PRNGKey(0), 3.5)
