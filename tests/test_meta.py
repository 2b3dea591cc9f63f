"""Meta-training: lr schedule, behaviour cloning, dataset contextualisation, save/load, resume."""

import csv

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bumps_jax import kick_env, meta, synthetic_experts


def _train_cfg(**changes):
    cfg = meta.tiny_config().train
    cfg.unlock()
    cfg.update(changes)
    cfg.lock()
    return cfg


def test_lr_schedule_matches_the_paper():
    """3e-4 x 0.8 every 5000 epochs, an epoch being one pass: 14 steps for 23 experts x 75 steps."""
    train = meta.default_config().train
    epoch_steps = meta.steps_per_epoch(train, 23 * 75)
    assert epoch_steps == 14  # 13 full batches of 128 and one of 61
    schedule = meta.lr_schedule(train, epoch_steps)
    for epoch, lr in [(0, 3e-4), (4999, 3e-4), (5000, 2.4e-4), (12000, 1.92e-4), (149_999, 3e-4 * 0.8**29)]:
        assert float(schedule(epoch * epoch_steps)) == pytest.approx(lr, rel=1e-5), epoch
        assert float(schedule(epoch * epoch_steps + epoch_steps - 1)) == pytest.approx(lr, rel=1e-5), epoch


def test_an_epoch_visits_every_row_once():
    """The loss of one epoch at lr ~ 0 is the dataset's mean error, each row counted once."""
    rng = np.random.default_rng(1)
    obs = jnp.asarray(rng.uniform(size=(300, 2)), jnp.float32)  # 3 batches: 128, 128, 44 rows
    actions = jnp.asarray(rng.normal(size=(300, 22)), jnp.float32)
    cfg = _train_cfg(learning_rate=1e-12, epochs=1, chunk=1, batch_size=128)
    model = meta.MetaPolicy(depth=1, width=8)
    init, chunk = meta.make_trainer(model, cfg, 300)
    state = init(meta.seed_keys(cfg))
    params0 = jax.tree.map(lambda a: a[0], state.params)
    per_row = np.abs(np.asarray(meta.policy_apply(model)(params0, obs)) - np.asarray(actions)).mean(axis=1)
    state, losses = chunk(state, obs, actions, meta.seed_keys(cfg))
    assert int(state.step) == 3 and losses.shape == (1, 3)
    weighted = (128 * losses[0, 0] + 128 * losses[0, 1] + 44 * losses[0, 2]) / 300
    assert float(weighted) == pytest.approx(per_row.mean(), rel=1e-4)


def test_behaviour_cloning_recovers_a_linear_map(tmp_path):
    rng = np.random.default_rng(0)
    w = rng.normal(size=(2, 22)).astype(np.float32) * 0.5
    b = rng.normal(size=22).astype(np.float32) * 0.3
    x = rng.uniform(size=(4096, 2)).astype(np.float32)
    data = meta.Dataset(obs=x, actions=x @ w + b, task=np.zeros(len(x), np.float32))
    # 4096 pairs: 32 steps per epoch, 2880 steps in all.
    cfg = _train_cfg(learning_rate=3e-3, decay_every=30, epochs=90, chunk=30, batch_size=128)
    model = meta.MetaPolicy(depth=2, width=32)
    state = meta.train(model, data, cfg, tmp_path, verbose=False)
    x_test = rng.uniform(size=(256, 2)).astype(np.float32)
    params0 = jax.tree.map(lambda a: a[0], state.params)
    pred = np.asarray(meta.policy_apply(model)(params0, jnp.asarray(x_test)))
    assert np.abs(pred - (x_test @ w + b)).mean() < 0.03


def _table_dataset(tasks) -> meta.Dataset:
    """The synthetic experts' (obs, action) pairs without simulating: phase k / T, their table row."""
    experts = synthetic_experts.synthetic_experts(tasks)
    tables = np.asarray(experts.params)  # (E, T, 22)
    n_exp, n_steps, _ = tables.shape
    phase = np.tile(np.arange(n_steps) / n_steps, n_exp)
    task = np.repeat(np.asarray(tasks, np.float32), n_steps)
    ctx = (task - 7.0) / 11.0
    return meta.Dataset(np.stack([phase, ctx], 1).astype(np.float32), tables.reshape(-1, 22), task)


def test_loss_falls_on_the_tiny_preset(tmp_path):
    data = _table_dataset(kick_env.meta_train_tasks())
    cfg = meta.tiny_config()
    # All 23 experts' rows (14 steps per epoch): the tiny schedule cut to 300 epochs.
    cfg.train.unlock()
    cfg.train.update(epochs=300, chunk=75, decay_every=100)
    depth, width = cfg.nets["meta_4x256"]
    model = meta.MetaPolicy(depth, width)
    init, _ = meta.make_trainer(model, cfg.train, len(data.obs))
    first = jax.tree.map(lambda a: a[0], init(meta.seed_keys(cfg.train)).params)
    initial = float(meta.mae_loss(first, meta.policy_apply(model), data.obs, data.actions))
    meta.train(model, data, cfg.train, tmp_path, verbose=False)
    with open(tmp_path / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    chunk, epochs = cfg.train.chunk, cfg.train.epochs
    assert [int(r["epoch"]) for r in rows] == list(range(chunk, epochs + 1, chunk))
    losses = [float(r["loss_mean"]) for r in rows]
    assert losses[-1] < losses[0] and losses[-1] < 0.3 * initial


def test_resume_equals_uninterrupted(tmp_path):
    data = _table_dataset((8.0, 12.0))
    cfg = _train_cfg(epochs=40, chunk=10, n_seeds=2)
    model = meta.MetaPolicy(depth=1, width=8)
    trainer = meta.make_trainer(model, cfg, len(data.obs))  # 150 pairs: 2 steps per epoch
    whole = meta.train(model, data, cfg, tmp_path / "a", verbose=False, trainer=trainer)
    part = meta.train(model, data, cfg, tmp_path / "b", verbose=False, max_chunks=2, trainer=trainer)
    assert int(part.step) == 2 * 20
    resumed = meta.train(model, data, cfg, tmp_path / "b", verbose=False, trainer=trainer)
    assert int(resumed.step) == 2 * 40
    for a, b in zip(jax.tree.leaves(whole), jax.tree.leaves(resumed), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with open(tmp_path / "b" / "progress.csv") as f:
        assert [int(r["epoch"]) for r in csv.DictReader(f)] == [10, 20, 30, 40]
    # The two seeds are different networks.
    w = jax.tree.leaves(whole.params)[0]
    assert not np.allclose(w[0], w[1])
    # load_policy reads the final checkpoint back.
    _, params = meta.load_policy(tmp_path / "b", 1, 8, cfg)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(whole.params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_load_policy_reads_params_whatever_the_optimiser_state(tmp_path):
    import orbax.checkpoint as ocp

    cfg = _train_cfg()
    init, _ = meta.make_trainer(meta.MetaPolicy(1, 8), cfg, n_rows=4)
    params = jax.tree.map(lambda a: a + 1.0, init(meta.seed_keys(cfg)).params)
    # A checkpoint from a trainer with another optimiser layout (here: none of Adam's).
    state = {"params": params, "opt_state": {"other": jnp.zeros(3)}, "step": jnp.asarray(7)}
    with ocp.CheckpointManager((tmp_path / "checkpoints").resolve()) as manager:
        manager.save(7, args=ocp.args.StandardSave(state))
    _, loaded = meta.load_policy(tmp_path, 1, 8, cfg)
    for a, b in zip(jax.tree.leaves(loaded), jax.tree.leaves(params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_dataset_save_load_round_trip(tmp_path):
    data = _table_dataset((7.0, 18.0))
    meta.save_dataset(tmp_path / "d.npz", data)
    back = meta.load_dataset(tmp_path / "d.npz")
    for a, b in zip(data, back, strict=True):
        np.testing.assert_array_equal(a, b)


def test_recorded_dataset_is_contextualised_with_the_experts_task():
    """Three synthetic experts, K = 1, noise off: X = (step / T, normalised own task), Y = their actions."""
    tasks = (7.5, 12.0, 16.5)
    experts = synthetic_experts.synthetic_experts(tasks)
    env = meta.dataset_env(1)
    assert all(v == 0.0 for v in env.config.noise.values())
    data, metrics = meta.collect_dataset(env, experts, repetitions=1)
    n_steps = env.n_steps
    assert data.obs.shape == (3 * n_steps, 2) and data.actions.shape == (3 * n_steps, 22)
    assert metrics["final_error"].shape == (3, 1)
    np.testing.assert_allclose(data.task, np.repeat(tasks, n_steps))
    np.testing.assert_allclose(data.obs[:, 1], (np.repeat(tasks, n_steps) - 7.0) / 11.0, rtol=1e-6)
    np.testing.assert_allclose(data.obs[:, 0], np.tile(np.arange(n_steps) / n_steps, 3), atol=1e-6)
    np.testing.assert_allclose(data.actions, np.asarray(experts.params).reshape(-1, 22), atol=1e-6)


def test_noisy_recording_env_when_k_above_one():
    assert meta.dataset_env(3).config.noise.friction > 0


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"train.epochs": 1000, "train.chunk": 300}, "1000"),
        ({"train.batch_size": 0}, "batch_size"),
        ({"eval.tasks": (5.0,)}, "5.0"),
        ({"dataset.repetitions": 0}, "repetitions"),
    ],
)
def test_bad_config_names_the_value(overrides, match):
    with pytest.raises(ValueError, match=match):
        meta.make_config("tiny", overrides)


def test_json_safe_strict_json():
    assert meta.json_safe({"a": [float("nan"), 1.0], "b": float("inf")}) == {"a": [None, 1.0], "b": None}


def test_unknown_preset():
    with pytest.raises(ValueError, match="huge"):
        meta.make_config("huge")
