"""Running stages into a run directory without ever mixing configs.

    run_dir/
      prior/     stage.json  kick_prior.json  kick_prior_asset.json  ...
      experts/   stage.json  experts.json  final_params/  checkpoints/  progress.csv
      meta/      stage.json  table1.json  <net>/checkpoints/  dataset.npz
      filter/    stage.json  table2.json  error_vs_target.png  context_map.png
      baseline/  stage.json  baseline.json  baseline_curve.png
      pipeline.json  report.md

Data flows one way: prior -> experts -> meta -> filter (and prior -> baseline). Each stage
module (`bumps_jax.pipeline.stages.<name>`) says which files it reads (`inputs`) and which record marks
it done (`OUTPUT`); `run_stage` checks every input before any work, compares the stage's
manifest (its config section, the env and the inputs' fingerprints) with what is already there,
and then reuses, resumes, recomputes (`force`) or refuses.
"""

from __future__ import annotations

import datetime
import hashlib
import importlib
import json
import time
from pathlib import Path

from bumps_jax import config, resumable, runio
from bumps_jax.tasks import registry as tasks
from bumps_jax.tasks.protocol import STAGE_ORDER

MANIFEST = "stage.json"  # each stage directory's manifest
# The manifest's layout and the config tree it records: raised when either changes so that a run
# directory of an older layout is refused whole rather than compared key by key.
MANIFEST_SCHEMA = 3

# Stage name -> the stages that read its outputs (directly or through another).
ORDER = STAGE_ORDER
DOWNSTREAM = {"prior": ("experts", "meta", "filter", "heldout", "baseline"), "experts": ("meta", "filter", "heldout"),
              "meta": ("filter", "heldout"), "filter": ("heldout",), "heldout": (), "baseline": ()}  # fmt: skip


def stage_module(name: str, task: str):
    """The module that runs stage `name` of `task`: the task's own (`Task.own_stages`, e.g. the
    kick's prior), else the pipeline's (`bumps_jax.pipeline.stages`)."""
    if name not in ORDER:
        raise ValueError(f"unknown stage {name!r}; choose one of {ORDER}")
    return importlib.import_module(tasks.get(task).own_stages.get(name, f"bumps_jax.pipeline.stages.{name}"))


def plan(name: str, cfg, run_dir: Path, force: bool = False) -> tuple[dict, str]:
    """(manifest wanted, status) of one stage, checked before any work: the config's task has the
    stage, every input exists and parses (ValueError naming it), and the stage directory holds
    nothing of another config (StaleRunError; with `force` such a directory is wiped).
    status: "new", "same" (resume), "done" (its record exists) or "forced"."""
    tasks.check_stage(cfg.task, name)
    module = stage_module(name, cfg.task)
    wanted = manifest(config.section(cfg, name), module.inputs(cfg, run_dir), run_dir, task=cfg.task)
    status = check_manifest(run_dir / name, wanted, force, finished=(run_dir / name / module.OUTPUT).exists())
    if status == "same" and (run_dir / name / module.OUTPUT).exists():
        status = "done"
    return wanted, status


def unfinished(run_dir: Path, stages, task: str) -> list[str]:
    """The stages of `stages` (of `task`) whose record `run_dir` lacks (never run, or stopped before the end)."""
    return [name for name in stages if not (Path(run_dir) / name / stage_module(name, task).OUTPUT).exists()]


def run_stage(name: str, cfg, run_dir: Path, force: bool = False, say=print) -> dict:
    """Run (or resume, or reuse) one stage; returns its record. With `force`, a stage whose
    outputs were made otherwise is wiped with every stage after it, and recomputed."""
    run_dir = runio.check_writable(run_dir)
    return execute(name, cfg, run_dir, *plan(name, cfg, run_dir, force), say=say)


def check_current(cfg, run_dir: Path, stages, inputs: bool = True) -> None:
    """StaleRunError unless every one of `stages` that `run_dir` holds was made with `cfg` and the
    inputs there now (its manifest, `check_manifest`): what publishing a run checks first, so that
    no record goes out under a config it was not made with. inputs=False: the configs only, for a
    run whose records were kept without its parameters (the inputs its manifests name)."""
    for name in stages:
        if not (run_dir / name).exists():
            continue
        if inputs:
            plan(name, cfg, run_dir)
            continue
        path = run_dir / name / MANIFEST  # none: `check_manifest` refuses the outputs, naming why
        have = runio.read_json(path, f"the {name} stage's manifest") if path.exists() else {}
        wanted = {**manifest(config.section(cfg, name), {}), "inputs": have.get("inputs", {})}
        check_manifest(run_dir / name, wanted, finished=True)


def execute(name: str, cfg, run_dir: Path, wanted: dict, status: str, say=print) -> dict:
    """One stage after `plan`: reuse its record, or write its manifest and run it. A stage that
    runs first removes the run's report (`publish.remove_report`), which would show the records
    it replaces; `run_pipeline` and the report command write it anew."""
    from bumps_jax.report import publish  # noqa: PLC0415

    module = stage_module(name, cfg.task)
    output = run_dir / name / module.OUTPUT
    runio.sync(f"stage {name} planned")  # every process has read the directory before any removes from it
    if status == "done":
        say(f"== {name}: up to date ({output})")
        changed = changed_source(runio.read_json(run_dir / name / MANIFEST), wanted)
        if changed:
            say(f"   note: {changed} changed since this stage ran (its record stands; --force redoes it)")
        try:
            return runio.read_json(output)
        except ValueError as err:
            raise ValueError(f"{err}. The {name} stage's record is damaged: remove it and rerun to redo the stage "
                             "from what it kept (the stages made from it then need --force)") from None  # fmt: skip
    if name not in tasks.get(cfg.task).own_stages:  # its env steps as the stage reads it, before any work
        from bumps_jax.pipeline import programs  # noqa: PLC0415

        programs.stage_env(cfg.env, cfg.task)
    if status == "forced":
        for later in DOWNSTREAM[name]:
            if (run_dir / later).exists():
                say(f"== {later}: removed (made from the {name} outputs that --force replaces)")
                runio.remove(run_dir / later)
    removed = publish.remove_report(run_dir)
    if removed:
        names = ", ".join(path.name for path in removed)
        say(f"== {names}: removed (made before the records this stage writes; the report command writes it anew)")
    write_manifest(run_dir / name, wanted)
    runio.sync(f"stage {name} starts")  # every process reads this stage's directory as the writer left it
    say(f"== {name}" + (" (resuming)" if status == "same" else ""), flush=True)
    # Ctrl-C only asks the stage to stop (a KeyboardInterrupt raised inside a Warp callback
    # crashed the process): its chunk loops stop at their next chunk, a stage without chunks
    # when it is done, and the call then ends as an interrupted one.
    with resumable.stop_on_interrupt(say, at="this chunk, or at the end of this stage") as stop:
        try:
            record = module.run(cfg, run_dir, say=say)
        except ValueError:
            _forget_empty_stage(run_dir / name)
            raise
        runio.sync(f"stage {name} ends")  # the next stage reads what this one wrote
        if stop.requested:  # the stage ran to its end: its record is written
            raise resumable.Interrupted(f"the {name} stage ran to its end before it could stop ({output}); the stages "
                                        "after it have not run: rerun the same command for them")  # fmt: skip
    return record


def _forget_empty_stage(stage_dir: Path) -> None:
    """Remove the manifest of a stage refused before it wrote anything else: a corrected rerun
    is then a new stage, not a stale one."""
    if all(p.name == MANIFEST for p in stage_dir.iterdir()):
        runio.remove(stage_dir)


def run_pipeline(stages, cfg, run_dir: Path, force: bool = False, say=print) -> dict:
    """Run `stages` in order into `run_dir` (those the config's task has: `tasks.STAGES`), then write
    the report. Writes run_dir/pipeline.json:
    each stage's wall time over every call (`stages_s`; their sum is `wall_s`), the number of
    calls, and this call's own time. Each update touches this call's stages only
    (`runio.update_json`), so commands running other stages side by side (`schedule`) share it.

    Every stage's inputs and manifest are checked up front where they already exist, so a stale
    later stage stops the call before the first stage does any work.
    """
    from bumps_jax.report import publish  # noqa: PLC0415

    run_dir = runio.check_writable(run_dir)
    stages = [name for name in stages if name in tasks.get(cfg.task).stages]
    for name in stages:
        if (run_dir / name).exists() and not force:
            try:
                plan(name, cfg, run_dir)
            except StaleRunError:
                raise
            except ValueError:
                pass  # an input that an earlier stage of this call writes
    timing_path = run_dir / "pipeline.json"
    timing = runio.update_json(timing_path, lambda t: count_killed_call(run_dir, t, stages, say),
                               "the run's wall times, damaged: remove it to count them afresh")  # fmt: skip
    counted = False
    t_call = time.perf_counter()
    for name in stages:
        wanted, status = plan(name, cfg, run_dir, force)
        if status == "done":
            execute(name, cfg, run_dir, wanted, status, say)
            continue
        first, counted = not counted, True  # a report says whether the run was resumed
        started = time.time()

        def opened(t, name=name, new=status in ("new", "forced"), first=first, started=started):
            t.setdefault("stages_s", {})
            if new:  # a stage made anew counts its own time, not its predecessor's
                t["stages_s"].pop(name, None)
            if first:
                t["calls"] = t.get("calls", 0) + 1
            # A SIGKILL skips the `finally` below; this mark lets the next call count the lost time.
            t.setdefault("open", {})[name] = started

        timing = runio.update_json(timing_path, opened)
        t0 = time.perf_counter()
        try:
            execute(name, cfg, run_dir, wanted, status, say)
        finally:  # also when interrupted: a resumed stage adds up its parts
            seconds = time.perf_counter() - t0

            def closed(t, name=name, seconds=seconds):
                t.get("open", {}).pop(name, None)
                if not t.get("open"):
                    t.pop("open", None)
                t["stages_s"][name] = t["stages_s"].get(name, 0.0) + seconds
                t["call_wall_s"] = time.perf_counter() - t_call
                t.update(runio.provenance(cfg.preset, sum(t["stages_s"].values()), config.resolved_env(cfg)))
                t["overrides"] = config.overrides_of(cfg)

            timing = runio.update_json(timing_path, closed)
    path = publish.write_report(run_dir)
    say(path.read_text())
    say(f"wrote {path}")
    return timing


def count_killed_call(run_dir: Path, timing: dict, stages=None, say=print) -> None:
    """Add a call that was killed mid-stage (its `open` mark is left) to `timing`, in place; only
    the marks of `stages` (default: all), since another command may be running the others now.

    Its time is counted up to the stage's last write under run_dir (a checkpoint, a progress
    row): what came after it was lost and is redone by this call."""
    marks = timing.get("open") or {}
    if "stage" in marks:  # an older version's single mark
        marks = {marks["stage"]: marks["started"]}
    timing.setdefault("stages_s", {})
    for stage in [s for s in marks if stages is None or s in stages]:
        started = marks.pop(stage)
        stage_dir = run_dir / stage
        writes = [p.stat().st_mtime for p in stage_dir.rglob("*") if p.is_file()] if stage_dir.exists() else []
        lost = max([0.0, *(t - started for t in writes)])
        timing["stages_s"][stage] = timing["stages_s"].get(stage, 0.0) + lost
        timing["killed_calls"] = timing.get("killed_calls", 0) + 1
        say(f"== a previous call was killed during {stage}: counting its {lost:.0f} s up to its last write")
    if marks:
        timing["open"] = marks
    else:
        timing.pop("open", None)


def record_launch(run_dir: Path, processes: int, phases, wall_s: float, finished: bool) -> dict:
    """Add one launched call (`launch.run`: its processes, phases and wall time from start to end,
    process start-up and compiles included) to run_dir/pipeline.json's `launches`, and write the
    report again so that it shows it. Stages run side by side add up to more than the wall time."""
    from bumps_jax.report import publish  # noqa: PLC0415

    entry = {
        "processes": int(processes),
        "phases": [[{"stages": list(stages), "processes": int(k)} for stages, k in phase] for phase in phases],
        "wall_s": float(wall_s),
        "finished": bool(finished),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    record = runio.update_json(Path(run_dir) / "pipeline.json", lambda t: t.setdefault("launches", []).append(entry))
    if record.get("stages_s"):
        publish.write_report(run_dir)
    return record


def schedule(stages, processes: int) -> list[list[tuple[tuple[str, ...], int]]]:
    """How a pipeline's `stages` run as `processes` processes (`launch`): phases one after
    another, each a list of branches (stages, processes) run side by side.

    The baseline reads only what the experts read (the prior). With several processes, once the
    stages before the experts are done, it trains on a quarter of the processes (at least one)
    beside the experts, the meta-policies, filtering and held-out evaluation on the others: at the
    paper's size neither batch fills its GPUs, so two jobs side by side beat one after the other.
    Otherwise every stage runs on every process, one after another."""
    stages = tuple(stages)
    first = STAGE_ORDER.index("experts")
    trunk = tuple(s for s in stages if STAGE_ORDER.index(s) < first)
    rest = tuple(s for s in stages if s not in trunk and s != "baseline")
    if processes < 2 or "baseline" not in stages or not rest:
        return [[(stages, processes)]]
    side = max(processes // 4, 1)
    return ([[(trunk, processes)]] if trunk else []) + [[(rest, processes - side), (("baseline",), side)]]


# -- the stage manifest ------------------------------------------------------------------------


class StaleRunError(ValueError):
    """A run directory holds outputs of another config or other inputs than this call's."""


def manifest(
    section: dict, inputs: dict[str, str | Path], run_dir: Path | None = None, task: str | None = None
) -> dict:
    """What a stage's outputs depend on: its config (`config.section`) and its input files'
    fingerprints (name -> path), under the manifest's schema (`MANIFEST_SCHEMA`). A path is recorded
    relative to `run_dir` where it lies inside it (`runio.recorded_path`): a record never says where
    the run directory happened to be. With `task`, also the task's code as it was (`task_source`):
    noted where it has changed since (`changed_source`), never compared by `check_manifest`."""
    wanted = {
        "schema": MANIFEST_SCHEMA,
        "config": section,
        "inputs": {
            name: {"path": runio.recorded_path(path, run_dir), "sha256": runio.file_hash(path)}
            for name, path in sorted(inputs.items())
        },
    }
    if task is not None:
        wanted["task_source"] = task_source(task)
    return wanted


def task_source(task: str) -> dict:
    """The task's own code: its folder ("bumps_jax/tasks/<task>/") and a sha256 of its .py files'
    relative paths and contents, in the order of their paths."""
    shown, folder = tasks.code_folder(task)
    h = hashlib.sha256()
    for rel, path in sorted((p.relative_to(folder).as_posix(), p) for p in folder.rglob("*.py")):
        data = path.read_bytes()
        h.update(f"{rel}\0{len(data)}\0".encode())
        h.update(data)
    return {"path": shown, "sha256": h.hexdigest()[:16]}


def changed_source(have: dict, wanted: dict) -> str | None:
    """The task folder whose code differs from when a stage ran (its manifest `have`'s
    `task_source` against `wanted`'s), None where it is the same or `have` records none (an older
    version's manifest)."""
    have, now = have.get("task_source"), wanted.get("task_source")
    if not isinstance(have, dict) or now is None or have.get("sha256") == now["sha256"]:
        return None
    return now["path"]


# Config keys that change no result: how many checkpoints are kept, always; the chunk sizes (updates
# or epochs between checkpoints) once the stage has finished (a resumed run's checkpoints lie on its
# own chunks' bounds, so an unfinished stage keeps its chunk size).
NO_RESULT_KEYS = (".keep_checkpoints",)
NO_RESULT_ONCE_FINISHED = (".updates_per_chunk", ".train.chunk")


def _changes_no_result(key: str, finished: bool) -> bool:
    return key.endswith(NO_RESULT_KEYS) or (finished and key.endswith(NO_RESULT_ONCE_FINISHED))


def check_manifest(stage_dir: Path, wanted: dict, force: bool = False, finished: bool = False) -> str:
    """Compare a stage directory's manifest with `wanted` before the stage runs.

    Returns "new" (nothing there yet), "same" (its outputs belong to this config and inputs: reuse
    or resume them) or "forced" (they differ, or the task's code changed since the stage ran
    (`changed_source`), and `force` wiped it). Otherwise raises
    StaleRunError naming the differing keys and the two ways on. Warp's buffer sizes
    (`env.warp_contacts`, `env.warp_constraints_per_world`) are not compared, nor keys that change
    no result (`NO_RESULT_KEYS`; `NO_RESULT_ONCE_FINISHED` where the stage has `finished`), nor
    an older manifest's sections since removed at their value that did nothing (`config.without_removed`). A
    manifest without `MANIFEST_SCHEMA` (an older version's) is refused in one line, whatever it holds.
    """
    from bumps_jax import records as env_records  # noqa: PLC0415

    path = stage_dir / MANIFEST
    if not path.exists():
        if stage_dir.exists() and any(p.name != MANIFEST for p in stage_dir.iterdir()):
            diff = ["(outputs without a manifest: made by an older version or another program)"]
        else:
            return "new"
    else:
        try:
            have, made = json.loads(path.read_text()), None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            have, made = {}, "is damaged (not JSON)"
        schema = have.get("schema") if isinstance(have, dict) else None
        if schema != MANIFEST_SCHEMA:
            if force:
                runio.remove(stage_dir)
                return "forced"
            if made is None:
                made = "has no schema" if schema is None else f"has schema {schema!r}"
                made += f", this version writes schema {MANIFEST_SCHEMA} (a run of another version)"
            raise StaleRunError(
                f"{path} {made}: use a new --run-dir, or --force to recompute this stage and every stage after it"
            )
        diff = env_records.differing_keys(
            {"config": config.without_removed(have.get("config", {})), "inputs": _hashes(have.get("inputs", {}))},
            {"config": wanted["config"], "inputs": _hashes(wanted["inputs"])},
        )
        diff = [key for key in diff if not _capacity(key) and not _changes_no_result(key, finished)]
        if not diff and not (force and changed_source(have, wanted)):
            return "same"
    if force:
        runio.remove(stage_dir)
        return "forced"
    shown = ", ".join(d.removeprefix("config.") for d in diff[:6]) + (" ..." if len(diff) > 6 else "")
    raise StaleRunError(
        f"{stage_dir} holds outputs of another config or other inputs ({shown}): "
        "use a new --run-dir, or --force to recompute this stage and every stage after it"
    )


def write_manifest(stage_dir: Path, wanted: dict) -> Path:
    return runio.write_json(stage_dir / MANIFEST, wanted)


def _capacity(key: str) -> bool:
    """Is dotted `key` one of Warp's buffer sizes (`env_records.CAPACITY_KEYS`)? They change no
    physics, so a run resumes under another size (a smaller GPU, a larger batch); too small a
    buffer is refused before any work, or its episodes are marked invalid, never silently wrong."""
    from bumps_jax.records import CAPACITY_KEYS  # noqa: PLC0415

    return any(key == f"config.env.{k}" for k in CAPACITY_KEYS)


def _hashes(inputs: dict) -> dict:
    return {name: entry.get("sha256") for name, entry in inputs.items()}
