"""Centre candidates side by side: for finished experts stages of a family (`experts.family`), how
many of each run's centre candidates stood upright, whether the one the family continued from
did, and what the family became (its error, its flipped experts, its env steps), grouped by
setting (candidates, choose_after).

Reads each run's experts/experts.json and experts/stage.json (the config it ran) and writes one
record; nothing is rerun.

    python experiments/centre_candidates.py runs/devc8_0_101 runs/devc8_0_102 \
        --out experiments/results/cheetah_centre_candidates_dev_gpu.json
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from bumps_jax import records, runio
from bumps_jax.algo.evaluate import FLIPPED
from bumps_jax.pipeline.family import upright as stands_upright

PROVENANCE = ("device", "n_devices", "versions", "preset", "env", "task", "unit")


def run_summary(run_dir: Path) -> dict:
    """One run's centre candidates and family, from its experts' record and config."""
    experts = runio.read_json(run_dir / "experts" / "experts.json", "a finished experts stage")
    config = runio.read_json(run_dir / "experts" / "stage.json", "the experts stage's config")["config"]["experts"]
    centre = experts.get("family_centre")
    if centre is None or "candidates" not in centre:
        raise ValueError(f"{run_dir}: its experts are no family with a centre choice (experts.family)")
    upright = [stands_upright(c) for c in centre["candidates"]]
    return {
        "run": run_dir.name,
        "seed": config["seed"],
        "candidates": int(config["family"].get("candidates", 1)),  # per round
        "choose_after": centre.get("choose_after", centre["updates"]),
        "rounds_allowed": int(config["family"].get("rounds", 1)),
        "rounds": centre.get("rounds", 1),  # rounds drawn: another only where every candidate ran flipped
        "candidates_drawn": len(upright),
        "centre_updates": centre["updates"],
        "candidate_errors": [c["error_m"] for c in centre["candidates"]],
        "upright_candidates": int(sum(upright)),
        "chosen": centre["chosen"],
        "chosen_upright": bool(upright[centre["chosen"]]),
        "flipped_experts": experts["family_check"]["flipped_experts"],
        "n_experts": len(experts["tasks_m"]),
        "error_mean_all": experts["error_mean_all_m"],
        "centre_env_steps": centre["env_steps"],
        "env_steps_all_experts": experts["env_steps_total"] * len(experts["tasks_m"]),
        "wall_s": experts["wall_s"],
    }


def settings(runs: list[dict]) -> list[dict]:
    """The runs grouped by (candidates, choose_after, rounds allowed): seeds, rounds drawn, how many
    chose an upright centre, the families' mean error and flipped experts, and the env steps of
    each run's experts."""
    out = []
    setting = lambda r: (r["candidates"], r["choose_after"], r["rounds_allowed"])  # noqa: E731
    for key in sorted({setting(r) for r in runs}):
        group = [r for r in runs if setting(r) == key]
        upright = sum(r["upright_candidates"] for r in group)
        out.append({
            "candidates": key[0],
            "choose_after": key[1],
            "rounds_allowed": key[2],
            "seeds": [r["seed"] for r in group],
            "rounds": [r["rounds"] for r in group],
            "upright_chosen": sum(r["chosen_upright"] for r in group),
            "upright_candidates": f"{upright} of {sum(r['candidates_drawn'] for r in group)}",
            "error_mean_all": float(np.mean([r["error_mean_all"] for r in group])),
            "flipped_experts": [r["flipped_experts"] for r in group],
            "env_steps_all_experts": [r["env_steps_all_experts"] for r in group],
        })  # fmt: skip
    return out


def record(run_dirs: list[Path], command: str) -> dict:
    """The record over `run_dirs`; ValueError where they ran other envs."""
    runs = [run_summary(d) for d in run_dirs]
    first = runio.read_json(run_dirs[0] / "experts" / "experts.json")
    for d in run_dirs[1:]:
        records.check_same_env(runio.read_json(d / "experts" / "experts.json").get("env"), first.get("env"), str(d))
    return {
        "settings": settings(runs),
        "runs": runs,
        "flipped_threshold": FLIPPED,
        **{k: first[k] for k in PROVENANCE if k in first},
        "date": first["date"],
        "command": command,
        "wall_s": sum(r["wall_s"] for r in runs),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run directories with a finished experts stage")
    parser.add_argument("--out", type=Path, required=True, help="the record to write (.json)")
    args = parser.parse_args()
    try:
        rec = record(args.runs, runio.command_line())
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"error: {err}") from None
    runio.write_json(args.out, rec)
    for s in rec["settings"]:
        print(f"{s['candidates']} candidates compared after {s['choose_after']} updates (at most "
              f"{s['rounds_allowed']} rounds; drawn {s['rounds']}), seeds {s['seeds']}: "
              f"upright centre chosen in {s['upright_chosen']} of {len(s['seeds'])} (upright candidates "
              f"{s['upright_candidates']}), experts {s['error_mean_all']:.3f} {rec.get('unit', '')}, flipped "
              f"{s['flipped_experts']}")  # fmt: skip
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
