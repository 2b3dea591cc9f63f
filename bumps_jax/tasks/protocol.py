"""What a contextual task declares to run BUMPS: the one interface between a task and the pipeline.

A task is one folder under `bumps_jax/tasks/` that builds a `Task` and one line in `registry.py`.
The pipeline and the algorithm ask a `Task` for everything task-specific; they never import a
task's folder or compare a task's name. `docs/your_task.md` is the recipe.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:  # this module stays light: the command line reads tasks' commands before MuJoCo loads
    import ml_collections
    import numpy as np

    from bumps_jax.envs.base import ContextualEnv

# The pipeline's stages in their order; a task runs those it lists in `Task.stages`.
STAGE_ORDER = ("prior", "experts", "meta", "filter", "heldout", "baseline")


class ExpertStart(Protocol):
    """How a task's experts start before PPO refines them (the kick: its keyframe kicks, cloned).
    A task without one starts every expert from a fresh policy."""

    size: int  # numbers describing one expert's start (the kick: a keyframe kick's 14 parameters)

    def inputs(self, cfg, run_dir: Path) -> dict[str, Path]:
        """The files the experts stage reads for the starts, each checked to exist and parse."""

    def starts(self, cfg, run_dir: Path, stage_dir: Path, say=print) -> np.ndarray:
        """The experts' starts (E, size), made on the host before training; may keep files
        under `stage_dir` (what it made them from, so that a rerun starts from the same)."""

    def make_init(self, cfg, env: ContextualEnv, trainer) -> Callable:
        """A pure fn (rng, target, start (size,)) -> (ppo.TrainState, losses (steps,))."""

    def describe(self, cfg, run_dir: Path, stage_dir: Path, env: ContextualEnv, record: dict) -> dict:
        """Entries the experts' record adds about the starts (their own evaluation, env steps)."""

    def scratch(self) -> tuple[str, ...]:
        """Folders under the experts stage's directory removed once its record is written."""

    def baseline_start(self, cfg, env: ContextualEnv, trainer, run_dir: Path, say=print) -> tuple:
        """The multi-task baseline's starting policy params and its losses (None: no cloning)."""


@dataclasses.dataclass(frozen=True)
class Report:
    """How a task's records read as tables: markdown from a stage's record or rows."""

    experts: Callable[[dict], str]  # experts.json -> experts.md
    table1: Callable[[dict, str], str]  # (Table 1 rows, unit) -> table1.md
    table2: Callable[[dict, str], str]  # (Table 2 rows, unit) -> table2.md
    # Plot axes: (the context, an error, what an episode achieved), each with its unit.
    axes: tuple[str, str, str]
    paper_rows: bool = False  # its records sit beside the paper's own numbers (the paper's task)
    # The experts' record's key holding their starts scored as the experts are (a Table 1 row
    # before PPO); None: no such row.
    start_row: str | None = None
    # Regenerates the repository's blocks that set its published records beside others' (root ->
    # the files written); None: none.
    published_blocks: Callable[[Path], list[Path]] | None = None
    # Ships a finished run's meta-policies for use without the run: (cfg, run_dir, dest) -> the
    # files written (the kick's `policies.write`); None: nothing is shipped.
    ship_policies: Callable | None = None


def _never(args) -> bool:
    return False


@dataclasses.dataclass(frozen=True)
class Command:
    """A command of a task's own beside every task's (report, publish, evaluate): `COMMANDS` of its
    folder's `commands.py`, which imports nothing heavy (the command line reads it before MuJoCo
    loads, to pick a GL backend)."""

    help: str
    run: Callable  # (cfg, run_dir, parsed arguments) -> None
    add_arguments: Callable | None = None  # (argparse parser) -> None: its own options
    # True: only its own options (no --preset, --run-dir, --task, --set): it runs under its own config.
    own_options_only: bool = False
    renders: Callable[[list], bool] = _never  # the arguments after its name -> whether this call renders
    needs_run: bool = False  # it reads a finished run (refused at once where none is) and writes into it
    writes_run: Callable | None = None  # (parsed arguments) -> whether it writes into the run (None: needs_run)


def plain_report(axes: tuple[str, str, str], **extra) -> Report:
    """The `Report` of a task without the paper's rows: the generic tables
    (`report.tables.task_*_markdown`) with its plot `axes`; `extra`: its other fields."""
    from bumps_jax.report import tables  # noqa: PLC0415

    return Report(experts=tables.task_experts_markdown, table1=tables.task_table1_markdown,
                  table2=tables.task_table2_markdown, axes=axes, **extra)  # fmt: skip


@dataclasses.dataclass(frozen=True)
class Task:
    """A contextual task as the pipeline sees it.

    The env is a brax-style `ContextualEnv` whose `reset(rng, context)` takes the context and whose
    `error_against(metrics, contexts)` scores a finished episode against any other context.
    """

    name: str
    # Built as env_class(env_config, overrides); its static `default_config()`, `resolved(env_config)`
    # (the config as records carry it) and `noise_free(env_config)` (overrides that switch the
    # env's noise off) describe its config.
    env_class: type[ContextualEnv]
    stages: tuple[str, ...]  # the stages it runs, a subset of STAGE_ORDER in that order
    # Its config (its folder's `config` module): `sections()`, its tree but `preset` and `task`
    # (`env` and a section per stage, `schema.sections`, at the `paper` preset's values, plus what
    # its plug-ins read); `PRESETS`, preset name -> dotted overrides of them ("tiny": CPU size);
    # `validate(cfg)`, its own checks of a whole config, after the stages'; optional `DERIVED`,
    # (key, function of the tree) pairs recomputed after the preset and --set (`config.derive`)
    # and `TRAINING_SEEDS`, keys a pipeline seed sets besides the stages'.
    config: Any
    report: Report
    expert_start: ExpertStart | None = None  # None: experts start from a fresh policy
    # The meta-policies' inputs normalised by the dataset's statistics (False: the observation as
    # it is, when it is in [0, 1] already).
    normalise_meta_inputs: bool = True
    own_stages: Mapping[str, str] = dataclasses.field(default_factory=dict)  # stage -> module (the kick's prior)

    def __post_init__(self):
        from bumps_jax.envs import base  # noqa: PLC0415 (the env class has loaded it already)

        unknown = [s for s in self.stages if s not in STAGE_ORDER]
        if unknown or list(self.stages) != [s for s in STAGE_ORDER if s in self.stages]:
            raise ValueError(f"task {self.name!r}: stages {self.stages} must be in the order {STAGE_ORDER}")
        gaps = base.interface_gaps(self.env_class)
        if gaps:
            raise ValueError(f"task {self.name!r}: its env class {self.env_class.__name__} defines no "
                             f"{', '.join(gaps)} (docs/your_task.md, section 1)")  # fmt: skip
        missing = [n for n in ("sections", "PRESETS", "validate") if not hasattr(self.config, n)]
        if missing:
            raise ValueError(f"task {self.name!r}: its config {getattr(self.config, '__name__', self.config)!r} "
                             f"defines no {', '.join(missing)} (docs/your_task.md, section 2)")  # fmt: skip

    def make_env(self, env_cfg, overrides: dict | None = None) -> ContextualEnv:
        """The task's env from its env config and dotted `overrides`; ValueError naming the first
        key where the env's own config differs from the one it was given (an env that builds its
        config anew ignores every `--set env.*`)."""
        from bumps_jax.envs.base import locked_config  # noqa: PLC0415
        from bumps_jax.records import differing_keys, lookup  # noqa: PLC0415

        env = self.env_class(env_cfg, overrides)
        if env_cfg is not None:
            given, kept = self.resolved_env(locked_config(env_cfg, overrides)), self.resolved_env(env.config)
            differ = differing_keys(given, kept)
            if differ:
                raise ValueError(
                    f"the {self.name} env does not keep the config it is given: env.{differ[0]} is "
                    f"{lookup(given, differ[0])!r} there, {lookup(kept, differ[0])!r} in the env (its __init__ "
                    "must start from its `config` argument: docs/your_task.md)"
                )
        return env

    def sections(self) -> ml_collections.ConfigDict:
        """Its config tree but `preset` and `task`, at the `paper` preset's values."""
        return self.config.sections()

    @property
    def presets(self) -> Mapping[str, dict]:
        """Preset name -> dotted overrides of `sections()`."""
        return self.config.PRESETS

    def validate(self, cfg: ml_collections.ConfigDict) -> None:
        """Its own checks of a whole config (ValueError naming the first bad value)."""
        self.config.validate(cfg)

    def env_config(self) -> ml_collections.ConfigDict:
        """The env section's defaults."""
        return self.env_class.default_config()

    def resolved_env(self, env_cfg) -> dict:
        """An env config as records carry it (its defaults resolved)."""
        return self.env_class.resolved(env_cfg)

    def noise_free(self, env_cfg) -> dict:
        """Overrides of an env config that switch the env's noise off."""
        return self.env_class.noise_free(env_cfg)

    @property
    def unit(self) -> str:
        return self.env_class.UNIT
