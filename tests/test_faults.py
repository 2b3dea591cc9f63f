"""Fault injection: what a damaged artifact, a second writer, a Ctrl-C or a bad value does. Each
fault must give one clear line naming what is wrong (or fall back, saying so), never a silently
wrong result."""

import shutil
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from bumps_jax import resumable, runio
from bumps_jax.tasks.kick import policies

# -- checksums ---------------------------------------------------------------------------------


def flip_bytes(path: Path, n: int = 64) -> None:
    """Invert `n` bytes in the middle of `path` (its length unchanged)."""
    data = bytearray(path.read_bytes())
    start = max(0, len(data) // 2 - n // 2)
    for i in range(start, min(len(data), start + n)):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))


def largest_file(directory: Path) -> Path:
    files = [p for p in directory.rglob("*") if p.is_file() and p.name != runio.CHECKSUMS]
    return max(files, key=lambda p: p.stat().st_size)


class Said(list):
    """A `say` that keeps its lines."""

    def __call__(self, line="", **kwargs):
        self.append(str(line))


def counting_loop() -> resumable.ChunkedTraining:
    """A chunked 'training' of a (64,) vector: chunk k adds 1 to it; its state is checkpointed."""
    fresh = {"w": jnp.zeros(64), "n": jnp.array(0)}
    return resumable.ChunkedTraining(
        init=lambda: fresh,
        chunk=lambda s: ({"w": s["w"] + 1.0, "n": s["n"] + 1}, {}),
        abstract=fresh,
        updates=lambda s: int(s["n"]),
        rows=lambda before, m: [{"update": before}],
        line=lambda m, update, eta: f"update {update}",
        fields=("update",),
    )


def test_a_flipped_checkpoint_falls_back_to_an_older_one_saying_which_file(tmp_path):
    said = Said()
    resumable.train_in_chunks(tmp_path, counting_loop(), 3, keep=3, say=said)
    newest = tmp_path / "checkpoints" / "3"
    assert (newest / runio.CHECKSUMS).is_file()
    bad = largest_file(newest)
    flip_bytes(bad)
    said.clear()
    out = resumable.train_in_chunks(tmp_path, counting_loop(), 5, keep=3, say=said)
    corrupt = [line for line in said if "corrupt" in line]
    assert len(corrupt) == 1 and bad.name in corrupt[0] and "checksum mismatch" in corrupt[0]
    assert any("resumed from update 2" in line for line in said)
    np.testing.assert_array_equal(np.asarray(out["state"]["w"]), np.full(64, 5.0))  # as uninterrupted
    assert (tmp_path / "checkpoints" / "3.corrupt").is_dir()


def test_an_intact_checkpoint_that_does_not_restore_is_kept_and_named(tmp_path):
    # Another version's state (here: a vector of 32 where 64 were saved): its bytes are as written,
    # so it is not set aside as corrupt (nor the older ones after it), and training does not restart.
    resumable.train_in_chunks(tmp_path, counting_loop(), 3, keep=3, say=Said())
    other = counting_loop()._replace(abstract={"w": jnp.zeros(32), "n": jnp.array(0)})
    with pytest.raises(ValueError, match=r"checkpoints/3 is intact \(its checksums match\) but does not restore"):
        resumable.train_in_chunks(tmp_path, other, 5, keep=3, say=Said())
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["1", "2", "3"]


def test_a_truncated_checkpoint_names_its_reason_not_a_repr(tmp_path):
    said = Said()
    resumable.train_in_chunks(tmp_path, counting_loop(), 2, keep=3, say=said)
    for p in (tmp_path / "checkpoints" / "2").rglob("*"):  # no checksums: the old version's case
        if p.name == runio.CHECKSUMS:
            p.unlink()
    bad = largest_file(tmp_path / "checkpoints" / "2")
    bad.write_bytes(bad.read_bytes()[:10])
    said.clear()
    out = resumable.train_in_chunks(tmp_path, counting_loop(), 3, keep=3, say=said)
    unreadable = [line for line in said if "unreadable" in line]
    assert len(unreadable) == 1 and "<bound method" not in unreadable[0]
    assert int(out["state"]["n"]) == 3


def test_sealed_directory_and_file_name_the_changed_file(tmp_path):
    folder = tmp_path / "final_params"
    (folder / "d").mkdir(parents=True)
    (folder / "d" / "a").write_bytes(bytes(range(256)))
    runio.write_checksums(folder)
    assert runio.verify_checksums(folder)
    assert runio.file_hash(folder) == runio.file_hash(folder)  # the manifest is not content
    flip_bytes(folder / "d" / "a")
    with pytest.raises(runio.CorruptError, match=r"final_params/d/a: checksum mismatch"):
        runio.verify_checksums(folder)
    data = tmp_path / "dataset.npz"
    np.savez(data, x=np.arange(100))
    runio.write_file_checksum(data)
    assert runio.verify_file_checksum(data)
    flip_bytes(data)
    with pytest.raises(runio.CorruptError, match=r"dataset.npz: checksum mismatch"):
        runio.verify_file_checksum(data)


def test_a_finished_stage_keeps_its_checkpoints_until_the_newest_verifies(tmp_path):
    resumable.train_in_chunks(tmp_path, counting_loop(), 2, keep=3, say=lambda *a, **k: None)
    flip_bytes(largest_file(tmp_path / "checkpoints" / "2"))
    with pytest.raises(runio.CorruptError):
        resumable.keep_newest_checkpoint(tmp_path / "checkpoints")
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["0", "1", "2"]


# -- shipped policies ----------------------------------------------------------------------------


def test_the_committed_policies_carry_their_checksums():
    manifest = runio.read_json(policies.ASSET_DIR / policies.MANIFEST)
    for entry in [*manifest["nets"].values(), manifest["experts"]]:
        assert entry["sha256"] == runio.sha256_of(policies.ASSET_DIR / entry["file"])


@pytest.mark.parametrize("fault", ["truncated", "empty", "swapped"])
def test_a_damaged_shipped_policy_is_named(tmp_path, fault):
    shipped = tmp_path / "policies"
    shutil.copytree(policies.ASSET_DIR, shipped)
    target = shipped / "meta_4x256.msgpack"
    if fault == "truncated":
        target.write_bytes(target.read_bytes()[:1000])
    elif fault == "empty":
        target.write_bytes(b"")
    else:
        other = shipped / "meta_11x128.msgpack"
        a, b = target.read_bytes(), other.read_bytes()
        target.write_bytes(b)
        other.write_bytes(a)
    with pytest.raises(ValueError, match=r"meta_4x256.msgpack: its sha256 is not the one policies.json records"):
        policies.load(shipped)
    if fault == "swapped":  # a manifest from before the checksums: the nets' shapes still tell
        manifest = runio.read_json(shipped / policies.MANIFEST)
        for entry in [*manifest["nets"].values(), manifest["experts"]]:
            entry.pop("sha256")
        runio.write_json(shipped / policies.MANIFEST, manifest)
        with pytest.raises(ValueError, match=r"meta_4x256.msgpack: holds no layer of width 256"):
            policies.load(shipped)


# -- one writer per run directory ----------------------------------------------------------------


@pytest.mark.parametrize(
    "command", [["evaluate", "--heldout"], ["evaluate", "--dev"], ["publish"], ["demo"], ["train-experts"], ["report"]]
)
def test_every_command_that_writes_a_run_directory_takes_its_lock(tmp_path, command):
    from bumps_jax import cli

    with runio.run_lock(tmp_path), pytest.raises(SystemExit) as exit_:
        cli.main([*command, "--run-dir", str(tmp_path)])
    assert "is in use by another process" in str(exit_.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == [".lock"]


@pytest.mark.parametrize("command", [["evaluate", "--heldout"], ["publish"], ["filter"], ["meta-train"]])
def test_a_missing_run_directory_is_refused_and_not_made(tmp_path, command):
    from bumps_jax import cli

    missing = tmp_path / "doesnotexist"
    with pytest.raises(SystemExit) as exit_:
        cli.main([*command, "--run-dir", str(missing)])
    assert str(exit_.value).startswith("error: ") and "\n" not in str(exit_.value)
    assert not missing.exists()


# -- Ctrl-C ----------------------------------------------------------------------------------------


def test_a_search_stopped_by_ctrl_c_resumes_after_its_last_generation(tmp_path, monkeypatch):
    """The prior's CMA-ES searches save their state after every generation: Ctrl-C stops one after
    the generation in flight, and the rerun ends exactly where an uninterrupted search does."""
    import os
    import signal

    from bumps_jax.tasks.kick import cmaes
    from bumps_jax.tasks.kick import keyframes as kick_model

    def cost_fn(params, keys, target, extra):
        return (params[:, 0] - target) ** 2 + params[:, 1] ** 2, {"valid": jnp.ones(keys.shape)}

    from bumps_jax.algo import sharding

    search = cmaes.make_search(cost_fn, 8, 2, 1.0, sharding.device_mesh())
    x0 = np.asarray(kick_model.DEFAULT_PARAMS, np.float32)[None]
    free = np.ones((1, kick_model.N_PARAMS), bool)
    whole = cmaes.run_search(search, x0, [14.0], free, 5, 3, say=lambda m: None)
    state = tmp_path / "search.npz"

    def press_at_gen_2(gen, stats):
        if gen == 1:
            os.kill(os.getpid(), signal.SIGINT)

    said = Said()
    with pytest.raises(resumable.Interrupted):
        cmaes.run_search(search, x0, [14.0], free, 5, 3, say=said, resume_path=state, on_generation=press_at_gen_2)
    assert sum("gen " in line for line in said) == 2 and state.is_file()
    said.clear()
    resumed = []
    again = cmaes.run_search(search, x0, [14.0], free, 5, 3, say=said, resume_path=state,
                             on_resume=lambda done, history: resumed.append((done, len(history))))  # fmt: skip
    assert resumed == [(2, 2)] and "resumed after generation 2" in said[0]
    np.testing.assert_array_equal(again.mean, whole.mean)
    np.testing.assert_array_equal(again.best, whole.best)
    np.testing.assert_array_equal(again.history["best"], whole.history["best"])
    # another search (here: another target) does not resume this one's state
    said.clear()
    cmaes.run_search(search, x0, [15.0], free, 1, 3, say=said, resume_path=state)
    assert "holds another search's state" in said[0]


# -- config checks, staleness, records -------------------------------------------------------------


@pytest.mark.parametrize("command", ["kick-prior", "train-experts"])
def test_a_physics_step_that_does_not_divide_the_control_step_is_named_before_any_write(tmp_path, command):
    from bumps_jax import cli

    with pytest.raises(SystemExit) as exit_:
        cli.main([command, "--run-dir", str(tmp_path / "run"), "--set", "env.physics_dt=0.003"])
    assert str(exit_.value).startswith("error: env.physics_dt 0.003 does not divide env.ctrl_dt 0.02")
    assert not (tmp_path / "run").exists()


def test_a_stage_refused_before_writing_leaves_no_manifest(tmp_path, monkeypatch):
    import types

    from bumps_jax import config
    from bumps_jax.pipeline import runner

    def refuse(cfg, run_dir, say=print):
        raise ValueError("refused")

    fake = types.SimpleNamespace(OUTPUT="out.json", inputs=lambda cfg, run_dir: {}, run=refuse)
    monkeypatch.setattr(runner, "stage_module", lambda name, task="kick": fake)
    with pytest.raises(ValueError, match="refused"):
        runner.run_stage("experts", config.make_config("tiny"), tmp_path)
    assert not (tmp_path / "experts").exists()  # a corrected rerun is a new stage, not a stale one


def test_knobs_that_change_no_result_leave_a_finished_stage_current(tmp_path):
    from bumps_jax import config
    from bumps_jax.pipeline import runner

    def wanted(**overrides):
        return runner.manifest(config.section(config.make_config("tiny", overrides), "experts"), {}, tmp_path)

    stage = tmp_path / "experts"
    runner.write_manifest(stage, wanted())
    (stage / "progress.csv").write_text("")
    assert runner.check_manifest(stage, wanted(**{"experts.keep_checkpoints": 5})) == "same"
    chunk = wanted(**{"experts.updates_per_chunk": 1})
    assert runner.check_manifest(stage, chunk, finished=True) == "same"
    with pytest.raises(runner.StaleRunError, match="experts.updates_per_chunk"):  # a resume keeps its chunks
        runner.check_manifest(stage, chunk, finished=False)
    with pytest.raises(runner.StaleRunError, match="experts.seed"):
        runner.check_manifest(stage, wanted(**{"experts.seed": 9}), finished=True)


def test_records_name_paths_inside_the_run_directory_relative_to_it(tmp_path):
    from bumps_jax.pipeline import runner
    from bumps_jax.pipeline.stages import meta

    record = tmp_path / "elsewhere" / "run" / "experts" / "experts.json"
    record.parent.mkdir(parents=True)
    record.write_text("{}")
    wanted = runner.manifest(
        {}, {"experts": record, "start": policies.ASSET_DIR / policies.MANIFEST}, record.parents[1]
    )
    assert wanted["inputs"]["experts"]["path"] == "experts/experts.json"
    assert wanted["inputs"]["start"]["path"] == "assets/policies/policies.json"
    row, _ = meta.experts_row({"accuracy_mean": 1.0}, record)
    assert row["source"] == "experts/experts.json"


def test_a_phase_clock_adds_up_every_process(tmp_path):
    path = tmp_path / "wall.json"
    runio.write_json(path, {"seconds": 3.5})  # a killed process's seconds up to its last save
    clock = resumable.CarriedClock(path)
    assert 3.5 <= clock.save() < 10.0 and runio.read_json(path)["seconds"] >= 3.5


# -- the command line ------------------------------------------------------------------------------


def test_kick_takes_only_its_own_options(capsys):
    from bumps_jax import cli

    with pytest.raises(SystemExit):
        cli.main(["kick", "--help"])
    text = capsys.readouterr().out
    for option in ("--preset", "--run-dir", "--task", "--force", "--distributed", "--set"):
        assert option not in text
    with pytest.raises(SystemExit) as exit_:
        cli.main(["kick", "--target", "12", "--preset", "paper"])
    assert exit_.value.code == 2 and "unrecognized arguments: --preset paper" in capsys.readouterr().err


def test_help_lists_the_stages_config_keys_and_a_bad_key_names_the_nearest(capsys):
    from bumps_jax import cli

    with pytest.raises(SystemExit):
        cli.main(["train-experts", "--help"])
    assert "experts.updates_per_chunk = 2   (paper: 25)" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exit_:
        cli.main(["train-experts", "--set", "experts.updates_per_chunks=3"])
    assert "did you mean experts.updates_per_chunk" in str(exit_.value)
    with pytest.raises(SystemExit) as exit_:
        cli.main(["train-experts", "--preset", "nope"])
    assert str(exit_.value) == "error: --preset 'nope': train-experts takes 'tiny' or 'paper'"


@pytest.mark.parametrize(
    ("argv", "libraries", "chosen"),
    [
        (["kick", "--target", "12", "--gif", "k.gif"], {"EGL", "OSMesa"}, "egl"),
        (["render"], {"OSMesa"}, "osmesa"),
        (["render"], set(), None),  # none found: left unset, the command says so before its work
        (["kick", "--target", "12"], {"EGL"}, None),  # no rendering: no GL library loaded
        (["train-experts"], {"EGL"}, None),
    ],
)
def test_the_gl_backend_is_chosen_only_for_rendering_commands(monkeypatch, argv, libraries, chosen):
    import ctypes.util
    import os

    from bumps_jax import cli

    monkeypatch.delenv("MUJOCO_GL", raising=False)
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: f"lib{name}.so" if name in libraries else None)
    cli.choose_gl(argv)
    assert os.environ.get("MUJOCO_GL") == chosen
    monkeypatch.setenv("MUJOCO_GL", "glfw")  # the user's choice is never overridden
    cli.choose_gl(argv)
    assert os.environ["MUJOCO_GL"] == "glfw"


def test_many_kicks_show_their_progress_with_an_eta(capsys):
    from bumps_jax.tasks.kick import commands

    assert commands.kicks_progress(16) is None  # the default: one call, no lines
    progress = commands.kicks_progress(1000)
    for done in range(32, 1000, 32):
        progress(done, 1000)
    progress(1000, 1000)
    lines = capsys.readouterr().out.splitlines()
    # a line once a tenth (100 kicks) more is done, calls of 32 kicks apart, and one at the end
    assert [int(line.split()[1].split("/")[0]) for line in lines] == [128, 256, 384, 512, 640, 768, 896, 1000]
    assert "compile included" in lines[0] and all("ETA" in line for line in lines[1:])


def test_many_kicks_are_listed_up_to_a_limit_and_summed_up_whole():
    import types

    shipped = types.SimpleNamespace(manifest=runio.read_json(policies.ASSET_DIR / policies.MANIFEST))
    n = policies.SHOWN_KICKS + 8
    distance = np.linspace(11.0, 13.0, n)
    kicks = policies.Kicks(12.0, np.array([12.0]), np.array([0.1]), distance, np.abs(distance - 12.0), np.ones(n, bool))
    lines = policies.describe(shipped, "meta_4x256", 12.0, kicks)
    listed = next(line for line in lines if line.startswith("each kick (m): "))
    assert len(listed.split(": ")[1].split(" ... ")[0].split()) == policies.SHOWN_KICKS
    assert listed.endswith(f" ... ({n} in all)") and any(f"{n} noisy kicks: resting distance 12.00" in x for x in lines)


def test_kick_blocks_do_not_depend_on_the_number_of_kicks():
    manifest = runio.read_json(policies.ASSET_DIR / policies.MANIFEST)
    pools = {policies.kick_env_config(manifest, None, n).warp_contacts for n in (1, 2, 16, 64)}
    assert len(pools) == 1
