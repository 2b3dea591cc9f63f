"""Meta-training (bc.py and the meta and filter stages): lr schedule, behaviour cloning, resume
(also past a corrupt checkpoint), loading a policy, the dataset's contextualisation, and the two
stages end to end on stand-in experts."""

import csv
import json
import re
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import stand_ins
from rollout_memo import RolloutMemo

from bumps_jax import cli, config, runio
from bumps_jax.algo import bc, evaluate, filtering
from bumps_jax.pipeline import programs as meta_programs
from bumps_jax.pipeline import runner as pipeline
from bumps_jax.pipeline.stages import experts as experts_stage
from bumps_jax.pipeline.stages import filter as filter_stage
from bumps_jax.pipeline.stages import heldout
from bumps_jax.pipeline.stages import meta as meta_stage
from bumps_jax.report import publish, tables
from bumps_jax.report import summary as report
from bumps_jax.tasks.kick import env as kick_env
from bumps_jax.tasks.kick import policies
from bumps_jax.tasks.kick.targets import HELDOUT_TARGETS


def quiet(*args, **kwargs):
    pass


def _train_cfg(**changes):
    cfg = config.make_config("tiny").meta.train
    cfg.unlock()
    cfg.update(changes)
    cfg.lock()
    return cfg


def test_lr_schedule_matches_the_paper():
    """3e-4 x 0.8 every 5000 epochs, an epoch being one pass: 14 steps for 23 experts x 75 steps."""
    train = config.make_config("paper").meta.train
    epoch_steps = bc.steps_per_epoch(train, 23 * 75)
    assert epoch_steps == 14  # 13 full batches of 128 and one of 61
    schedule = bc.lr_schedule(train, epoch_steps)
    for epoch, lr in [(0, 3e-4), (4999, 3e-4), (5000, 2.4e-4), (12000, 1.92e-4), (149_999, 3e-4 * 0.8**29)]:
        assert float(schedule(epoch * epoch_steps)) == pytest.approx(lr, rel=1e-5), epoch
        assert float(schedule(epoch * epoch_steps + epoch_steps - 1)) == pytest.approx(lr, rel=1e-5), epoch


def test_an_epoch_visits_every_row_once():
    """The loss of one epoch at lr ~ 0 is the dataset's mean error, each row counted once."""
    rng = np.random.default_rng(1)
    obs = jnp.asarray(rng.uniform(size=(300, 2)), jnp.float32)  # 3 batches: 128, 128, 44 rows
    actions = jnp.asarray(rng.normal(size=(300, 22)), jnp.float32)
    cfg = _train_cfg(learning_rate=1e-12, epochs=1, chunk=1, batch_size=128)
    model = bc.MetaPolicy(depth=1, width=8)
    init, chunk = bc.make_trainer({"net": model}, cfg, 300)
    states = init(bc.seed_keys(cfg))
    params0 = jax.tree.map(lambda a: a[0], states["net"].params)
    per_row = np.abs(np.asarray(bc.policy_apply(model)(params0, obs)) - np.asarray(actions)).mean(axis=1)
    states, losses = chunk(states, obs, actions, bc.seed_keys(cfg))
    losses = losses["net"]
    assert int(states["net"].step) == 3 and losses.shape == (1, 3)
    weighted = (128 * losses[0, 0] + 128 * losses[0, 1] + 44 * losses[0, 2]) / 300
    assert float(weighted) == pytest.approx(per_row.mean(), rel=1e-4)


def test_nets_trained_in_one_program_end_where_each_alone_does():
    rng = np.random.default_rng(2)
    obs = jnp.asarray(rng.uniform(size=(300, 2)), jnp.float32)
    actions = jnp.asarray(rng.normal(size=(300, 22)), jnp.float32)
    cfg = _train_cfg(learning_rate=1e-2, epochs=4, chunk=2, batch_size=128, n_seeds=2)
    models = {"a": bc.MetaPolicy(depth=1, width=8), "b": bc.MetaPolicy(depth=3, width=4)}
    keys = bc.seed_keys(cfg)
    init, chunk = bc.make_trainer(models, cfg, 300)
    states = init(keys)
    for _ in range(2):
        states, joint_losses = chunk(states, obs, actions, keys)
    for name, model in models.items():
        init_one, chunk_one = bc.make_trainer({name: model}, cfg, 300)
        state = init_one(keys)
        for _ in range(2):
            state, losses = chunk_one(state, obs, actions, keys)
        state, losses = state[name], losses[name]
        assert int(states[name].step) == int(state.step) == 12
        np.testing.assert_allclose(joint_losses[name], losses, rtol=1e-5)
        jax.tree.map(
            lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6), states[name].params, state.params
        )
    assert not np.allclose(joint_losses["a"], joint_losses["b"])  # two nets, not one twice


def test_behaviour_cloning_recovers_a_linear_map(tmp_path):
    rng = np.random.default_rng(0)
    w = rng.normal(size=(2, 22)).astype(np.float32) * 0.5
    b = rng.normal(size=22).astype(np.float32) * 0.3
    x = rng.uniform(size=(4096, 2)).astype(np.float32)
    data = bc.Dataset(obs=x, actions=x @ w + b, task=np.zeros(len(x), np.float32))
    # 4096 pairs: 32 steps per epoch, 2880 steps in all.
    cfg = _train_cfg(learning_rate=3e-3, decay_every=30, epochs=90, chunk=30, batch_size=128)
    model = bc.MetaPolicy(depth=2, width=32)
    state = bc.train(model, data, cfg, tmp_path, say=quiet)
    x_test = rng.uniform(size=(256, 2)).astype(np.float32)
    params0 = jax.tree.map(lambda a: a[0], state.params)
    pred = np.asarray(bc.policy_apply(model)(params0, jnp.asarray(x_test)))
    assert np.abs(pred - (x_test @ w + b)).mean() < 0.03


def _table_dataset(tasks) -> bc.Dataset:
    """The stand-in experts' (obs, action) pairs without simulating: phase k / T, their table row."""
    experts = stand_ins.synthetic_experts(tasks)
    tables_ = np.asarray(experts.params)  # (E, T, 22)
    n_exp, n_steps, _ = tables_.shape
    phase = np.tile(np.arange(n_steps) / n_steps, n_exp)
    task = np.repeat(np.asarray(tasks, np.float32), n_steps)
    ctx = (task - 7.0) / 11.0
    return bc.Dataset(np.stack([phase, ctx], 1).astype(np.float32), tables_.reshape(-1, 22), task)


def test_loss_falls_on_the_tiny_preset(tmp_path):
    data = _table_dataset(kick_env.meta_train_tasks())
    cfg = config.make_config("tiny", {"meta.train.epochs": 50, "meta.train.chunk": 25, "meta.train.decay_every": 25})
    # All 23 experts' rows (14 steps per epoch): the tiny schedule cut to 50 epochs, 2 chunks, the
    # rate decayed once between them (measured: loss 0.101 after the first chunk, 0.048 after the
    # second, from 0.453 at the start; the bar below is 0.136).
    depth, width = cfg.meta.nets["meta_4x256"]
    model = bc.MetaPolicy(depth, width)
    init, _ = bc.make_trainer({"net": model}, cfg.meta.train, len(data.obs))
    first = jax.tree.map(lambda a: a[0], init(bc.seed_keys(cfg.meta.train))["net"].params)
    initial = float(bc.mae_loss(first, bc.policy_apply(model), data.obs, data.actions))
    lines = []
    bc.train(model, data, cfg.meta.train, tmp_path, say=lines.append)
    with open(tmp_path / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    chunk, epochs = cfg.meta.train.chunk, cfg.meta.train.epochs
    assert [int(r["epoch"]) for r in rows] == list(range(chunk, epochs + 1, chunk))
    losses = [float(r["loss_mean"]) for r in rows]
    assert losses[-1] < losses[0] and losses[-1] < 0.3 * initial
    # One progress line per chunk: the first says it compiled, the others give an ETA.
    assert len(lines) == epochs // chunk and "compile included" in lines[0] and all("ETA" in x for x in lines[1:])


def test_resume_equals_uninterrupted(tmp_path):
    data = _table_dataset((8.0, 12.0))
    cfg = _train_cfg(epochs=40, chunk=10, n_seeds=2)
    model = bc.MetaPolicy(depth=1, width=8)
    trainer = bc.make_trainer({"net": model}, cfg, len(data.obs))  # 150 pairs: 2 steps per epoch
    whole = bc.train(model, data, cfg, tmp_path / "a", say=quiet, trainer=trainer)
    part = bc.train(model, data, cfg, tmp_path / "b", say=quiet, max_chunks=2, trainer=trainer)
    assert int(part.step) == 2 * 20
    resumed = bc.train(model, data, cfg, tmp_path / "b", say=quiet, trainer=trainer)
    assert int(resumed.step) == 2 * 40
    for a, b in zip(jax.tree.leaves(whole), jax.tree.leaves(resumed), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with open(tmp_path / "b" / "progress.csv") as f:
        assert [int(r["epoch"]) for r in csv.DictReader(f)] == [10, 20, 30, 40]
    # The two seeds are different networks.
    w = jax.tree.leaves(whole.params)[0]
    assert not np.allclose(w[0], w[1])
    # load_policy reads the final checkpoint back.
    _, params = bc.load_policy(tmp_path / "b", 1, 8, cfg)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(whole.params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_resume_falls_back_past_a_corrupt_checkpoint(tmp_path):
    """A truncated newest checkpoint is reported by path, set aside, and its chunk redone: the run
    still ends where an uninterrupted one does, its progress.csv without the redone chunk twice."""
    data = _table_dataset((8.0, 12.0))
    cfg = _train_cfg(epochs=30, chunk=10)
    model = bc.MetaPolicy(depth=1, width=8)
    trainer = bc.make_trainer({"net": model}, cfg, len(data.obs))
    whole = bc.train(model, data, cfg, tmp_path / "a", say=quiet, trainer=trainer)
    bc.train(model, data, cfg, tmp_path / "b", say=quiet, max_chunks=2, trainer=trainer)
    newest = tmp_path / "b" / "checkpoints" / "40"  # 2 chunks x 10 epochs x 2 steps
    for path in newest.rglob("*"):
        if path.is_file():
            path.write_bytes(b"")
    lines = []
    resumed = bc.train(model, data, cfg, tmp_path / "b", say=lines.append, trainer=trainer)
    assert any(str(newest) in line for line in lines), lines
    for a, b in zip(jax.tree.leaves(whole), jax.tree.leaves(resumed), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with open(tmp_path / "b" / "progress.csv") as f:
        assert [int(r["epoch"]) for r in csv.DictReader(f)] == [10, 20, 30]


def test_load_policy_reads_params_whatever_the_optimiser_state(tmp_path):
    import orbax.checkpoint as ocp

    cfg = _train_cfg()
    init, _ = bc.make_trainer({"net": bc.MetaPolicy(1, 8)}, cfg, n_rows=4)
    params = jax.tree.map(lambda a: a + 1.0, init(bc.seed_keys(cfg))["net"].params)
    # A checkpoint from a trainer with another optimiser layout (here: none of Adam's).
    state = {"params": params, "opt_state": {"other": jnp.zeros(3)}, "step": jnp.asarray(7)}
    with ocp.CheckpointManager((tmp_path / "checkpoints").resolve()) as manager:
        manager.save(7, args=ocp.args.StandardSave(state))
    _, loaded = bc.load_policy(tmp_path, 1, 8, cfg)
    for a, b in zip(jax.tree.leaves(loaded), jax.tree.leaves(params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_load_policy_names_the_folder_without_a_checkpoint(tmp_path):
    cfg = _train_cfg()
    with pytest.raises(ValueError, match=re.escape(str((tmp_path / "net" / "checkpoints").resolve()))):
        bc.load_policy(tmp_path / "net", 1, 8, cfg)
    (tmp_path / "net" / "checkpoints").mkdir(parents=True)
    with pytest.raises(ValueError, match="no checkpoint"):
        bc.load_policy(tmp_path / "net", 1, 8, cfg)


def test_dataset_save_load_round_trip(tmp_path):
    data = _table_dataset((7.0, 18.0))
    meta_stage.save_dataset(tmp_path / "d.npz", data)
    back = meta_stage.load_dataset(tmp_path / "d.npz")
    for a, b in zip(data, back, strict=True):
        np.testing.assert_array_equal(a, b)


def test_recording_env_is_noise_free_only_when_k_is_one():
    cfg = config.make_config("tiny")
    assert all(v == 0.0 for v in meta_stage.dataset_env(cfg).config.noise.values())
    assert cfg.env.noise.friction > 0  # the run's own env is left as it was
    noisy = config.make_config("tiny", {"meta.dataset.repetitions": 3})
    assert meta_stage.dataset_env(noisy).config.noise.friction == cfg.env.noise.friction


def test_nets_run_in_the_papers_order_first():
    assert meta_stage.net_names({"zz": 1, "meta_11x128": 1, "aa": 1, "meta_4x256": 1}) == [
        "meta_4x256",
        "meta_11x128",
        "aa",
        "zz",
    ]


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"meta.train.epochs": 1000, "meta.train.chunk": 300}, "1000"),
        ({"meta.train.batch_size": 0}, "meta.train.batch_size"),
        # every batch is padded to its size: 100000 trained for many minutes on a dataset of 225 pairs
        (
            {"meta.train.batch_size": 226},
            r"^meta.train.batch_size 226 exceeds the dataset's 225 pairs \(3 experts x 1 episode\(s\) x 75",
        ),
        ({"meta.eval.tasks": (5.0,)}, "5.0"),
        ({"meta.dataset.repetitions": 0}, "meta.dataset.repetitions"),
        ({"meta.nets.meta_4x256": (0, 256)}, "meta.nets.meta_4x256"),
    ],
)
def test_bad_config_names_the_value(overrides, match):
    with pytest.raises(ValueError, match=match):
        config.make_config("tiny", overrides)


def test_unknown_preset():
    with pytest.raises(ValueError, match="huge"):
        config.make_config("huge")


# -- the stages, on stand-in experts -----------------------------------------------------------

OVERRIDES = {
    # Both nets of one small architecture: one compiled evaluation program serves the two.
    "meta.nets.meta_4x256": (1, 16),
    "meta.nets.meta_11x128": (1, 16),
    "meta.train.epochs": 4,
    "meta.train.chunk": 2,
    "meta.eval.tasks": (10.0, 13.0),
    "filter.tasks": (10.0, 13.0),
    "filter.context_range": (9.0, 14.0),
    "filter.context_step": 2.5,
    "filter.high_context_step": 1.25,
    # Every selection and evaluation below in one call of one compiled program (at most 14
    # episodes): on a CPU a call costs its physics steps (~5 s), nearly whatever its batch.
    "filter.block": 16,
    # Two held-out targets, both nearest the 12 m stand-in expert; few kicks: one new program (the
    # experts'), the meta-policies' is the filter stage's.
    "heldout.targets": (10.023, 12.987),
    "heldout.repetitions": 3,
    "heldout.selection_repetitions": 2,
}


# The two nets of OVERRIDES are one architecture trained from the same seeds on the same dataset,
# so they end as the same params, and every stage rolls them out on the same episodes: their
# rollouts run once (on a CPU each call costs seconds). Shared by the stage and held-out runs.
ROLLOUTS = RolloutMemo()


def _experts_run(cfg, run_dir):
    """What the experts stage leaves for the meta stage: experts.json (a record of made-up
    numbers) and a final_params folder (the stand-ins replace what it would hold)."""
    tasks = cfg.experts.tasks
    rng = np.random.default_rng(0)
    err = rng.uniform(0.1, 0.5, size=(len(tasks), 4))
    metrics = {"final_error": err, "rel_error": err / np.asarray(tasks)[:, None], "valid": np.ones_like(err)}
    record = {
        **evaluate.experts_record(tasks, metrics, 600),
        **runio.provenance(cfg.preset, 0.0, config.resolved_env(cfg)),
    }
    # The starting kicks before PPO: made-up numbers a little worse than the experts'.
    record["starting_kicks"] = evaluate.tasks_record(tasks, {**metrics, "final_error": err + 0.3})
    runio.write_json(run_dir / "experts" / "experts.json", record)
    (run_dir / "experts" / "final_params").mkdir()
    return record


@pytest.fixture(scope="module")
def stage_run(tmp_path_factory):
    """The meta and filter stages run in order by the stage runner on stand-in experts."""
    cfg = config.make_config("tiny", OVERRIDES)
    run_dir = tmp_path_factory.mktemp("run")
    record = _experts_run(cfg, run_dir)
    family = stand_ins.synthetic_experts(cfg.experts.tasks)
    loads = []

    def load_family(c, d):
        loads.append(d)
        return family

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(experts_stage, "load_family", load_family)
        ROLLOUTS.patch(mp, filtering, meta_stage)
        table1 = pipeline.run_stage("meta", cfg, run_dir, say=quiet)
        table2 = pipeline.run_stage("filter", cfg, run_dir, say=quiet)
        # Both up to date now: read back, no work (the filter's reading of the nets' checkpoints
        # left them as the manifest hashed them).
        again = {name: pipeline.run_stage(name, cfg, run_dir, say=quiet) for name in ("meta", "filter")}
    return {"cfg": cfg, "dir": run_dir, "experts": record, "family": family, "loads": loads,
            "table1": table1, "table2": table2, "again": again}  # fmt: skip


def test_meta_stage_records_the_experts_contextualised(stage_run):
    """X = (step / T, normalised own task), Y = the expert's actions, one noise-free rollout each."""
    cfg, family = stage_run["cfg"], stage_run["family"]
    data = meta_stage.load_dataset(stage_run["dir"] / "meta" / "dataset.npz")
    n_steps, tasks = 75, np.asarray(cfg.experts.tasks)
    assert data.obs.shape == (3 * n_steps, 2) and data.actions.shape == (3 * n_steps, 22)
    np.testing.assert_allclose(data.task, np.repeat(tasks, n_steps))
    np.testing.assert_allclose(data.obs[:, 1], (np.repeat(tasks, n_steps) - 7.0) / 11.0, rtol=1e-6)
    np.testing.assert_allclose(data.obs[:, 0], np.tile(np.arange(n_steps) / n_steps, 3), atol=1e-6)
    np.testing.assert_allclose(data.actions, np.asarray(family.params).reshape(-1, 22), atol=1e-6)
    assert stage_run["loads"] == [stage_run["dir"]]  # the experts were loaded once, for the dataset


def test_meta_stage_writes_table1(stage_run):
    cfg, table1 = stage_run["cfg"], stage_run["table1"]
    saved = json.loads((stage_run["dir"] / "meta" / "table1.json").read_text())  # strict JSON
    assert saved == table1 == stage_run["again"]["meta"]
    old_keys = {"rows", "rows_per_seed", "per_task", "eval", "dataset_pairs", "timings", "device", "n_devices",
                "versions", "date", "command", "preset", "wall_s"}  # fmt: skip
    assert old_keys <= set(saved) and saved["env"]["physics_dt"] == 0.0025
    assert list(saved["rows"]) == ["experts", "starting_kicks", "meta_4x256", "meta_11x128"]
    for name, record in (("experts", stage_run["experts"]), ("starting_kicks", stage_run["experts"]["starting_kicks"])):
        expected = {k: record[k] for k in meta_stage.ROW_KEYS}
        assert {k: saved["rows"][name][k] for k in meta_stage.ROW_KEYS} == expected
        assert saved["rows"][name]["per_task"] == [
            {k: r[k] for k in meta_stage.PER_TASK_KEYS} for r in record["per_task"]
        ]
    assert saved["per_task"]["starting_kicks"]["error_mean_m"] == [
        r["error_mean_m"] for r in stage_run["experts"]["starting_kicks"]["per_task"]
    ]
    assert saved["per_task"]["experts"]["tasks"] == list(cfg.experts.tasks)
    assert saved["per_task"]["tasks"] == [10.0, 13.0] and saved["dataset_pairs"] == 3 * 75
    assert saved["eval"] == {"repetitions": 2, "n_tasks": 2, "seed": 1}
    for net in ("meta_4x256", "meta_11x128"):
        assert saved["rows"][net]["n_tasks"] == 2 and len(saved["rows_per_seed"][net]) == 1
        assert len(saved["per_task"][net]["error_mean_m"]) == 2
        assert [r["target_m"] for r in saved["rows"][net]["per_task"]] == [10.0, 13.0]
        assert [r["error_mean_m"] for r in saved["rows"][net]["per_task"]] == saved["per_task"][net]["error_mean_m"]
        assert set(saved["timings"][net]) == {"train_wall_s", "eval_wall_s"}
        with open(stage_run["dir"] / "meta" / net / "progress.csv") as f:
            assert [int(r["epoch"]) for r in csv.DictReader(f)] == [2, 4]
        # two chunks wrote two checkpoints; the finished stage keeps the newest (the trained net)
        assert len([p for p in (stage_run["dir"] / "meta" / net / "checkpoints").iterdir() if p.name.isdigit()]) == 1
    assert (stage_run["dir"] / "meta" / "table1.md").read_text() == tables.table1_markdown(saved["rows"])


def test_filter_stage_writes_table2(stage_run):
    cfg, saved = stage_run["cfg"], stage_run["table2"]
    stage_dir = stage_run["dir"] / "filter"
    assert json.loads((stage_dir / "table2.json").read_text()) == saved == stage_run["again"]["filter"]
    assert list(saved["rows"]) == list(tables.PAPER_TABLE2)
    n_low = len(filtering.candidate_contexts(cfg.filter.tasks, [9.0, 11.5, 14.0]))
    n_high = len(filtering.candidate_contexts(cfg.filter.tasks, [9.0, 10.25, 11.5, 12.75, 14.0]))
    rows = saved["rows"]
    assert (rows["filtered_4x256"]["n_contexts"], rows["high_sample_rate_4x256"]["n_contexts"]) == (n_low, n_high)
    assert rows["filtered_4x256"]["rollouts"] == n_low * 2 and rows["high_sample_rate_4x256"]["rollouts"] == n_high * 2
    assert rows["filtered_ensemble"]["rollouts"] == 2 * n_low * 2
    # Per task the ensemble keeps the lower of the two nets' selection scores.
    best = min(rows["filtered_4x256"]["selection_error_m"], rows["filtered_11x128"]["selection_error_m"])
    assert rows["filtered_ensemble"]["selection_error_m"] <= best + 1e-12
    # Each task's selection score beside its fresh error; per variant their means and the gap.
    for name, row in rows.items():
        scores, fresh = saved["per_task_selection_error_m"][name], saved["per_task_error_m"][name]
        assert len(scores) == len(fresh) == 2
        assert row["selection_error_m"] == pytest.approx(np.mean(scores))
        assert row["selection_gap_m"] == pytest.approx(np.mean(fresh) - np.mean(scores))
    for name, chosen in saved["chosen_contexts"].items():
        if name != "filtered_ensemble_uses_11x128":
            assert np.all(np.abs(np.asarray(chosen) - saved["tasks"]) <= cfg.filter.width + 1e-6), name
    assert set(saved["per_task_error_m"]) == {*tables.PAPER_TABLE2}
    assert saved["config"]["block"] == 16 and saved["paper"]["filtered_ensemble"]["error_mean_m"] == 0.40
    assert (stage_dir / "table2.md").read_text() == tables.table2_markdown(rows)
    for name in ("error_vs_target.png", "context_map.png"):
        assert (stage_dir / name).read_bytes()[:4] == b"\x89PNG"


def test_meta_inputs_name_what_is_missing(tmp_path):
    cfg = config.make_config("tiny")
    path = tmp_path / "experts" / "experts.json"
    with pytest.raises(ValueError, match=re.escape(str(path)) + ".*train-experts"):
        meta_stage.inputs(cfg, tmp_path)
    path.parent.mkdir()
    path.write_text("{not json")
    with pytest.raises(ValueError, match=re.escape(str(path))):
        meta_stage.inputs(cfg, tmp_path)
    _experts_run(cfg, tmp_path / "other")
    shutil.copy(tmp_path / "other" / "experts" / "experts.json", path)
    with pytest.raises(ValueError, match=re.escape(str(tmp_path / "experts" / "final_params"))):
        meta_stage.inputs(cfg, tmp_path)
    (tmp_path / "experts" / "final_params").mkdir()
    assert meta_stage.inputs(cfg, tmp_path)["experts"] == path
    # Experts made under another env config are refused, naming the key.
    with pytest.raises(ValueError, match="env.noise.friction"):
        meta_stage.inputs(config.make_config("tiny", {"env.noise.friction": 0.3}), tmp_path)


def test_meta_dataset_is_reused_without_loading_the_experts(tmp_path, monkeypatch):
    data = _table_dataset((8.0, 12.0))
    meta_stage.save_dataset(tmp_path / "meta" / "dataset.npz", data)

    def no_experts(cfg, run_dir):
        raise AssertionError("the experts were loaded although the dataset was saved")

    monkeypatch.setattr(experts_stage, "load_family", no_experts)
    back = meta_stage.dataset(config.make_config("tiny"), tmp_path, say=quiet)
    np.testing.assert_array_equal(back.actions, data.actions)


def test_filter_inputs_refuse_another_meta_config(stage_run):
    run_dir = stage_run["dir"]
    overrides = {**OVERRIDES, "meta.train.epochs": 6}
    with pytest.raises(ValueError, match="meta.train.epochs"):
        filter_stage.inputs(config.make_config("tiny", overrides), run_dir)
    overrides = {**OVERRIDES, "meta.nets.meta_11x128": (2, 16)}
    with pytest.raises(ValueError, match="meta.nets.meta_11x128"):
        filter_stage.inputs(config.make_config("tiny", overrides), run_dir)
    with pytest.raises(ValueError, match=re.escape(str(run_dir / "nothing" / "meta" / "table1.json"))):
        filter_stage.inputs(stage_run["cfg"], run_dir / "nothing")


# -- the held-out evaluation, shipped policies and `kick`, on the same run ------------------------


@pytest.fixture(scope="module")
def heldout_run(stage_run, tmp_path_factory):
    """evaluate --heldout on the finished stand-in run, then `publish` into a fresh repository root
    (results/heldout.json, assets/policies/)."""
    cfg, run_dir = stage_run["cfg"], stage_run["dir"]
    root = tmp_path_factory.mktemp("repo")
    variants = {}  # net -> what heldout.meta_variants returned (the dev test replays them)
    real = heldout.meta_variants

    def kept(cfg, run_dir, net, *args):
        variants[net] = real(cfg, run_dir, net, *args)
        return variants[net]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(experts_stage, "load_family", lambda c, d: stage_run["family"])
        mp.setattr(heldout, "meta_variants", kept)
        ROLLOUTS.patch(mp, filtering, meta_stage)
        record = heldout.run(cfg, run_dir, say=quiet)
        written = publish.publish(run_dir, root, cfg=cfg)
    return {"record": record, "root": root, "written": written, "variants": variants}


def test_heldout_scores_every_variant_on_its_own_targets(stage_run, heldout_run):
    cfg, record = stage_run["cfg"], heldout_run["record"]
    saved = json.loads((stage_run["dir"] / "heldout" / "heldout.json").read_text())
    assert saved == record and saved["env"]["physics_dt"] == 0.0025 and saved["env"]["impl"] == cfg.env.impl
    assert saved["targets_m"] == [10.023, 12.987] and saved["seed"] == cfg.heldout.seed == 2222
    assert list(saved["rows"]) == ["experts_nearest", "meta_4x256", "meta_11x128", "filtered_4x256",
                                   "filtered_11x128", "filtered_ensemble"]  # fmt: skip
    assert saved["nearest_expert_task_m"] == [12.0, 12.0]  # of the stand-ins' 8, 12 and 16 m
    for name, row in saved["rows"].items():
        errors = np.asarray(row["per_target_error_m"])
        assert errors.shape == (2,) and np.all(np.isfinite(errors)), name
        assert row["error_mean_m"] == pytest.approx(errors.mean()), name
        assert row["accuracy_mean"] == pytest.approx(np.mean(row["per_target_accuracy"])), name
    for name, chosen in saved["chosen_contexts"].items():
        gap = np.abs(np.asarray(chosen) - saved["targets_m"])
        assert np.all(gap <= cfg.filter.width + 1e-6), name
    rows = saved["rows"]
    best = min(rows["filtered_4x256"]["selection_error_m"], rows["filtered_11x128"]["selection_error_m"])
    assert rows["filtered_ensemble"]["selection_error_m"] <= best + 1e-12
    # Candidates: the filter's grid (9, 11.5, 14) and the two targets.
    assert rows["filtered_4x256"]["n_contexts"] == 5 and rows["filtered_4x256"]["rollouts"] == 5 * 2
    text = report.build(stage_run["dir"])
    assert "## Held-out targets" in text and "| experts_nearest |" in text and "different env" not in text


def test_dev_evaluation_uses_its_own_targets_and_noise_and_leaves_the_heldout_record(stage_run, heldout_run):
    """`evaluate --dev`: the held-out evaluation on the dev section's targets and seed, written to
    run_dir/dev/, beside (not over) the held-out record; config refuses dev settings that touch it."""
    cfg, run_dir = stage_run["cfg"], stage_run["dir"]
    heldout_before = (run_dir / "heldout" / "heldout.json").read_text()
    # The meta-policies' variants are the held-out run's code path (scored there); here they replay
    # its outputs (same shapes), and what the dev section hands them is checked: on a CPU each of
    # their six physics calls costs seconds whatever its batch.
    handed = []

    def replay(cfg_, run_dir_, net, targets, contexts, noise_keys, mesh, h):
        handed.append((net, np.asarray(targets).tolist(), noise_keys, h))
        return heldout_run["variants"][net]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(experts_stage, "load_family", lambda c, d: stage_run["family"])
        mp.setattr(heldout, "meta_variants", replay)
        record = heldout.run(cfg, run_dir, say=quiet, section="dev")
    assert [net for net, *_ in handed] == list(meta_stage.NETS)
    dev_keys = filtering.noise_keys(cfg.dev.seed)
    for _, targets, keys, h in handed:
        assert targets == list(cfg.dev.targets) and h == cfg.dev
        for got, want in zip(keys, dev_keys, strict=True):
            np.testing.assert_array_equal(jax.random.key_data(got), jax.random.key_data(want))
    saved = json.loads((run_dir / "dev" / "dev.json").read_text())
    assert saved == record and saved["section"] == "dev" and saved["seed"] == cfg.dev.seed == 3333
    assert saved["targets_m"] == list(cfg.dev.targets) == [7.485, 14.351]
    assert set(saved["rows"]) == set(heldout_run["record"]["rows"])
    assert (run_dir / "dev" / "dev.md").read_text().startswith("# Development targets")
    assert (run_dir / "heldout" / "heldout.json").read_text() == heldout_before
    for overrides, message in (
        ({"dev.seed": cfg.heldout.seed}, "dev.seed 2222 is heldout.seed"),
        ({"dev.targets": (cfg.heldout.targets[0] + 0.001,)}, "within 0.005 m of a held-out target"),
        ({"dev.targets": (12.3,)}, "dev.targets: 12.3 m lies within 0.005 m of the 0.1 m grid"),
    ):
        with pytest.raises(ValueError, match=re.escape(message)):
            config.make_config("tiny", overrides)


def test_publish_ships_the_runs_results_and_policies(stage_run, heldout_run):
    root = heldout_run["root"]
    assert json.loads((root / "results" / "heldout.json").read_text()) == heldout_run["record"]
    shipped = policies.load(root / "assets" / "policies", stage_run["cfg"].env)
    assert set(shipped.nets) == {"meta_4x256", "meta_11x128"}
    _, params = bc.load_policy(stage_run["dir"] / "meta" / "meta_4x256", 1, 16, stage_run["cfg"].meta.train)
    for a, b in zip(jax.tree.leaves(shipped.nets["meta_4x256"]), jax.tree.leaves(params), strict=True):
        np.testing.assert_array_equal(a, np.asarray(b)[0])
    np.testing.assert_array_equal(shipped.experts, np.asarray(stage_run["family"].params))
    m = shipped.manifest
    assert (m["physics_dt"], m["impl"]) == (0.0025, stage_run["cfg"].env.impl)
    assert m["filtering_choices"]["chosen_contexts"] == stage_run["table2"]["chosen_contexts"]
    assert m["heldout_choices"]["targets_m"] == [10.023, 12.987]
    assert sum(p.stat().st_size for p in (root / "assets" / "policies").iterdir()) < 5e6
    # Another physics step is refused, naming it.
    with pytest.raises(ValueError, match=re.escape("env.physics_dt: 0.0025 there, 0.005 here")):
        policies.load(root / "assets" / "policies", config.make_config("tiny", {"env.physics_dt": 0.005}).env)


def test_publish_of_records_only_keeps_assets_and_checks_configs_without_params(stage_run, heldout_run, tmp_path):
    cfg, run_dir = stage_run["cfg"], stage_run["dir"]
    kept = tmp_path / "kept"  # the run's records and manifests, not its parameters
    shutil.copytree(run_dir, kept, ignore=shutil.ignore_patterns("final_params", "checkpoints", "meta_*"))
    for name in ("meta", "filter"):  # as a pipeline leaves them (the stand-in run's stages ran alone)
        pipeline.write_manifest(kept / name, pipeline.manifest(config.section(cfg, name), {}))
    pipeline.check_current(cfg, kept, ("meta", "filter"), inputs=False)
    with pytest.raises(pipeline.StaleRunError, match="outputs without a manifest"):
        pipeline.check_current(cfg, kept, ("heldout",), inputs=False)
    with pytest.raises(ValueError, match="final_params"):  # its inputs are what a full check reads
        pipeline.check_current(cfg, kept, ("meta",))
    other = config.make_config("tiny", {"filter.width": 2 * cfg.filter.width})
    with pytest.raises(pipeline.StaleRunError, match="filter.width"):
        pipeline.check_current(other, kept, ("filter",), inputs=False)
    root = tmp_path / "repo"
    written = publish.publish(kept, root, cfg=cfg, assets=False)
    assert root / "results" / "table2.json" in written and not (root / "assets").exists()


def test_kick_filters_a_context_and_reports_the_resting_distances(stage_run, heldout_run, capsys):
    directory = heldout_run["root"] / "assets" / "policies"
    shipped = policies.load(directory)
    # The command's env: the policies' own, with the contact pool sized to its 16 kicks (a user's
    # setting wins).
    env_cfg = policies.kick_env_config(shipped.manifest, None, 16)
    assert env_cfg.warp_contacts == kick_env.CONTACTS_PER_EPISODE * 16
    assert policies.kick_env_config(shipped.manifest, {"warp_contacts": 4096}, 16).warp_contacts == 4096
    assert kick_env.resolved(env_cfg) | {"warp_contacts": 0} == kick_env.resolved(
        policies.env_config(shipped.manifest)
    ) | {"warp_contacts": 0}
    # The command filters and kicks once (on a CPU each of its two physics calls costs seconds):
    # it hands `filtered_kicks` that env, and prints what that returned.
    calls = []
    real = policies.filtered_kicks

    def spy(*args, **kwargs):
        calls.append((args, kwargs, real(*args, **kwargs)))
        return calls[-1][2]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(policies, "filtered_kicks", spy)
        cli.main(["kick", "--target", "12.3", "--kicks", "16", "--selection-reps", "2", "--policies", str(directory)])
    printed = capsys.readouterr().out
    assert len(calls) == 1
    (got_shipped, net, target, n_kicks, got_cfg, reps, seed, progress), kwargs, out = calls[0]
    assert (net, target, n_kicks, reps, seed, progress, kwargs) == ("meta_4x256", 12.3, 16, 2, 0, None, {})
    assert got_shipped.manifest == shipped.manifest and kick_env.resolved(got_cfg) == kick_env.resolved(env_cfg)
    assert out.context in (11.5, 12.3) and list(out.candidates) == [11.5, 12.3]
    assert out.distance.shape == (16,) and np.all(np.isfinite(out.distance))
    # The error is the resting point's distance to the target: at least its miss along the line.
    assert np.all(out.final_error >= np.abs(out.distance - 12.3) - 1e-4)
    assert "physics backend " + stage_run["cfg"].env.impl + ", step 2.5 ms" in printed
    each = next(line for line in printed.splitlines() if line.startswith("each kick (m): "))
    np.testing.assert_allclose([float(d) for d in each.split(":")[1].split()], out.distance, atol=0.006)
    with pytest.raises(SystemExit, match="publish a paper run"):
        cli.main(["kick", "--target", "12.3", "--policies", str(heldout_run["root"] / "nothing")])
    with pytest.raises(SystemExit, match="target 19.0 m is outside"):
        cli.main(["kick", "--target", "19", "--policies", str(directory)])


def test_heldout_refuses_a_run_without_its_stages(tmp_path):
    with pytest.raises(SystemExit, match=re.escape(str(tmp_path / "experts" / "experts.json"))):
        cli.main(["evaluate", "--heldout", "--run-dir", str(tmp_path)])
    with pytest.raises(SystemExit, match=re.escape(str(tmp_path / "experts" / "experts.json"))):
        cli.main(["evaluate", "--dev", "--run-dir", str(tmp_path)])
    for both_or_neither in ([], ["--heldout", "--dev"]):
        with pytest.raises(SystemExit, match="needs one of --heldout"):
            cli.main(["evaluate", *both_or_neither, "--run-dir", str(tmp_path)])


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"heldout.targets": (12.3, 13.517)}, "12.3 m lies within 0.005 m of the 0.1 m grid"),
        ({"heldout.targets": (12.345, 18.5)}, "heldout.targets: target 18.5 m is outside"),
        ({"heldout.repetitions": 0}, "heldout.repetitions must be a positive integer"),
    ],
)
def test_bad_heldout_config_names_the_value(overrides, match):
    with pytest.raises(ValueError, match=match):
        config.make_config("tiny", overrides)


def test_the_paper_heldout_set_is_large_and_off_the_grid():
    targets = np.asarray(config.make_config("paper").heldout.targets)
    assert len(targets) >= 50 and len(set(targets.tolist())) == len(targets)
    assert targets.min() >= 7.0 and targets.max() <= 18.0 and np.all(np.abs(targets - np.round(targets, 1)) >= 0.005)
    with pytest.raises(ValueError, match="heldout.targets holds 6 targets; the paper preset needs at least 50"):
        config.make_config("paper", {"heldout.targets": HELDOUT_TARGETS[:6]})
    seeds = [
        v for k, v in _leaves(config.make_config("paper").to_dict()) if "seed" in k and not k.startswith("heldout")
    ]
    assert config.make_config("paper").heldout.seed not in seeds


def _leaves(d, prefix=""):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _leaves(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", v


# -- the nets' input map (`bc.MetaPolicy.obs_norm`) ---------------------------------------------


def test_the_kick_nets_read_phase_and_context_as_they_are(env):
    data = bc.Dataset(obs=np.zeros((4, 2), np.float32), actions=np.zeros((4, 22), np.float32),
                      task=np.zeros(4, np.float32))  # fmt: skip
    assert meta_stage.net_obs_norm(config.make_config("tiny"), env, data) is None
    assert bc.obs_norm_of_record({}) is None and bc.obs_norm_fields(None) == {}
    norm = ((0.5, 0.5), (0.5, 0.5))
    assert bc.obs_norm_of_record(bc.obs_norm_fields(norm)) == norm
    with pytest.raises(ValueError, match=re.escape("unknown config key 'meta.inputs'")):
        config.make_config("tiny", {"meta.inputs": "raw"})


def test_shipped_nets_carry_their_input_map_to_kick(stage_run, tmp_path, monkeypatch):
    """A run whose nets read their inputs through a map (another task's: the dataset's statistics)
    ships the map with each net, and `kick` builds them with it."""
    run_dir = tmp_path / "run"
    shutil.copytree(stage_run["dir"], run_dir)
    table1 = json.loads((run_dir / "meta" / meta_stage.OUTPUT).read_text())
    shift, scale = (0.5, 0.5), (0.5, 0.5)
    table1.update(obs_shift=list(shift), obs_scale=list(scale))
    (run_dir / "meta" / meta_stage.OUTPUT).write_text(json.dumps(table1))
    monkeypatch.setattr(experts_stage, "load_family", lambda c, d: stage_run["family"])
    policies.write(stage_run["cfg"], run_dir, tmp_path / "shipped")
    shipped = policies.load(tmp_path / "shipped", stage_run["cfg"].env)
    assert all(bc.obs_norm_of_record(entry) == (shift, scale) for entry in shipped.manifest["nets"].values())
    built = []

    def meta_grid(env_cfg, depth, width, mesh, task="kick", obs_norm=None):
        built.append(obs_norm)
        raise RuntimeError("built")

    monkeypatch.setattr(meta_programs, "meta_grid", meta_grid)
    with pytest.raises(RuntimeError, match="built"):
        policies.filtered_kicks(shipped, "meta_4x256", 12.0, 2, stage_run["cfg"].env)
    assert built == [(shift, scale)]


def test_heldout_on_a_run_of_another_preset_names_the_preset_to_add(tmp_path):
    """A run whose env this preset shares but whose experts trained other tasks: the message names
    the run's preset (it said only 'not experts.tasks of this config')."""
    cfg = config.make_config("paper", {"task": "cheetah_vel"})
    runio.write_json(tmp_path / "experts" / "experts.json",
                     {"preset": "tiny", "env": config.resolved_env(cfg), "tasks_m": [1.0]})  # fmt: skip
    with pytest.raises(ValueError, match=r"trained the tasks \[1\.0\], not experts\.tasks of this config \(a run of "
                                         r"preset 'tiny': add --preset tiny\)$"):  # fmt: skip
        heldout.inputs(cfg, tmp_path)
    runio.write_json(tmp_path / "experts" / "experts.json",
                     {"preset": "paper", "env": config.resolved_env(cfg), "tasks_m": [1.0]})  # fmt: skip
    with pytest.raises(ValueError, match=r"not experts\.tasks of this config$"):
        heldout.inputs(cfg, tmp_path)
