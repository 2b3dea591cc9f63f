"""The meta-policies' one BC trainer (`bc.make_trainer`): every net padded and stacked in one
program with a hand-written backward pass, held to `jax.grad`'s optimisation of each net alone;
padding that changes nothing; the epoch's loop unrolled; resuming; the meta stage's use of it."""

import csv
import functools
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from bumps_jax import config
from bumps_jax.algo import bc
from bumps_jax.pipeline.stages import meta as meta_stage

# Two nets unlike in depth and width, as the paper's 4x256 and 11x128 are.
MODELS = {"wide": bc.MetaPolicy(depth=2, width=8), "deep": bc.MetaPolicy(depth=4, width=4)}


def _train_cfg(**changes):
    cfg = config.make_config("tiny").meta.train
    cfg.unlock()
    cfg.update({"learning_rate": 1e-2, "decay_every": 2, "epochs": 4, "chunk": 2, "batch_size": 128, "n_seeds": 2,
                **changes})  # fmt: skip
    cfg.lock()
    return cfg


def _data(n=300, obs_size=2, seed=2):
    rng = np.random.default_rng(seed)
    obs = jnp.asarray(rng.uniform(size=(n, obs_size)), jnp.float32)
    return obs, jnp.asarray(rng.normal(size=(n, 22)), jnp.float32)


def _assert_close(a, b, rtol=1e-5, atol=1e-6):
    jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=rtol, atol=atol), a, b)


def reference_trainer(model, train_cfg, n_rows: int, obs_size: int = 2):
    """The optimisation the trainer must perform, written the plain way for one net: flax's
    initialisation, `jax.value_and_grad` of its MAE, Adam over one flat vector with the staircase
    schedule, the same shuffled batches, one step per loop iteration. (init, chunk) over one
    net's `bc.TrainState`, as `bc.make_trainer` has over a dict of them."""
    epoch_steps = bc.steps_per_epoch(train_cfg, n_rows)
    optimizer = optax.flatten(optax.adam(bc.lr_schedule(train_cfg, epoch_steps)))
    apply_fn = bc.policy_apply(model)

    def init_one(key):
        params = model.init(key, jnp.zeros((1, obs_size)))["params"]
        return params, optimizer.init(params)

    @jax.jit
    def init(seed_keys):
        params, opt_state = jax.vmap(init_one)(seed_keys)
        return bc.TrainState(params, opt_state, jnp.zeros((), jnp.int32))

    def epoch(obs, actions, seed_key, carry, epoch_index):
        n = obs.shape[0]

        def step(carry, batch):
            params, opt_state = carry
            idx, slot = batch
            weights = (slot < n).astype(obs.dtype)
            loss, grads = jax.value_and_grad(bc.mae_loss)(params, apply_fn, obs[idx], actions[idx], weights)
            updates, opt_state = optimizer.update(grads, opt_state, params)
            return (optax.apply_updates(params, updates), opt_state), loss

        return jax.lax.scan(step, carry, bc.epoch_batches(seed_key, epoch_index, n, epoch_steps, 128))

    @jax.jit
    def chunk(state, obs, actions, seed_keys):
        epochs = state.step // epoch_steps + jnp.arange(int(train_cfg.chunk), dtype=jnp.int32)

        def one(params, opt_state, key):
            (params, opt_state), losses = jax.lax.scan(
                functools.partial(epoch, obs, actions, key), (params, opt_state), epochs
            )
            return params, opt_state, losses.reshape(-1)

        params, opt_state, losses = jax.vmap(one)(state.params, state.opt_state, seed_keys)
        return bc.TrainState(params, opt_state, state.step + int(train_cfg.chunk) * epoch_steps), losses

    return init, chunk


def _run(init, chunk, obs, actions, keys, chunks=2):
    state = init(keys)
    for _ in range(chunks):
        state, losses = chunk(state, obs, actions, keys)
    return state, losses


def test_the_trainer_is_autodiffs_optimisation_of_each_net_alone():
    """Two chunks of the stacked trainer end, net by net, where each net's plain `jax.grad`
    training ends: the same start, losses and Adam moments. MAE's gradient is the residual's
    sign, so a residual at zero in one rounding and not the other can move a weight by one Adam
    step; on these 300 pairs (3 steps an epoch, the last partial) none does, and the tolerances
    are rounding's."""
    n_rows = 300
    obs, actions = _data(n=n_rows)
    cfg = _train_cfg()
    keys = bc.seed_keys(cfg)
    init, chunk = bc.make_trainer(MODELS, cfg, n_rows)
    assert init(keys)["wide"].params["Dense_0"]["kernel"].shape == (2, 2, 8)  # (seeds, obs, width)
    stacked, stacked_losses = _run(init, chunk, obs, actions, keys)
    for name, model in MODELS.items():
        ref_init, ref_chunk = reference_trainer(model, cfg, n_rows)
        _assert_close(init(keys)[name].params, ref_init(keys).params, rtol=0, atol=0)  # flax's initialisation
        ref, ref_losses = _run(ref_init, ref_chunk, obs, actions, keys)
        assert int(stacked[name].step) == int(ref.step) == 2 * 2 * bc.steps_per_epoch(cfg, n_rows)
        np.testing.assert_allclose(stacked_losses[name], ref_losses, rtol=1e-4)
        _assert_close(stacked[name].params, ref.params, rtol=1e-4, atol=1e-5)
        _assert_close(stacked[name].opt_state, ref.opt_state, rtol=1e-3, atol=1e-6)  # each net's own Adam state
    assert not np.allclose(stacked_losses["wide"], stacked_losses["deep"])  # two nets, not one twice


def test_a_net_alone_and_beside_another_train_alike():
    """Stacking a net beside a deeper, narrower one changes nothing but rounding."""
    obs, actions = _data()
    cfg = _train_cfg()
    keys = bc.seed_keys(cfg)
    both, both_losses = _run(*bc.make_trainer(MODELS, cfg, 300), obs, actions, keys)
    for name, model in MODELS.items():
        alone, alone_losses = _run(*bc.make_trainer({name: model}, cfg, 300), obs, actions, keys)
        np.testing.assert_allclose(both_losses[name], alone_losses[name], rtol=1e-5)
        _assert_close(both[name], alone[name], rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("models", [MODELS, {"one": bc.MetaPolicy(1, 4), "two": bc.MetaPolicy(1, 6)}])
def test_the_hand_written_backward_is_autodiffs_gradient(models):
    """The batched backward pass: each net's loss and gradient equal `jax.grad` of its own flax
    net's MAE (padding included; nets of one hidden layer too: no stacked layers at all), and a
    narrower or shallower net's padding gets exactly zero gradient, so Adam leaves it at zero."""
    obs, actions = _data(n=40)
    weights = jnp.asarray(np.r_[np.ones(33), np.zeros(7)], jnp.float32)  # a last, partial batch
    params = {name: m.init(jax.random.key(i), obs[:1])["params"] for i, (name, m) in enumerate(models.items())}
    stacked = bc.stack_params(models, params)
    _assert_close(bc.unstack_params(models, stacked), params, rtol=0, atol=0)
    out = bc.make_forward(models)(stacked, obs)
    losses, grads = bc.make_loss_and_grads(models)(stacked, obs, actions, weights)
    by_net = bc.unstack_params(models, grads)
    for i, (name, model) in enumerate(models.items()):
        np.testing.assert_allclose(out[i], model.apply({"params": params[name]}, obs), rtol=1e-6, atol=1e-6)
        want, want_grads = jax.value_and_grad(bc.mae_loss)(params[name], bc.policy_apply(model), obs, actions, weights)
        np.testing.assert_allclose(losses[i], want, rtol=1e-6)
        _assert_close(by_net[name], want_grads, rtol=1e-5, atol=1e-7)
    # everything `unstack_params` leaves out is padding: its gradient is exactly zero
    padding = jax.tree.map(lambda g, s: g - s, grads, bc.stack_params(models, by_net))
    assert all(np.all(np.asarray(leaf) == 0) for leaf in jax.tree.leaves(padding))
    if "wide" in models:
        assert np.any(np.asarray(grads["wh"][0, 0]) != 0)  # the shallower net's own second layer learns


def test_normalised_observations_and_mismatched_nets():
    norm = ((0.5, 0.5, 0.5), (2.0, 2.0, 2.0))
    models = {"a": bc.MetaPolicy(1, 4, obs_norm=norm), "b": bc.MetaPolicy(2, 3, obs_norm=norm)}
    obs, actions = _data(n=200, obs_size=3)
    cfg = _train_cfg(n_seeds=1)
    keys = bc.seed_keys(cfg)
    stacked, stacked_losses = _run(*bc.make_trainer(models, cfg, 200, obs_size=3), obs, actions, keys, chunks=1)
    for name, model in models.items():
        ref, ref_losses = _run(*reference_trainer(model, cfg, 200, obs_size=3), obs, actions, keys, chunks=1)
        np.testing.assert_allclose(stacked_losses[name], ref_losses, rtol=1e-4)
        # MAE's gradient is the residual's sign: a residual at zero in one rounding and not the
        # other moves a weight by a whole Adam step (here 1e-2 or less) in one of the two
        _assert_close(stacked[name].params, ref.params, rtol=0, atol=1e-2)
    with pytest.raises(ValueError, match="share n_actions and obs_norm"):
        bc.make_trainer({"a": bc.MetaPolicy(1, 4), "b": bc.MetaPolicy(1, 4, n_actions=6)}, cfg, 200)


def _scan_unrolls(jaxpr) -> list[int]:
    """The `unroll` of every scan in a jaxpr, nested programs included."""
    out = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "scan":
            out.append(int(eqn.params["unroll"]))
        for value in eqn.params.values():
            for sub in value if isinstance(value, tuple | list) else (value,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    out += _scan_unrolls(inner)
    return out


def test_the_epoch_loop_is_unrolled_at_most_an_epoch():
    """`bc.UNROLL` steps per iteration of the epoch's loop, at most the epoch's (the paper's 1,725
    pairs: 14 steps, the whole epoch); the other test above holds the unrolled loop to the plain one."""
    assert bc.UNROLL == 14 and bc.steps_unrolled(bc.steps_per_epoch(_train_cfg(), 23 * 75)) == 14
    assert bc.steps_unrolled(bc.steps_per_epoch(_train_cfg(), 20_000)) == 14
    obs, actions = _data()
    cfg = _train_cfg()
    init, chunk = bc.make_trainer(MODELS, cfg, 300)
    keys = bc.seed_keys(cfg)
    scans = _scan_unrolls(jax.make_jaxpr(chunk)(init(keys), obs, actions, keys).jaxpr)
    assert 3 in scans and set(scans) <= {1, 3}, scans  # 300 pairs: 3 steps an epoch, unrolled whole


def _dataset(n=300):
    obs, actions = _data(n=n)
    return bc.Dataset(np.asarray(obs), np.asarray(actions), np.zeros(n, np.float32))


def test_nets_trained_in_one_loop_keep_a_net_alone_files_and_resume(tmp_path):
    """`bc.train_nets`: each net's progress.csv and checkpoints in its own folder, as a net trained
    alone; a run stopped after one chunk resumes to the uninterrupted result, also when one net
    saved a chunk more than the other before the kill; `load_policy` reads each net back."""
    data, cfg = _dataset(), _train_cfg(epochs=6)
    trainer = bc.make_trainer(MODELS, cfg, 300)
    quiet = lambda *a, **k: None  # noqa: E731
    dirs = {name: tmp_path / "whole" / name for name in MODELS}
    whole = bc.train_nets(MODELS, data, cfg, dirs, say=quiet, trainer=trainer)
    part = {name: tmp_path / "part" / name for name in MODELS}
    bc.train_nets(MODELS, data, cfg, part, say=quiet, max_chunks=2, trainer=trainer)
    newest = part["deep"] / "checkpoints" / "12"  # 2 chunks x 2 epochs x 3 steps
    shutil.rmtree(newest)  # killed between the two nets' saves: "wide" is a chunk ahead
    lines = []
    resumed = bc.train_nets(MODELS, data, cfg, part, say=lines.append, trainer=trainer)
    assert lines[0].startswith("  resumed from epoch 2 in") and "loss wide" in lines[1]
    _assert_close(resumed, whole, rtol=0, atol=0)
    for name, model in MODELS.items():
        with open(part[name] / "progress.csv") as f:
            assert [int(r["epoch"]) for r in csv.DictReader(f)] == [2, 4, 6]
        _, params = bc.load_policy(part[name], model.depth, model.width, cfg)
        _assert_close(params, whole[name].params, rtol=0, atol=0)


def test_the_meta_stage_trains_its_nets_in_one_loop(env, tmp_path):
    """The stage's two nets, unlike in depth and width as the paper's are (at sizes that compile
    quickly), trained in one loop to the losses of each net's plain `jax.grad` training."""
    data = _dataset(n=225)
    nets = {"meta.nets.meta_4x256": (2, 16), "meta.nets.meta_11x128": (4, 8)}
    cfg = config.make_config("tiny", {"meta.train.epochs": 4, "meta.train.chunk": 2, **nets})
    lines = []
    models, states, seconds = meta_stage.train(cfg, tmp_path, data, env, say=lines.append)
    assert "trained stacked in one loop" in lines[2]
    assert set(states) == set(seconds) == set(cfg.meta.nets) and all(int(s.step) == 8 for s in states.values())
    keys = bc.seed_keys(cfg.meta.train)
    for name, model in models.items():
        ref_init, ref_chunk = reference_trainer(model, cfg.meta.train, 225)
        _, ref_losses = _run(ref_init, ref_chunk, jnp.asarray(data.obs), jnp.asarray(data.actions), keys)
        with open(tmp_path / name / "progress.csv") as f:
            last = float(list(csv.DictReader(f))[-1]["loss_mean"])
        np.testing.assert_allclose(last, float(np.asarray(ref_losses).mean()), rtol=1e-4)


def test_bc_profile_writes_its_record(tmp_path):
    """benchmarks.bc_profile on the CPU: a timed chunk and one compiled with per-program options;
    no device kernels to count here, which the record says; bad input is one clear line."""
    from benchmarks import bc_profile  # noqa: PLC0415

    out = tmp_path / "bc_profile.json"
    record = bc_profile.main(["--preset", "tiny", "--epochs", "1", "--out", str(out)])
    assert record["steps_per_chunk"] == record["epochs_per_chunk"] * 2  # the tiny dataset: 2 batches an epoch
    assert record["unroll"] == 2
    assert record["us_per_step"] > 0 and record["program_options"]["us_per_step"] > 0
    assert record["traced"] is False and out.exists()
    assert bc_profile._kind("gemm_fusion_dot_431") == "gemm_fusion_dot"
    assert bc_profile._kind("loop_select_tanh_fusion") == "loop_select_tanh_fusion"
    with pytest.raises(SystemExit):
        bc_profile.parse_args(["--preset", "tiny", "--epochs", "0", "--out", str(out)])


def test_a_batch_larger_than_the_dataset_trains_as_the_whole_dataset(tmp_path):
    """Every batch was padded to batch_size slots: 100000 on a dataset of 960 pairs trained for many
    minutes where 128 takes seconds. A batch now holds at most the dataset: the same nets as a
    batch of exactly its pairs."""
    obs, actions = _data(n=100)
    data = bc.Dataset(np.asarray(obs), np.asarray(actions), np.zeros(100, np.float32))
    nets = [
        bc.train(MODELS["wide"], data, _train_cfg(batch_size=size), tmp_path / f"net{size}") for size in (100000, 100)
    ]
    for a, b in zip(jax.tree.leaves(nets[0]), jax.tree.leaves(nets[1]), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
