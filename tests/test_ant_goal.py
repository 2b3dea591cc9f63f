"""Ant-Goal, the ant walking to a goal (x, y) m: its env (shapes, the reward against a hand
computation, the physics against C MuJoCo), its scoring against other goals, its posture, its
config's checks, and the tiny pipeline (experts, meta, filter, baseline) through `run_pipeline`."""

import json

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from bumps_jax import config
from bumps_jax.algo import filtering
from bumps_jax.pipeline import runner as pipeline
from bumps_jax.tasks.ant_goal import config as ant_config
from bumps_jax.tasks.ant_goal import env as ant_env

# Three goals, one on the task range's edge.
GOALS = ((1.0, -2.0), (-3.0, 0.0), (0.5, 2.5))
N_STEPS = 20  # the ant, dropped from 0.75 m, touches the floor from about step 4


def open_loop(i: int) -> np.ndarray:
    """A fixed command sequence (8,) at step i, beyond the motors' [-1, 1] at times: the env clips it."""
    return (1.4 * np.sin(0.3 * i + np.arange(8))).astype(np.float32)


@pytest.fixture(scope="module")
def ant():
    """The env on MJX-JAX (compiles in seconds on a CPU; Warp runs the pipeline test)."""
    return ant_env.AntGoalEnv(config_overrides={"impl": "jax"})


@pytest.fixture(scope="module")
def trace(ant):
    """N_STEPS control steps of len(GOALS) episodes, one jitted vmapped reset and step:
    (first state, states after each step (T, B, ...), the actions (T, 8))."""
    reset, step = jax.jit(jax.vmap(ant.reset)), jax.jit(jax.vmap(ant.step))
    state = first = reset(jax.random.split(jax.random.PRNGKey(3), len(GOALS)), jnp.asarray(GOALS))
    states, actions = [], []
    for i in range(N_STEPS):
        actions.append(open_loop(i))
        state = step(state, jnp.broadcast_to(jnp.asarray(actions[-1]), (len(GOALS), 8)))
        states.append(state)
    return jax.tree.map(np.asarray, first), jax.tree.map(lambda *xs: np.stack(xs), *states), np.stack(actions)


def episode(tree, *index):
    """One episode's (or one step's) slice of a batched state or trace."""
    return jax.tree.map(lambda a: np.asarray(a)[index], tree)


def c_mujoco_step(env, data, ctrl):
    """One control step of C MuJoCo from MJX data (its solver warm start too), with cfrc_ext as
    `mj_rnePostConstraint` computes it: (MjData after, the geoms that touched the floor in any
    physics step)."""
    d = mujoco.MjData(env.mj_model)
    d.qpos[:], d.qvel[:], d.ctrl[:] = np.asarray(data.qpos), np.asarray(data.qvel), ctrl
    d.qacc_warmstart[:] = np.asarray(data.qacc_warmstart)
    touched = set()
    for _ in range(env.n_substeps):
        mujoco.mj_step(env.mj_model, d)
        touched |= {int(g) for g in d.contact.geom[: d.ncon, 1]}
    mujoco.mj_rnePostConstraint(env.mj_model, d)
    return d, touched


def test_reset_and_step_shapes_under_jit(ant, trace):
    assert (ant.observation_size, ant.context_observation_size, ant.action_size) == (29, 31, 8)
    assert (ant.n_steps, ant.n_substeps, ant.physics_dt, ant.dt) == (200, 5, 0.01, 0.05)
    assert ant.contacts_per_episode == 25 and ant.ACTION_BOUND == 1.0 and ant.CONTEXT_SIZE == 2
    first, states, _ = trace
    assert first.obs.shape == (len(GOALS), 29) and states.obs.shape == (N_STEPS, len(GOALS), 29)
    for b, goal in enumerate(GOALS):
        state = episode(first, b)
        data = state.pipeline_state
        # PEARL's observation without its contact forces: qpos (15) and qvel (14).
        np.testing.assert_allclose(state.obs, np.concatenate([data.qpos, data.qvel]))
        # Gym's reset noise: qpos within +-0.1 of the model's (torso at 0.75 m, upright, joints at 0).
        assert np.all(np.abs(data.qpos - ant.mj_model.qpos0) <= 0.1 + 1e-6)
        np.testing.assert_allclose(state.info["target"], goal)
        assert float(state.done) == 0.0 and float(state.metrics["target_clipped"]) == 0.0
        # A meta-policy sees the goal normalised over the task range (-3, 3) m, each coordinate.
        seen = ant.with_context(jnp.asarray(state.obs), jnp.asarray(goal))
        np.testing.assert_allclose(seen[29:], (np.asarray(goal) + 3.0) / 6.0, rtol=1e-6)
    assert not np.allclose(first.obs[0], first.obs[1])  # each episode its own reset noise
    np.testing.assert_array_equal(states.info["step"][:, 0], np.arange(1, N_STEPS + 1))
    assert np.all(states.done == 0.0)  # no early end: 200 steps (PEARL's done = False)
    for key, value in states.metrics.items():
        assert np.isfinite(value).all(), key
    assert float(states.metrics["overflow"].max()) == 0.0 and np.all(states.metrics["valid"] == 1.0)
    # The score: the torso's Euclidean distance to the goal, from where it is (its body position).
    pos = states.pipeline_state.xpos[:, :, ant.torso_body, :2]
    np.testing.assert_allclose(states.metrics["final_position"], pos)
    np.testing.assert_allclose(states.metrics["final_error"], np.linalg.norm(pos - np.asarray(GOALS), axis=-1),
                               rtol=1e-5)  # fmt: skip
    # A concrete goal outside the task range raises; the observation without the torso's x, y is Gym's 27.
    with pytest.raises(ValueError, match=r"target \(3.5, 0\) m is outside the task range"):
        ant.reset(jax.random.PRNGKey(0), jnp.array([3.5, 0.0]))
    assert ant_env.AntGoalEnv(config_overrides={"impl": "jax", "torso_xy": False}).observation_size == 27


def test_default_goals_are_uniform_on_the_disc():
    keys = jax.random.split(jax.random.key(0), 4000)
    goals = np.asarray(jax.jit(jax.vmap(lambda k: ant_env.sample_goal(k, 3.0)))(keys))
    radius = np.linalg.norm(goals, axis=-1)
    assert radius.max() <= 3.0 + 1e-5
    # Uniform on the disc: P(r < 1.5) = 1/4, and the angle uniform (each quadrant 1/4).
    assert abs(np.mean(radius < 1.5) - 0.25) < 0.03
    for sx in (-1, 1):
        for sy in (-1, 1):
            assert abs(np.mean((sx * goals[:, 0] > 0) & (sy * goals[:, 1] > 0)) - 0.25) < 0.03


def test_step_reward_by_hand(ant, trace):
    """reward = -|p - goal|_1 - 0.1 |clip(a)|^2 - 0.5e-3 |clip(cfrc_ext, -1, 1)|^2 from the state
    after each step, every episode against its own goal; the contact cost pays once the legs touch."""
    _, states, actions = trace
    clipped = np.clip(actions, -1.0, 1.0)
    assert np.abs(actions).max() > 1.0  # the commands go beyond the motors' range: the cost is on the clipped ones
    xy = states.pipeline_state.xpos[:, :, ant.torso_body, :2].astype(np.float64)  # (T, B, 2)
    l1 = np.abs(xy - np.asarray(GOALS)).sum(axis=-1)
    ctrl = 0.1 * np.sum(clipped**2, axis=-1)[:, None]
    cfrc = states.pipeline_state._impl.cfrc_ext.astype(np.float64)  # (T, B, nbody, 6)
    assert cfrc.shape[2:] == (14, 6)
    contact = 0.5e-3 * np.sum(np.clip(cfrc, -1.0, 1.0) ** 2, axis=(-2, -1))
    np.testing.assert_allclose(states.reward, -l1 - ctrl - contact, rtol=1e-5, atol=1e-5)
    m = states.metrics
    np.testing.assert_allclose(m["distance_l1"], l1, rtol=1e-5)
    np.testing.assert_allclose(m["reward_distance"], -l1, rtol=1e-5)
    np.testing.assert_allclose(m["potential"], -l1, rtol=1e-5)  # the distance term, for PPO's shaping
    np.testing.assert_allclose(m["reward_ctrl"], -np.broadcast_to(ctrl, l1.shape), rtol=1e-5)
    np.testing.assert_allclose(m["reward_contact"], -contact, rtol=1e-5, atol=1e-9)
    np.testing.assert_array_equal(m["reward_survive"], 0.0)
    np.testing.assert_allclose(m["return"], np.cumsum(states.reward, axis=0), rtol=1e-5)
    touching = contact > 0
    assert touching.any() and not touching[:3].any()  # dropped from 0.75 m: in the air at first


def test_physics_is_c_mujoco_but_for_the_capsules_friction_pyramid(ant, trace):
    """Each control step of the trace against C MuJoCo's from the same state: a step in which no
    leg capsule touches the floor agrees to 1e-4 (the torso's sphere and every joint limit too). MJX builds a capsule's
    contact frame on the world axes, C MuJoCo along the capsule: with pyramidal friction cones the
    friction pyramids differ, so a step in contact differs by up to centimetres (docs/ant_goal.md)."""
    first, states, actions = trace
    capsules = {int(g) for g in ant_env.colliding_geoms(ant.mj_model)
                if ant.mj_model.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE}  # fmt: skip
    free_steps = contact_steps = 0
    for b in range(len(GOALS)):
        before = episode(first, b)
        for i in range(N_STEPS):
            after = episode(states, i, b)
            d, touched = c_mujoco_step(ant, before.pipeline_state, np.clip(actions[i], -1, 1))
            ours = after.pipeline_state
            if touched & capsules:
                contact_steps += 1
                np.testing.assert_allclose(ours.qpos, d.qpos, atol=0.1, err_msg=f"episode {b}, step {i}")
            else:
                free_steps += 1
                np.testing.assert_allclose(ours.qpos, d.qpos, atol=1e-4, err_msg=f"episode {b}, step {i}")
                np.testing.assert_allclose(ours.xpos, d.xpos, atol=1e-4)
            before = after
    assert free_steps > 0 and contact_steps > 0


@pytest.mark.parametrize("impl", ["jax", "warp"])
def test_physics_and_contact_cost_are_c_mujoco_on_brax_feet(impl):
    """Brax's own contacts (the four foot spheres): every control step, in contact too, is C
    MuJoCo's, and the contact cost is C's `mj_rnePostConstraint`'s cfrc_ext clipped and weighed
    (MJX-JAX computes cfrc_ext after the step, Warp in its step)."""
    overrides = {"impl": impl, "all_contacts": False, **({"warp_contacts": 4} if impl == "warp" else {})}
    env = ant_env.AntGoalEnv(config_overrides=overrides)
    assert env.contacts_per_episode == 4 and env.max_episodes == (1 if impl == "warp" else None)
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    state = reset(jax.random.PRNGKey(1), jnp.array([1.0, -2.0]))
    touched_steps = 0
    for i in range(N_STEPS):
        after = step(state, jnp.asarray(open_loop(i)))
        d, touched = c_mujoco_step(env, state.pipeline_state, np.clip(open_loop(i), -1, 1))
        np.testing.assert_allclose(after.pipeline_state.qpos, d.qpos, atol=1e-4, err_msg=f"step {i}")
        np.testing.assert_allclose(after.pipeline_state._impl.cfrc_ext, d.cfrc_ext, atol=1e-3, err_msg=f"step {i}")
        c_contact = 0.5e-3 * np.sum(np.clip(d.cfrc_ext, -1, 1) ** 2)
        assert float(-after.metrics["reward_contact"]) == pytest.approx(c_contact, abs=1e-6)
        touched_steps += bool(touched) and c_contact > 0
        state = after
    assert touched_steps > 0, "no step touched the floor: the comparison says nothing about contacts"


def test_error_against_scores_final_positions_against_any_goal():
    env = object.__new__(ant_env.AntGoalEnv)  # error_against reads no model
    # Two contexts x two repetitions of final positions; the second rollout of context 1 invalid.
    metrics = {
        "final_position": np.array([[[0.0, 0.0], [3.0, 4.0]], [[1.0, 1.0], [-0.6, 0.8]]]),
        "valid": np.array([[1.0, 1.0], [1.0, 0.0]]),
    }
    goals = np.array([[0.0, 0.0], [3.0, 0.0]])
    expected = [
        [[0.0, 5.0], [np.sqrt(2.0), np.inf]],  # |p - (0, 0)|
        [[3.0, 4.0], [np.sqrt(5.0), np.inf]],  # |p - (3, 0)|
    ]
    np.testing.assert_allclose(env.error_against(metrics, goals[:, None, None, :]), expected)
    np.testing.assert_allclose(filtering.scoring(env)["errors"](metrics, goals), expected)


def test_posture_tells_a_flipped_ant():
    env = object.__new__(ant_env.AntGoalEnv)
    qpos = np.zeros((2, 4, 15))  # two episodes of four steps
    qpos[..., 2] = [[0.6, 0.5, 0.5, 0.4], [0.2, 0.2, 0.2, 0.2]]
    qpos[0, :, 3] = 1.0  # upright: the identity quaternion
    qpos[1, :3, 4] = 2.0  # on its back for three steps: half a turn about x (an unnormalised quaternion)
    qpos[1, 3, 3] = 1.0
    p = env.posture(qpos)
    np.testing.assert_allclose(p["height_m"], [0.5, 0.2])
    np.testing.assert_allclose(p["flipped_fraction"], [0.0, 0.75])
    np.testing.assert_allclose(p["up_z"], [1.0, -0.5])


def test_config_goals_and_sizes():
    assert len(ant_config.TRAIN_TASKS) == 37 and ant_config.TRAIN_TASKS[0] == (0.0, 0.0)
    assert max(np.hypot(*g) for g in ant_config.TRAIN_TASKS) <= 3.0
    assert ant_config.TEST_TASKS == ant_env.disc_goals(30, 3.0, seed=2026)
    cfg = config.make_config("paper", {"task": "ant_goal"})
    # The baseline's budget is the experts' (the centre's included), in whole updates of all 37.
    e, b = cfg.experts, cfg.baseline
    experts_steps = len(e.tasks) * e.ppo.total_env_steps + e.family.centre_updates * e.ppo.num_envs * 200
    assert b.ppo.total_env_steps == experts_steps == 102 * b.ppo.num_envs * 200
    assert cfg.env.warp_contacts == 25 * 3 * 37 * 512  # the baseline's 3 seeds hold the most episodes


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"env.goal_radius": 4.0}, "env.goal_radius must be in"),
        ({"env.reward.contact": -1.0}, "env.reward.contact must be a finite weight >= 0, got -1.0"),
        ({"env.reset_noise": -0.1}, "env.reset_noise must be a finite number >= 0, got -0.1"),
        ({"env.impl": "torch"}, "env.impl must be one of"),
        ({"experts.tasks": ((1.0,), (2.0,))}, r"experts.tasks: targets must be vectors of 2 numbers \(m\), got shape"),
        ({"filter.tasks": ((3.5, 0.0),)}, r"filter.tasks: target \(3.5, 0\) m is outside the task range \[-3.0, 3.0\]"),
        ({"env.warp_contacts": 100}, "env.warp_contacts 100 holds 4 episodes, but the experts program runs 12"),
    ],
)
def test_a_bad_config_value_names_its_key(overrides, message):
    with pytest.raises(ValueError, match=message):
        config.make_config("tiny", {"task": "ant_goal", **overrides})


def test_the_tiny_pipeline_runs_every_bumps_stage(tmp_path):
    """Experts (a family from the centre goal), meta and filter at the tiny preset (Warp, the
    default backend): finite errors and records naming the task. (The baseline, task-generic, runs
    in the cheetah's pipeline test and the kick's.)"""
    # Both nets of one small architecture, so that one compiled rollout program serves the two.
    nets = {f"meta.nets.{name}": (1, 16) for name in ("meta_4x256", "meta_11x128")}
    cfg = config.make_config("tiny", {"task": "ant_goal", **nets})
    stages = ("experts", "meta", "filter")
    say = []
    timing = pipeline.run_pipeline(stages, cfg, tmp_path, say=lambda *a, **k: say.append(str(a[0])))
    assert sorted(timing["stages_s"]) == ["experts", "filter", "meta"]
    experts = json.loads((tmp_path / "experts" / "experts.json").read_text())
    assert experts["task"] == "ant_goal" and experts["unit"] == "m"
    assert experts["tasks_m"] == [list(t) for t in cfg.experts.tasks]
    assert experts["family_centre"]["context"] == [0.0, 0.0]
    for row in experts["family_check"]["per_task"]:
        assert np.isfinite(row["error_m"]) and 0.0 <= row["flipped_fraction"] <= 1.0 and row["height_m"] > 0.0
    table1 = json.loads((tmp_path / "meta" / "table1.json").read_text())
    assert table1["task"] == "ant_goal" and table1["obs_size"] == 31 and table1["n_actions"] == 8
    for name in ("meta_4x256", "meta_11x128"):
        assert np.isfinite(table1["rows"][name]["error_mean_all_m"])
    table2 = json.loads((tmp_path / "filter" / "table2.json").read_text())
    assert table2["task"] == "ant_goal" and table2["tasks"] == [list(t) for t in cfg.filter.tasks]
    for name, row in table2["rows"].items():
        assert np.isfinite(row["error_mean_m"]) and row["accuracy_mean"] == 1.0, name
        assert row["return_mean"] < 0.0, name  # the meta-test return, the papers' score, beside the distance
        for context, task in zip(table2["chosen_contexts"].get(name, []), table2["tasks"], strict=False):
            assert np.linalg.norm(np.subtract(context, task)) <= cfg.filter.width + 1e-6
    report = (tmp_path / "report.md").read_text()
    assert "BUMPS on ant_goal" in report and "(error_map.png)" in report  # the 2-D goals' error map
    assert (tmp_path / "error_map.png").stat().st_size > 0
    # Cloned from the experts' recorded episodes (DART noise, clipped labels): the pairs are the
    # recording's steps, the nets' checkpoints where later stages read them; a rerun is up to date.
    n, steps = len(cfg.experts.tasks), cfg.env.episode_steps
    first = n * cfg.meta.dataset.repetitions * steps
    assert table1["dataset_pairs"] == first and table1["cloning"]["env_steps"] == {"dataset": first}
    assert "DART action noise" in table1["cloning"]["variant"] and "labels clipped" in table1["cloning"]["variant"]
    for name in cfg.meta.nets:
        assert (tmp_path / "meta" / name / "checkpoints").is_dir()
    again = []
    pipeline.run_pipeline(stages, cfg, tmp_path, say=lambda *a, **k: again.append(str(a[0])))
    assert sum("up to date" in line for line in again) == 3
