"""Centre candidates over runs (experiments/centre_candidates.py): read from each run's experts
record and config, grouped by setting."""

import json

import pytest

from experiments import centre_candidates

ENV = {"impl": "warp", "episode_steps": 200}


def _run(root, name, seed, candidates, chosen, flipped_experts, choose_after=None, env=ENV, rounds=None):
    """A finished experts stage as the pipeline writes it, reduced to what the reader takes."""
    stage = root / name / "experts"
    stage.mkdir(parents=True)
    centre = {"context": 1.5, "updates": 130, "env_steps": 1000 * len(candidates), "chosen": chosen,
              "candidates": [{"error_m": e, "flipped_fraction": f} for e, f in candidates]}  # fmt: skip
    if choose_after is not None:
        centre["choose_after"] = choose_after
    if rounds is not None:  # (allowed, drawn): the candidates of every round drawn, in order
        centre["rounds"] = rounds[1]
    experts = {"family_centre": centre, "family_check": {"flipped_experts": flipped_experts},
               "tasks_m": [0.0, 1.5, 3.0],
               "error_mean_all_m": 0.1 * (1 + flipped_experts), "env_steps_total": 500, "wall_s": 10.0, "env": env,
               "device": "cpu", "versions": {}, "preset": "paper", "task": "cheetah_vel", "unit": "m/s",
               "date": "2026-11-28T00:00:00+00:00"}  # fmt: skip
    (stage / "experts.json").write_text(json.dumps(experts))
    family = {"candidates": len(candidates) // (1 if rounds is None else rounds[1]), "centre_updates": 130}
    if rounds is not None:
        family["rounds"] = rounds[0]
    (stage / "stage.json").write_text(json.dumps({"config": {"experts": {"seed": seed, "family": family}}}))
    return root / name


def test_runs_are_summarised_and_grouped_by_setting(tmp_path):
    runs = [
        _run(tmp_path, "a", 101, [(0.04, 0.0), (0.27, 0.95)], chosen=0, flipped_experts=0),
        _run(tmp_path, "b", 102, [(0.28, 0.94), (0.25, 0.93)], chosen=1, flipped_experts=2),
        _run(tmp_path, "c", 101, [(0.30, 0.9)] * 3 + [(0.05, 0.1)], chosen=3, flipped_experts=0, choose_after=40),
        # Up to 3 rounds of 2: the first two flipped, so a second round, whose first stood upright.
        _run(
            tmp_path,
            "d",
            104,
            [(0.3, 0.9), (0.4, 0.8), (0.06, 0.0), (0.3, 0.9)],
            chosen=2,
            flipped_experts=0,
            choose_after=40,
            rounds=(3, 2),
        ),  # fmt: skip
    ]
    rec = centre_candidates.record(runs, "python experiments/centre_candidates.py a b c d --out x.json")
    a, b, c, d = rec["runs"]
    assert (a["upright_candidates"], a["chosen_upright"], a["choose_after"]) == (1, True, 130)  # chosen at the end
    assert (b["upright_candidates"], b["chosen_upright"]) == (0, False)  # every candidate on its back
    assert (c["candidates"], c["choose_after"], c["chosen_upright"]) == (4, 40, True)
    assert a["env_steps_all_experts"] == 1500 and a["seed"] == 101
    assert (d["candidates"], d["rounds_allowed"], d["rounds"], d["candidates_drawn"]) == (2, 3, 2, 4)
    assert (d["upright_candidates"], d["chosen_upright"]) == (1, True)
    rounds, full, early = rec["settings"]  # by (candidates, choose_after, rounds allowed)
    assert (rounds["candidates"], rounds["rounds_allowed"], rounds["rounds"], rounds["seeds"]) == (2, 3, [2], [104])
    assert rounds["upright_candidates"] == "1 of 4" and (full["rounds_allowed"], full["rounds"]) == (1, [1, 1])
    assert (full["candidates"], full["choose_after"], full["seeds"]) == (2, 130, [101, 102])
    assert full["upright_chosen"] == 1 and full["upright_candidates"] == "1 of 4" and full["flipped_experts"] == [0, 2]
    assert full["error_mean_all"] == pytest.approx((0.1 + 0.3) / 2)
    assert (early["candidates"], early["choose_after"], early["upright_chosen"]) == (4, 40, 1)
    assert rec["device"] == "cpu" and rec["date"] == "2026-11-28T00:00:00+00:00" and rec["wall_s"] == 40.0


def test_runs_of_other_envs_or_without_a_centre_choice_are_refused(tmp_path):
    one = _run(tmp_path, "a", 101, [(0.04, 0.0)], chosen=0, flipped_experts=0)
    other = _run(tmp_path, "b", 102, [(0.04, 0.0)], chosen=0, flipped_experts=0, env={**ENV, "episode_steps": 100})
    with pytest.raises(ValueError, match="another env config"):
        centre_candidates.record([one, other], "cmd")
    path = one / "experts" / "experts.json"
    path.write_text(json.dumps({k: v for k, v in json.loads(path.read_text()).items() if k != "family_centre"}))
    with pytest.raises(ValueError, match="no family with a centre choice"):
        centre_candidates.record([one], "cmd")
