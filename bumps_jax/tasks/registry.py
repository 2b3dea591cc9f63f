"""The contextual tasks the pipeline runs (`task` in the config), by name.

Each entry names a task's `task.py`, which builds its `protocol.Task` as `TASK`; a `commands.py`
beside it, where there is one, holds the task's own commands (`COMMANDS`). Adding a task is its
folder and one line here (`docs/your_task.md`).
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
from pathlib import Path, PurePath

from bumps_jax.tasks.protocol import Task

_TASKS = {
    "kick": "bumps_jax.tasks.kick.task",  # the paper's: the NAO kicks a ball to a distance (m)
    "cheetah_vel": "bumps_jax.tasks.cheetah_vel.task",  # HalfCheetah-Vel: run at a velocity (m/s)
    "point_goal": "bumps_jax.tasks.point_goal.task",  # a point mass reaches a goal (x, y) (m)
    "ant_goal": "bumps_jax.tasks.ant_goal.task",  # Ant-Goal: the ant walks to a goal (x, y) (m)
}
TASKS = tuple(_TASKS)
DEFAULT = "kick"  # the task a command runs without --task


def check_task(name: str) -> str:
    """`name`, or ValueError naming the tasks there are."""
    if name not in _TASKS:
        raise ValueError(f"unknown task {name!r}; choose one of {TASKS}")
    return name


@functools.cache
def get(name: str) -> Task:
    """The task called `name` (its folder is imported on first use)."""
    return importlib.import_module(_TASKS[check_task(name)]).TASK


def own_commands(task: str) -> dict:
    """`task`'s own commands: name -> `protocol.Command`."""
    return {name: spec for name, (owner, spec) in commands().items() if owner == task}


@functools.cache
def commands() -> dict:
    """Every task's own commands: name -> (task, `protocol.Command`), from each folder's light
    `commands.py` (no task module is imported: MuJoCo is not loaded)."""
    import importlib.util  # noqa: PLC0415

    out = {}
    for name, module in _TASKS.items():
        path = module.rsplit(".", 1)[0] + ".commands"
        if importlib.util.find_spec(path) is None:
            continue
        for command, spec in importlib.import_module(path).COMMANDS.items():
            if command in out:
                raise ValueError(f"tasks {out[command][0]!r} and {name!r} both define a {command!r} command")
            out[command] = (name, spec)
    return out


def folder(name: str) -> PurePath:
    """Task `name`'s folder under runs/ and results/: none for the default task (its records are
    results/*.json), its name for another (results/<task>/)."""
    return PurePath() if check_task(name) == DEFAULT else PurePath(name)


def code_folder(name: str) -> tuple[str, Path]:
    """Task `name`'s own code: its folder as the package names it ("bumps_jax/tasks/<name>/") and
    where that folder lies."""
    package = _TASKS[check_task(name)].rpartition(".")[0]
    return package.replace(".", "/") + "/", Path(importlib.util.find_spec(package).submodule_search_locations[0])


def check_record_task(found, name: str, what: str) -> None:
    """ValueError naming `what` unless its records name task `name` (`found`: the task they name)."""
    if found != name:
        raise ValueError(f"{what} holds no {name} run (its records name {found!r})")


def make_env(name: str, env_cfg, overrides: dict | None = None):
    """The env of task `name` built from its env config (and dotted `overrides`; `Task.make_env`)."""
    return get(name).make_env(env_cfg, overrides)


def resolved(name: str, env_cfg) -> dict:
    """Task `name`'s env config as plain data, as records carry it."""
    return get(name).resolved_env(env_cfg)


def check_stage(name: str, stage: str) -> str:
    """`stage`, or ValueError if task `name` has no such stage."""
    stages = get(name).stages
    if stage not in stages:
        raise ValueError(f"the {name} task has no {stage} stage; its stages are {stages}")
    return stage
