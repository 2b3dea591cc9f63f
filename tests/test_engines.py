"""The physics backends (`env.impl`): config checks, and the MuJoCo Warp env against C MuJoCo.

The Warp tests skip where warp-lang is not installed. On a CPU each Warp program compiles in
seconds once Warp's kernel cache holds its kernels (the first run on a machine builds them).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks import c_replay
from bumps_jax import config
from bumps_jax.algo import rollout
from bumps_jax.envs import base as task_env
from bumps_jax.tasks.kick import cmaes, scene
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import keyframes as kick_model

NO_NOISE = {f"noise.{k}": 0.0 for k in ("ball_xy", "joint_angle", "friction", "actuator_gain")}
MAIN = kick_model.ANCHORS.index("main")
AGREE_M = 0.01  # Warp against C MuJoCo at the same solver iterations


@pytest.mark.parametrize(
    "overrides, named",
    [
        ({"impl": "torch"}, "env.impl must be one of"),
        ({"solver_iterations": 0}, "env.solver_iterations must be a positive integer"),
        ({"warp_contacts": 0}, "env.warp_contacts must be a positive integer"),
        ({"warp_constraints_per_world": -3}, "env.warp_constraints_per_world must be a positive integer"),
    ],
)
def test_backend_settings_are_refused_in_one_line(overrides, named):
    with pytest.raises(ValueError, match=named) as err:
        kick_env.KickEnv(config_overrides=overrides)
    assert "\n" not in str(err.value)


def test_missing_warp_is_refused_in_one_line(monkeypatch):
    monkeypatch.setattr(task_env.importlib.util, "find_spec", lambda name: None)  # the check every env shares
    with pytest.raises(ValueError, match="warp-lang") as err:
        config.make_config("tiny", {"env.impl": "warp"})
    assert "\n" not in str(err.value)


def test_solver_iterations_reach_the_model_and_records():
    assert kick_env.KickEnv().mj_model.opt.iterations == 4  # the default: converged for our kicks
    assert kick_env.KickEnv(config_overrides={"solver_iterations": None}).mj_model.opt.iterations == 2  # the scene's
    assert kick_env.resolved(kick_env.default_config())["solver_iterations"] == 4
    assert (
        kick_env.resolved({**kick_env.default_config().to_dict(), "solver_iterations": None})["solver_iterations"] == 2
    )
    # A record from before these keys was made on MJX-JAX at the scene's iterations, and reads so.
    old = {
        k: v for k, v in kick_env.resolved(kick_env.default_config()).items() if k not in ("impl", "solver_iterations")
    }
    assert (kick_env.resolved(old)["impl"], kick_env.resolved(old)["solver_iterations"]) == ("jax", 2)
    # The committed prior was made under the default env: every preset loads it.
    kick_model.load_record(kick_model.ASSET, kick_env.resolved(config.make_config("tiny").env))


# -- MuJoCo Warp ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def warp():
    return pytest.importorskip("warp")


def warp_env(iterations=None, contacts=12 * 8, **overrides):
    cfg = {"impl": "warp", "solver_iterations": iterations, "warp_contacts": contacts, **overrides}
    return kick_env.KickEnv(config.make_config("tiny").env, cfg)


@pytest.fixture(scope="module")
def anchors():
    return kick_model.load_record()["anchors"]


def play(env, params, reps=1, seed=0):
    """Keyframe kicks (N, 14) through `rollout.matched_fn`, `reps` episodes each: metrics (N, reps)."""
    tables = kick_model.action_tables(params, env.n_steps, env.config.ctrl_dt)
    targets = jnp.full(len(params), 12.0)
    fn = rollout.matched_fn(env, rollout.table_policy)
    return jax.tree.map(np.asarray, fn(tables, targets, targets, rollout.repetition_keys(seed, len(params), reps)))


def test_warp_env_steps_under_jit_and_vmap_with_the_jax_metrics(warp):
    env = warp_env(iterations=1)  # one solver iteration: the solver stops at its limit
    keys, targets = jax.random.split(jax.random.key(0), 3), jnp.array([8.0, 12.0, 16.0])
    state = jax.jit(jax.vmap(env.reset))(keys, targets)
    step = jax.jit(jax.vmap(env.step))
    for _ in range(2):
        state = step(state, jnp.tile(jnp.asarray(scene.stance_command()), (3, 1)))
    assert state.obs.shape == (3, env.observation_size)
    assert np.isfinite(np.asarray(state.obs)).all() and np.isfinite(np.asarray(state.reward)).all()
    assert not np.asarray(state.metrics["overflow"]).any()
    assert (np.asarray(state.metrics["solver_limit_steps"]) > 0).all()  # counted, not printed
    jax_env = kick_env.KickEnv(config.make_config("tiny", {"env.impl": "jax"}).env)
    jax_state = jax.eval_shape(
        jax_env.step, jax.eval_shape(jax_env.reset, jax.random.key(0), 12.0), state.info["command"][0]
    )
    assert set(state.metrics) == set(jax_state.metrics)
    assert all(np.isfinite(np.asarray(v)).all() for v in state.metrics.values())


def test_warp_rests_the_anchors_where_c_mujoco_does_with_each_episodes_jitter(warp, anchors):
    """Every anchor, two episodes with only the per-episode friction and servo-gain jitter: each
    rests where C MuJoCo rests it with the same scales, and the main kick's two rest apart (the
    jitter reaches Warp). Measured on a CPU at 4 iterations: within 0.06 mm but for one long kick
    (2.3 mm); without jitter within 0.3 mm (the long kick is 5 cm off at 2 iterations)."""
    env = warp_env(iterations=4, **{**NO_NOISE, "noise.friction": 0.1, "noise.actuator_gain": 0.05})
    metrics = play(env, anchors, reps=2)
    keys = rollout.repetition_keys(0, len(anchors), 2)
    for i, params in enumerate(anchors):
        info = jax.vmap(env.reset)(keys[i], jnp.full(2, 12.0)).info
        actions = c_replay.kick_actions(env, params)
        for r in range(2):
            model = c_replay.scene_model(env)
            model.pair_friction[:] *= float(info["friction_scale"][r])
            model.actuator_gainprm[:, 0] *= float(info["gain_scale"][r])
            model.actuator_biasprm[:, 1] *= float(info["gain_scale"][r])
            c = c_replay.replay(env, actions, model=model)
            assert metrics["distance"][i, r] == pytest.approx(c.distance, abs=AGREE_M), (i, r)
            assert metrics["lateral"][i, r] == pytest.approx(c.lateral, abs=AGREE_M), (i, r)
    assert abs(metrics["distance"][MAIN, 0] - metrics["distance"][MAIN, 1]) > 5 * AGREE_M
    assert metrics["valid"].all() and not metrics["overflow"].any()
    assert (metrics["solver_limit_steps"] <= env.n_steps * env.n_substeps).all()


def test_a_contact_overflow_invalidates_the_episode(warp, anchors):
    env = warp_env(contacts=4, **NO_NOISE)  # a standing robot alone makes 9
    metrics = play(env, anchors[MAIN : MAIN + 1])
    assert metrics["overflow"][0, 0] == 1.0 and metrics["valid"][0, 0] == 0.0


def test_the_tuning_fits_the_pool_of_one_generation(warp, anchors):
    """A pool that holds one generation's episodes (2 tasks x 2 candidates x 1) is enough, and no
    contact is dropped. A pool one episode smaller is refused in one line before anything compiles."""
    tune = {"population_size": 2, "repetitions": 1, "eval_repetitions": 1}
    tune = config.make_config("tiny", {f"experts.tune.{k}": v for k, v in tune.items()})
    fitness = config.make_config("tiny").prior.fitness
    starts = np.stack([anchors[MAIN]] * 2)
    out = cmaes.tune_for_tasks(warp_env(contacts=12 * 4), [11.0, 12.0], starts, tune.experts.tune, 1, 0.5,
                               fitness=fitness, say=lambda m: None)  # fmt: skip
    assert np.isfinite(out["tuned_cost"]).all() and out["episodes"] == 2 * (1 * 2 * 1 + 2 * 1)
    with pytest.raises(ValueError, match="env.warp_contacts 36 holds 3 episodes, but the tuning") as err:
        cmaes.tune_for_tasks(warp_env(contacts=12 * 3), [11.0, 12.0], starts, tune.experts.tune, 1, 0.5,
                             fitness=fitness, say=lambda m: None)  # fmt: skip
    assert "\n" not in str(err.value)
    # the config says so before any stage starts: the paper preset's pool holds its tuning, not twice it
    with pytest.raises(ValueError, match="but the experts tuning .* runs 11776") as err:
        config.make_config("paper", {"experts.tune.population_size": 64})
    assert "\n" not in str(err.value)
