"""The task switch of the config: the kick's stage sections are pinned (a kick run made before the
switch resumes), another task's sections are its own, and bad tasks fail at once."""

import hashlib
import json

import pytest

from bumps_jax import config
from bumps_jax.pipeline import runner as pipeline
from bumps_jax.tasks import registry as tasks

# sha256 of json.dumps(config.section(cfg, stage), sort_keys=True) for the kick: what a stage's
# manifest records of the config. A change here makes every kick run made before it refuse to resume
# (`pipeline.check_manifest`); a change of the tree's layout comes with a new
# `pipeline.MANIFEST_SCHEMA`. Re-pinned when the losing arms' knobs left the tree (schema 2), and
# when every section came to name its task (the kick's values unchanged: the pins without it held).
# experts: the old pins' sections less the deleted losing-arm knobs (tune.scheme ... bc.common_start_strength).
# Keys that join later at a value that changes nothing leave the pins as they are (`config.ADDED_KEYS`).
# meta: re-pinned with schema 3, when closed-loop cloning's knobs (meta.dataset.action_noise,
# clip_labels, meta.dagger) joined the tree at values that change nothing (the kick's pins held otherwise).
# Sections deleted since (`config.REMOVED_SECTIONS`) are put back as the pinned records held them.
KICK_SECTIONS = {
    "tiny": {
        "prior": "c77d5ee26ce79ab481bb9e662a761800766d5204f5cb12fa5c4abe3858fe232d",
        "experts": "f0296a2c6baa1e33c32353ff41740a126f388b5e6930fd8e61951cb368ad692f",
        "meta": "acb20d3d70bae0f2574b25af91d2a0e4ef17e3ada1d2ef8f8bf785ec24072c4e",
        "filter": "25192c3f5983701f519587d2751b13a476b2d74c42985a855c0b5b6af8b77757",
        "heldout": "8bc6c1a9635b8e095e776cb3f006cb4378154fa4e755b89594bbe5768cd7ad0d",
        "baseline": "6a979f969de01a641d4650e63fdd1f326f0abd38a46ce1abfff45ce08793f69b",
    },
    "paper": {
        "prior": "60e55d10a9447f32ad888a955a4228849515451ee277be74d5ef7aef6bed3d2d",
        "experts": "09c1bb73a36a203a230cae681fc237b2412b1651be073a6f9131ecc7c743d3d6",
        "meta": "23715b7f08d2ffa70ae7426856b968d4caaef23cc59c7c3d2e4fdc5799ff9e44",
        "filter": "28c68bd2e8a7fcbf5c7ee90aaf6dd5164a9097f322b524f9bfbfa020d98004c8",
        "heldout": "be6b478575aee78b6124528e9ff0987742791f2d5f312e8a448e5bb78a1b1e53",
        "baseline": "fe3b2493c8c10f2803dede6d928187700b942007d20d00b55ad870a67b29a358",
    },
}


# What the pinned records held of each section since deleted: DAgger's, at 0 rounds (plain cloning).
PINNED_REMOVED = {"meta": {"dagger": {"rounds": 0, "repetitions": 4, "epochs": 100}}}


def digest(section: dict) -> str:
    return hashlib.sha256(json.dumps(section, sort_keys=True).encode()).hexdigest()


def pinned(cfg, stage: str) -> dict:
    """`config.section` as the pinned records hold it: with the sections deleted since, put back."""
    section = config.section(cfg, stage)
    section[stage].update(PINNED_REMOVED.get(stage, {}))
    return section


@pytest.mark.parametrize("preset", sorted(KICK_SECTIONS))
def test_the_kicks_stage_sections_are_unchanged(preset):
    cfg = config.make_config(preset)
    assert cfg.task == "kick"
    sections = {s: digest(pinned(cfg, s)) for s in KICK_SECTIONS[preset]}
    assert sections == KICK_SECTIONS[preset]


def test_a_stage_made_before_a_section_was_deleted_still_matches(tmp_path):
    """A meta stage whose manifest holds DAgger at 0 rounds (plain cloning) resumes; one that ran
    DAgger rounds is another config's, named."""
    cfg = config.make_config("tiny")
    wanted = pipeline.manifest(config.section(cfg, "meta"), {})
    pipeline.write_manifest(tmp_path, pipeline.manifest(pinned(cfg, "meta"), {}))
    assert pipeline.check_manifest(tmp_path, wanted) == "same"
    older = pinned(cfg, "meta")
    older["meta"]["dagger"]["rounds"] = 2
    pipeline.write_manifest(tmp_path, pipeline.manifest(older, {}))
    with pytest.raises(pipeline.StaleRunError, match=r"other inputs \(meta\.dagger\)"):
        pipeline.check_manifest(tmp_path, wanted)


def test_a_tasks_tree_is_its_own():
    cfg = config.make_config("tiny", {"task": "cheetah_vel"})
    assert cfg.task == "cheetah_vel" and "prior" not in cfg and "cheetah_vel" not in cfg
    assert tuple(cfg.experts.tasks) == (0.5, 2.0) and cfg.env.episode_steps == 10
    section = config.section(cfg, "experts")
    assert section["task"] == "cheetah_vel" and section["env"]["physics_dt"] == pytest.approx(0.01)
    assert section["experts"] == config.without_added(json.loads(json.dumps(cfg.experts.to_dict(), default=list)))
    # A key that joined later is left out at its value that changes nothing (old runs resume), kept otherwise.
    assert "potential_shaping" not in section["experts"]["ppo"]
    shaped = config.section(
        config.make_config("tiny", {"task": "cheetah_vel", "experts.ppo.potential_shaping": 2.0}), "experts"
    )
    assert shaped["experts"]["ppo"]["potential_shaping"] == 2.0
    # The default task is the kick's, with its own sections.
    kick = config.make_config("tiny")
    assert config.section(kick, "experts") == config.section(config.make_config("tiny", {"task": "kick"}), "experts")
    assert "prior" in kick and "tune" in kick.experts and "tune" not in cfg.experts
    paper = config.make_config("paper", {"task": "cheetah_vel"})
    assert paper.env.warp_contacts >= 16 * len(paper.experts.tasks) * paper.experts.ppo.num_envs
    assert not set(paper.experts.tasks) & set(paper.filter.tasks)  # the test velocities are held out


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"task": "walker"}, "unknown task 'walker'; choose one of"),
        ({"task": "cheetah_vel", "experts.tasks": (3.5,)}, "experts.tasks: target 3.5 m/s"),
        ({"task": "cheetah_vel", "env.impl": "torch"}, "env.impl must be one of"),
        (
            {"task": "cheetah_vel", "baseline.eval_tasks": (3.5,)},
            "baseline.eval_tasks: target 3.5 m/s",
        ),
        (
            {"task": "cheetah_vel", "baseline.ppo.sample_task_range": (2.0, 0.5)},
            "baseline.ppo.sample_task_range must be",
        ),
        (
            {
                "task": "cheetah_vel",
                "experts.ppo.num_envs": 64,
                "experts.ppo.total_env_steps": 1280,
            },
            "env.warp_contacts 256 holds 16 episodes",
        ),
    ],
)
def test_bad_task_configs_fail_at_once(overrides, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(")):
        config.make_config("tiny", overrides)


def test_a_stage_the_task_lacks_is_refused(tmp_path):
    cfg = config.make_config("tiny", {"task": "cheetah_vel"})
    with pytest.raises(ValueError, match="the cheetah_vel task has no prior stage"):
        pipeline.plan("prior", cfg, tmp_path)
    assert tasks.get("kick").stages == pipeline.ORDER


def test_the_command_line_sets_the_selected_tasks_own_sections():
    from bumps_jax import cli

    # A stage's own keys may drop their section; the top sections are the task's.
    assert cli.parse_overrides([["ppo.learning_rate=1e-5"]], "experts", "cheetah_vel") == {
        "experts.ppo.learning_rate": 1e-5
    }
    assert cli.parse_overrides([["tune.generations=2"]], "experts") == {"experts.tune.generations": 2}
    with pytest.raises(ValueError, match="unknown config key 'experts.tune.generations'"):
        config.make_config("tiny", {"task": "cheetah_vel", **cli.parse_overrides([["tune.generations=2"]], "experts")})
    assert str(cli.default_run_dir("reproduce", "paper", "cheetah_vel")) == "runs/cheetah_vel/paper"
    assert str(cli.default_run_dir("demo", "tiny")) == "runs/demo"
    args = cli.build_parser().parse_args(["reproduce", "--task", "cheetah_vel", "--set", "experts.seed=3"])
    assert (args.task, args.preset) == ("cheetah_vel", "paper")


def test_an_env_class_lacking_what_the_pipeline_calls_is_named_when_its_task_is_built():
    # A task whose env left out error_against trained its experts' whole budget, then stopped in a
    # bare NotImplementedError; without ACHIEVED it asked for the kick's "distance".
    from bumps_jax.envs import base
    from bumps_jax.tasks.point_goal import config as point_config
    from bumps_jax.tasks.protocol import Task, plain_report

    bare = type("Bare", (base.ContextualEnv,), {"reset": None, "step": None, "observation_size": 1})
    with pytest.raises(ValueError) as err:
        Task(name="bare", env_class=bare, stages=("experts",), config=point_config, report=plain_report(("", "", "")))
    message = str(err.value)
    for gap in ("error_against", "with_context", "default_config()", "n_steps_of()", "ACHIEVED"):
        assert gap in message
    assert message.startswith("task 'bare': its env class Bare defines no ")


def test_a_config_module_lacking_what_the_config_tree_reads_is_named_when_its_task_is_built():
    # A task whose config module left out `validate` stopped in an AttributeError once a command
    # built its config.
    import types

    from bumps_jax.tasks.point_goal import config as point_config
    from bumps_jax.tasks.point_goal import env as point_env
    from bumps_jax.tasks.protocol import Task, plain_report

    partial = types.ModuleType("my_task.config")
    partial.sections, partial.PRESETS = point_config.sections, point_config.PRESETS
    with pytest.raises(
        ValueError,
        match=r"^task 'mine': its config 'my_task.config' defines no validate \(docs/your_task.md, section 2\)$",
    ):
        Task(name="mine", env_class=point_env.PointGoalEnv, stages=("experts",), config=partial,
             report=plain_report(("", "", "")))  # fmt: skip


def _point_env(**changes):
    """PointGoal's env at the tiny preset, as a subclass with `changes` (attributes) over it."""
    from bumps_jax.tasks.point_goal import env as point_env

    cls = type("Changed", (point_env.PointGoalEnv,), changes)
    return cls(config.make_config("tiny", {"task": "point_goal"}).env)


def _without(metric):
    from bumps_jax.tasks.point_goal import env as point_env

    def step(self, state, action):
        nxt = point_env.PointGoalEnv.step(self, state, action)
        return nxt.replace(metrics={k: v for k, v in nxt.metrics.items() if k != metric})

    return step


def _reward_of_shape_1(self, state, action):
    from bumps_jax.tasks.point_goal import env as point_env

    nxt = point_env.PointGoalEnv.step(self, state, action)
    return nxt.replace(reward=nxt.reward[None])


@pytest.mark.parametrize(
    "changes, message",
    [
        ({}, None),
        ({"step": _without("final_error")}, r"step's metrics hold no 'final_error'"),
        ({"step": _without("valid")}, r"step's metrics hold no 'valid'"),
        ({"ACHIEVED": "distance"}, r"step's metrics hold no 'distance'"),
        ({"step": _reward_of_shape_1}, r"step returns state.reward as float32\[1\], reset as float32\[\]"),
        ({"context_observation_size": property(lambda self: self.observation_size)},
         r"with_context's observation has shape \(6,\), its size says \(4,\)"),
        ({"observation_size": property(lambda self: 3)}, r"reset's observation has shape \(4,\), its size says \(3,\)"),
    ],
)  # fmt: skip
def test_an_env_that_steps_otherwise_than_the_pipeline_reads_is_refused_before_any_work(changes, message):
    # Each of these trained the experts' whole budget or two stages before failing deep in JAX or flax.
    from bumps_jax.envs import base

    env = _point_env(**changes)
    if message is None:
        base.check_episode(env)
        return
    with pytest.raises(ValueError, match=r"^Changed: " + message):
        base.check_episode(env)


def test_a_stage_checks_its_env_before_writing_anything(tmp_path, monkeypatch):
    from bumps_jax.envs import base
    from bumps_jax.pipeline import programs

    def refused(env):
        raise ValueError("Changed: step's metrics hold no 'valid'")

    monkeypatch.setattr(base, "check_episode", refused)
    monkeypatch.setattr(programs, "_ENVS", {})
    cfg = config.make_config("tiny", {"task": "point_goal"})
    with pytest.raises(ValueError, match="hold no 'valid'"):
        pipeline.run_stage("experts", cfg, tmp_path, say=lambda *a, **k: None)
    assert not (tmp_path / "experts").exists()


def test_a_task_without_a_baseline_leaves_its_section_out(monkeypatch, capsys):
    # `stages` may be any subset, but the config's checks read cfg.baseline of every task: a task
    # without one stopped in ml_collections' AttributeError "'baseline'".
    import dataclasses
    import types

    import ml_collections

    from bumps_jax import cli
    from bumps_jax.tasks.point_goal import config as point_config

    point = tasks.get("point_goal")
    full = point_config.sections()
    own = types.SimpleNamespace(
        sections=lambda: ml_collections.ConfigDict({k: v for k, v in full.items() if k != "baseline"}),
        PRESETS={p: {k: v for k, v in o.items() if not k.startswith("baseline.")} for p, o in point.presets.items()},
        validate=lambda cfg: None,
    )
    lean = dataclasses.replace(point, stages=("experts", "meta", "filter"), config=own)
    monkeypatch.setattr(tasks, "get", lambda name: lean if name == "point_goal" else point)
    cfg = config.make_config("tiny", {"task": "point_goal"})
    assert "baseline" not in cfg and cfg.experts.ppo.num_envs == point.presets["tiny"]["experts.ppo.num_envs"]
    cli.main(["config", "--task", "point_goal"])
    assert "baseline" not in capsys.readouterr().out


@pytest.mark.parametrize(
    "item, message",
    [
        ("filter.context_range=[0.5,-0.5]", r"filter.context_range must be \(low, high\) with low < high"),
        ("filter.context_step=5", r"filter.context_step 5.0 m exceeds filter.context_range's width 2 m"),
        ("meta.dataset.clip_labels=true", r"meta.dataset.clip_labels: the point_goal env clips no action"),
        ("env.episode_steps=0", r"env.episode_steps must be a positive integer, got 0"),
    ],
)
def test_values_that_ran_wrong_or_deep_are_refused_at_once(item, message):
    # A reversed context range filtered over no grid; clip_labels on an env without a bound did
    # nothing while the record said "labels clipped"; episode_steps=0 divided by zero.
    key, value = item.split("=")
    with pytest.raises(ValueError, match=message):
        config.make_config("tiny", {"task": "point_goal", key: json.loads(value)})


def test_an_env_that_ignores_the_config_it_is_given_is_refused_naming_the_key(monkeypatch):
    """An env whose __init__ builds its config from its defaults (as `locked_config(default_config(),
    overrides)` does) ignored every `--set env.*`: a run with gear 0 trained as if with gear 1 and
    recorded gear 0. Building it through the registry names the first key it did not keep."""
    import dataclasses

    from bumps_jax import config
    from bumps_jax.tasks import registry
    from bumps_jax.tasks.point_goal import env as point_env

    class Ignoring(point_env.PointGoalEnv):
        def __init__(self, config=None, config_overrides=None):
            super().__init__(None, config_overrides)  # its defaults, not the config it was given

    cfg = config.make_config("tiny", {"task": "point_goal", "env.gear": 0.0})
    registry.make_env("point_goal", cfg.env)  # the task's own env keeps it
    task = dataclasses.replace(registry.get("point_goal"), env_class=Ignoring)
    monkeypatch.setattr(registry, "get", lambda name: task)
    with pytest.raises(
        ValueError, match=r"^the point_goal env does not keep the config it is given: env.gear is 0.0 there, "
    ):
        registry.make_env("point_goal", cfg.env)


@pytest.mark.parametrize(("task", "preset"), [(t, p) for t in tasks.TASKS for p in sorted(tasks.get(t).presets)])
def test_every_preset_of_every_task_passes_its_checks(task, preset):
    # Each preset is a valid config of its task (the cheetah's and the ant's tiny presets ask for
    # meta batches larger than their datasets, 64 of 40 pairs and 32 of 30: bc.make_trainer clamps
    # a batch to the dataset, so that is no error).
    cfg = config.make_config(preset, {"task": task})
    assert cfg.task == task and cfg.preset == preset
