"""The stacked BC trainer (bumps_jax.algo.bc_stacked): the joint trainer's optimisation in one stacked
program, padding that changes nothing, and states either trainer resumes."""

import csv
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bumps_jax import config
from bumps_jax.algo import bc, bc_stacked
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


def _setup(backward="autodiff"):
    """(obs, actions, seed keys, the joint trainer's (init, chunk), the stacked trainer's (init, chunk))
    of MODELS on 300 random pairs."""
    obs, actions = _data()
    cfg = _train_cfg()
    joint = bc.make_joint_trainer(MODELS, cfg, 300)
    return obs, actions, bc.seed_keys(cfg), joint, bc_stacked.make_stacked_trainer(MODELS, cfg, 300, backward=backward)


def test_stacked_nets_end_where_the_joint_trainer_ends():
    obs, actions, keys, (init, chunk), (init_s, chunk_s) = _setup()
    joint, stacked = init(keys), init_s(keys)
    _assert_close(joint, stacked, rtol=0, atol=0)  # the same start: flax's initialisation
    for _ in range(2):
        joint, joint_losses = chunk(joint, obs, actions, keys)
        stacked, stacked_losses = chunk_s(stacked, obs, actions, keys)
    for name in MODELS:
        assert int(stacked[name].step) == int(joint[name].step) == 12
        np.testing.assert_allclose(stacked_losses[name], joint_losses[name], rtol=1e-5)
        _assert_close(stacked[name].params, joint[name].params)
        _assert_close(stacked[name].opt_state, joint[name].opt_state)  # Adam's moments laid out as the joint's
    assert not np.allclose(stacked_losses["wide"], stacked_losses["deep"])  # two nets, not one twice


def test_either_trainer_resumes_the_others_state():
    obs, actions, keys, (init, chunk), (_, chunk_s) = _setup()
    both_joint = chunk(chunk(init(keys), obs, actions, keys)[0], obs, actions, keys)[0]
    mixed = chunk(chunk_s(init(keys), obs, actions, keys)[0], obs, actions, keys)[0]
    _assert_close(mixed, both_joint)


def test_padding_gets_exactly_zero_gradients_and_stacking_round_trips():
    """A narrower net's padded units and a shallower net's extra layers: zero gradient, so Adam
    leaves them at zero; each net's outputs are its flax net's."""
    obs, actions = _data(n=16)
    params = {name: m.init(jax.random.key(i), obs[:1])["params"] for i, (name, m) in enumerate(MODELS.items())}
    stacked = bc_stacked.stack_params(MODELS, params)
    _assert_close(bc_stacked.unstack_params(MODELS, stacked), params, rtol=0, atol=0)
    out = bc_stacked.make_forward(MODELS)(stacked, obs)
    for i, (name, model) in enumerate(MODELS.items()):
        np.testing.assert_allclose(out[i], model.apply({"params": params[name]}, obs), rtol=1e-6, atol=1e-6)
    grads = jax.grad(lambda s: jnp.sum(jnp.abs(bc_stacked.make_forward(MODELS)(s, obs) - actions)))(stacked)
    wide, deep = 0, 1
    assert np.all(np.asarray(grads["wh"][wide, 1:]) == 0) and np.all(np.asarray(grads["bh"][wide, 1:]) == 0)
    assert np.any(np.asarray(grads["wh"][wide, 0]) != 0)  # its own second layer learns
    for key, cut in (("w0", np.s_[deep, :, 4:]), ("b0", np.s_[deep, 4:]), ("wh", np.s_[deep, :, 4:, :]),
                     ("wh", np.s_[deep, :, :, 4:]), ("bh", np.s_[deep, :, 4:]), ("wo", np.s_[deep, 4:])):  # fmt: skip
        assert np.all(np.asarray(grads[key][cut]) == 0), key


def test_normalised_observations_and_mismatched_nets():
    norm = ((0.5, 0.5, 0.5), (2.0, 2.0, 2.0))
    models = {"a": bc.MetaPolicy(1, 4, obs_norm=norm), "b": bc.MetaPolicy(2, 3, obs_norm=norm)}
    obs, actions = _data(n=200, obs_size=3)
    cfg = _train_cfg(n_seeds=1)
    keys = bc.seed_keys(cfg)
    init, chunk = bc.make_joint_trainer(models, cfg, 200, obs_size=3)
    init_s, chunk_s = bc_stacked.make_stacked_trainer(models, cfg, 200, obs_size=3)
    stacked, stacked_losses = chunk_s(init_s(keys), obs, actions, keys)
    joint, joint_losses = chunk(init(keys), obs, actions, keys)
    for name in models:
        np.testing.assert_allclose(stacked_losses[name], joint_losses[name], rtol=1e-4)
        # MAE's gradient is the residual's sign: a residual at zero in one rounding and not the
        # other moves a weight by a whole Adam step (here 1e-2 or less) in one of the two
        _assert_close(stacked[name].params, joint[name].params, rtol=0, atol=1e-2)
    with pytest.raises(ValueError, match="share n_actions and obs_norm"):
        bc_stacked.make_stacked_trainer({"a": bc.MetaPolicy(1, 4), "b": bc.MetaPolicy(1, 4, n_actions=6)}, cfg, 200)


@pytest.mark.parametrize("models", [MODELS, {"one": bc.MetaPolicy(1, 4), "two": bc.MetaPolicy(1, 6)}])
def test_the_hand_written_backward_is_autodiffs_gradient(models):
    """The batched backward pass: the same losses and gradients as `jax.grad`, padding included
    (nets of one hidden layer too: no stacked layers at all)."""
    obs, actions = _data(n=40)
    weights = jnp.asarray(np.r_[np.ones(33), np.zeros(7)], jnp.float32)  # a last, partial batch
    params = {name: m.init(jax.random.key(i), obs[:1])["params"] for i, (name, m) in enumerate(models.items())}
    stacked = bc_stacked.stack_params(models, params)
    auto = bc_stacked.make_loss_and_grads(models, "autodiff")(stacked, obs, actions, weights)
    batched = bc_stacked.make_loss_and_grads(models, "batched")(stacked, obs, actions, weights)
    _assert_close(batched, auto, rtol=1e-5, atol=1e-7)
    for name, model in models.items():  # each net's loss is its flax net's MAE over the rows of weight 1
        i = list(models).index(name)
        want = bc.mae_loss(params[name], bc.policy_apply(model), obs, actions, weights)
        np.testing.assert_allclose(batched[0][i], want, rtol=1e-6)
    with pytest.raises(ValueError, match="backward must be 'autodiff' or 'batched', got 'manual'"):
        bc_stacked.make_loss_and_grads(models, "manual")


def test_the_batched_backward_trains_as_the_joint_trainer():
    obs, actions, keys, (init, chunk), (_, chunk_b) = _setup(backward="batched")
    joint, joint_losses = chunk(init(keys), obs, actions, keys)
    batched, batched_losses = chunk_b(init(keys), obs, actions, keys)
    for name in MODELS:
        np.testing.assert_allclose(batched_losses[name], joint_losses[name], rtol=1e-4)
        _assert_close(batched[name].params, joint[name].params, rtol=0, atol=1e-2)  # MAE's sign: see above


def _dataset(n=300):
    obs, actions = _data(n=n)
    return bc.Dataset(np.asarray(obs), np.asarray(actions), np.zeros(n, np.float32))


def test_nets_trained_in_one_loop_keep_a_net_alone_files_and_resume(tmp_path):
    """`bc.train_nets`: each net's progress.csv and checkpoints in its own folder, as a net trained
    alone; a run stopped after one chunk resumes to the uninterrupted result, also when one net
    saved a chunk more than the other before the kill; `load_policy` reads each net back."""
    data, cfg = _dataset(), _train_cfg(epochs=6)
    trainer = bc_stacked.make_stacked_trainer(MODELS, cfg, 300)
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


def test_the_meta_stage_trains_stacked_when_told(env, tmp_path):
    """`meta.trainer`: "stacked" and "stacked_batched" (the paper preset's) train the stage's nets
    in one loop to the losses of "separate"; an unknown value is one line naming it."""
    data = _dataset(n=225)
    # The stage's two nets, unlike in depth and width as the paper's are, at sizes that compile quickly.
    nets = {"meta.nets.meta_4x256": (2, 16), "meta.nets.meta_11x128": (4, 8)}
    losses = {}
    for trainer in ("separate", "stacked", "stacked_batched"):
        cfg = config.make_config(
            "tiny", {"meta.trainer": trainer, "meta.train.epochs": 4, "meta.train.chunk": 2, **nets}
        )
        _, states, seconds = meta_stage.train(cfg, tmp_path / trainer, data, env, say=lambda *a, **k: None)
        assert set(states) == set(seconds) == set(cfg.meta.nets) and all(int(s.step) == 8 for s in states.values())
        with open(tmp_path / trainer / "meta_11x128" / "progress.csv") as f:
            losses[trainer] = [float(r["loss_mean"]) for r in csv.DictReader(f)]
    np.testing.assert_allclose(losses["stacked"], losses["separate"], rtol=1e-3)
    np.testing.assert_allclose(losses["stacked_batched"], losses["separate"], rtol=1e-3)
    with pytest.raises(ValueError, match=r"meta.trainer must be one of \('separate', 'stacked', 'stacked_batched'\)"):
        config.make_config("tiny", {"meta.trainer": "fused"})


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


@pytest.mark.parametrize("make", ["joint", "stacked_batched"])
def test_unrolled_steps_train_as_the_loop_does(make):
    """meta.train.unroll runs several steps per loop iteration: the same steps on the same batches."""
    obs, actions = _data()
    trainers = {}
    for unroll in (1, 3):  # 300 pairs: 3 steps per epoch, unrolled whole
        cfg = _train_cfg(unroll=unroll)
        trainers[unroll] = (
            bc.make_joint_trainer(MODELS, cfg, 300)
            if make == "joint"
            else bc_stacked.make_stacked_trainer(MODELS, cfg, 300, backward="batched")
        )
    keys = bc.seed_keys(_train_cfg())
    ends = {}
    for unroll, (init, chunk) in trainers.items():
        state = init(keys)
        # the knob reaches the program: its epoch loop (the scan over batches) unrolled that far
        scans = _scan_unrolls(jax.make_jaxpr(chunk)(state, obs, actions, keys).jaxpr)
        assert sorted(set(scans)) == sorted({1, unroll}), scans
        for _ in range(2):
            state, losses = chunk(state, obs, actions, keys)
        ends[unroll] = (state, losses)
    (loop, loop_losses), (unrolled, unrolled_losses) = ends[1], ends[3]
    for name in MODELS:
        assert int(unrolled[name].step) == int(loop[name].step) == 12
        np.testing.assert_allclose(unrolled_losses[name], loop_losses[name], rtol=1e-5)
        _assert_close(unrolled[name].params, loop[name].params)


def test_bc_profile_writes_its_record(tmp_path):
    """benchmarks.bc_profile on the CPU: a timed chunk and one compiled with per-program options;
    no device kernels to count here, which the record says; bad input is one clear line."""
    from benchmarks import bc_profile  # noqa: PLC0415

    out = tmp_path / "bc_profile.json"
    record = bc_profile.main(["--preset", "tiny", "--set", "meta.trainer=stacked_batched", "--epochs", "1",
                              "--out", str(out)])  # fmt: skip
    assert record["steps_per_chunk"] == record["epochs_per_chunk"] * 2  # the tiny dataset: 2 batches an epoch
    assert record["us_per_step"] > 0 and record["program_options"]["us_per_step"] > 0
    assert record["traced"] is False and out.exists()
    assert bc_profile._kind("gemm_fusion_dot_431") == "gemm_fusion_dot"
    assert bc_profile._kind("loop_select_tanh_fusion") == "loop_select_tanh_fusion"
    with pytest.raises(SystemExit):
        bc_profile.parse_args(["--preset", "tiny", "--out", str(out)])  # the separate trainer: nothing to profile
