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
# `pipeline.MANIFEST_SCHEMA`. Re-pinned when the losing arms' knobs left the tree (schema 2).
KICK_SECTIONS = {
    "tiny": {
        "prior": "7129f2c0c8a5fbc223648451c94ff60aa6c7cd5fb1e7dfdb2cefd1160c757983",
        "experts": "9b27aef357e3d85016bfb28f8e3a0cc63ad5eea30e461f028eaaa0cf811da046",
        "meta": "9f61c7c2f0ee9df1b5d6582298d9413735fd8dedd8e446cb824f7ec68e224381",
        "filter": "81ae60fe857ac89f1eba00f63262b72dc2554fb7f176b221b5d52f41a7dd1465",
        "heldout": "76980f87b5f5a78ea4c3b8b909581a3629b9e5e823f5167e86fb002102c19581",
        "baseline": "88f64e4ead9f1c4ed6875a1891601ce9d0415e4ce069bc8c23094462beb64272",
    },
    "paper": {
        "prior": "e38b970f96217601c6ed4c31aff219830db04d78627ad7239a92aca0fb1dfadc",
        "experts": "0f1c1ef60373fb2544c4b4bec487d47a8d47cf7c92d19072c58465ebca6c8c6f",
        "meta": "b3cbdc5da8d75d3f3d733a551ce389880e93f61c2b330750bd0b66d84070b146",
        "filter": "ab9e5ff5612b5c379ee36c36ee5c678ece58954c529f0017aab817c2269f29c9",
        "heldout": "3d00234a9a024e9b03d79264da1858dd0404759e5043654ec3c158bebcff9205",
        "baseline": "853e9de1255af4d4709ad6b988a5da7470cc7750e72ce0ea0479a003b50474e1",
    },
}


def digest(section: dict) -> str:
    return hashlib.sha256(json.dumps(section, sort_keys=True).encode()).hexdigest()


@pytest.mark.parametrize("preset", sorted(KICK_SECTIONS))
def test_the_kicks_stage_sections_are_unchanged(preset):
    cfg = config.make_config(preset)
    assert cfg.task == "kick"
    sections = {s: digest(config.section(cfg, s)) for s in KICK_SECTIONS[preset]}
    assert sections == KICK_SECTIONS[preset]
    assert config.task_view(cfg) is cfg


def test_cheetah_sections_are_its_own():
    cfg = config.make_config("tiny", {"task": "cheetah_vel"})
    view = config.task_view(cfg)
    assert view.task == "cheetah_vel" and config.task_view(view) is view
    assert tuple(view.experts.tasks) == (0.5, 2.0) and view.env.episode_steps == 10
    section = config.section(cfg, "experts")
    assert section["task"] == "cheetah_vel" and section["env"]["physics_dt"] == pytest.approx(0.01)
    assert section["experts"] == json.loads(json.dumps(view.experts.to_dict(), default=list))
    # The kick's sections of the same config are untouched by the switch.
    kick = config.make_config("tiny")
    assert config.section(kick, "experts") == config.section(config.make_config("tiny", {"task": "kick"}), "experts")
    paper = config.task_view(config.make_config("paper", {"task": "cheetah_vel"}))
    assert paper.env.warp_contacts >= 16 * len(paper.experts.tasks) * paper.experts.ppo.num_envs
    assert not set(paper.experts.tasks) & set(paper.filter.tasks)  # the test velocities are held out


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"task": "walker"}, "unknown task 'walker'; choose one of"),
        ({"task": "cheetah_vel", "cheetah_vel.experts.tasks": (3.5,)}, "cheetah_vel.experts.tasks: target 3.5 m/s"),
        ({"task": "cheetah_vel", "cheetah_vel.env.impl": "torch"}, "cheetah_vel.env.impl must be one of"),
        (
            {"task": "cheetah_vel", "cheetah_vel.baseline.eval_tasks": (3.5,)},
            "cheetah_vel.baseline.eval_tasks: target 3.5 m/s",
        ),
        (
            {"task": "cheetah_vel", "cheetah_vel.baseline.ppo.sample_task_range": (2.0, 0.5)},
            "cheetah_vel.baseline.ppo.sample_task_range must be",
        ),
        (
            {
                "task": "cheetah_vel",
                "cheetah_vel.experts.ppo.num_envs": 64,
                "cheetah_vel.experts.ppo.total_env_steps": 1280,
            },
            "cheetah_vel.env.warp_contacts 256 holds 16 episodes",
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

    assert cli.task_overrides({"experts.seed": 3}) == {"experts.seed": 3}
    moved = cli.task_overrides({"task": "cheetah_vel", "experts.seed": 3, "preset": "tiny"})
    assert moved == {"task": "cheetah_vel", "cheetah_vel.experts.seed": 3, "preset": "tiny"}
    assert str(cli.default_run_dir("reproduce", "paper", "cheetah_vel")) == "runs/cheetah_vel/paper"
    assert str(cli.default_run_dir("demo", "tiny")) == "runs/demo"
    args = cli.build_parser().parse_args(["reproduce", "--task", "cheetah_vel", "--set", "experts.seed=3"])
    assert (args.task, args.preset) == ("cheetah_vel", "paper")
