"""Headlines over pipeline seeds: runs of one config that differ only in their training seeds,
their rows side by side with the mean and spread over them (results/<task>/seeds.json)."""

from __future__ import annotations

import datetime
import shutil
from pathlib import Path

import numpy as np

from bumps_jax import config, records, runio
from bumps_jax.tasks import registry

# Each run's records the summary reads: run file -> the name it is kept under per seed.
RUN_RECORDS = {"experts/experts.json": "experts.json", "meta/table1.json": "table1.json",
               "filter/table2.json": "table2.json"}  # fmt: skip
HELDOUT = ("heldout/heldout.json", "heldout.json")  # read too where the run has it: rows heldout_<policy>
PIPELINE = ("pipeline.json", "pipeline.json")  # published beside them where the run has it (its wall times)


def run_rows(run_dir: Path) -> dict:
    """One run's headline errors: {"experts": all tasks, each net unfiltered, each filtered variant};
    their mean episode returns beside them where the env keeps one."""
    rec = {name: runio.read_json(Path(run_dir) / rel, f"a finished run's {name}") for rel, name in RUN_RECORDS.items()}
    rows = {"experts": rec["experts.json"]["error_mean_all_m"]}
    rows.update({n: r["error_mean_all_m"] for n, r in rec["table1.json"]["rows"].items() if n.startswith("meta_")})
    rows.update({n: r["error_mean_m"] for n, r in rec["table2.json"]["rows"].items()})
    if (Path(run_dir) / HELDOUT[0]).exists():
        rec[HELDOUT[1]] = runio.read_json(Path(run_dir) / HELDOUT[0])
        rows.update({f"heldout_{n}": r["error_mean_m"] for n, r in rec[HELDOUT[1]]["rows"].items()})
    scored = {**rec["table1.json"]["rows"], **rec["table2.json"]["rows"], "experts": rec["experts.json"]}
    returns = {n: r["return_mean"] for n, r in scored.items() if n in rows and r.get("return_mean") is not None}
    family = rec["experts.json"].get("family_check", {})
    n_experts = len(rec["experts.json"]["tasks_m"])
    return {"rows": rows, "returns": returns, "flipped_experts": family.get("flipped_experts"),
            "n_experts": n_experts, "records": rec}  # fmt: skip


def spread(values) -> dict:
    """Mean, std, min, max and the values themselves (per seed, in order)."""
    values = np.asarray(values, np.float64)
    return {"mean": float(values.mean()), "std": float(values.std()), "min": float(values.min()),
            "max": float(values.max()), "per_seed": values.tolist()}  # fmt: skip


def seed_of(record: dict) -> dict:
    """A run's training seeds as its record's overrides name them (the preset's own where unset)."""
    overrides = record.get("overrides", {})
    return {key: overrides.get(key, 0) for key in config.TRAINING_SEEDS}


def seeds_record(run_dirs, command: str) -> dict:
    """Every run's rows and their mean, std, min and max over the runs; ValueError naming a run
    whose env or task differs from the first's."""
    runs = [(Path(d), run_rows(Path(d))) for d in run_dirs]
    first = runs[0][1]["records"]["table2.json"]
    for d, r in runs[1:]:
        other = r["records"]["table2.json"]
        records.check_same_env(other.get("env"), first.get("env"), f"{d / 'filter/table2.json'}")
        registry.check_record_task(other.get("task"), first.get("task"), str(d))
    names = [n for n in runs[0][1]["rows"] if all(n in r["rows"] for _, r in runs)]  # rows every run has
    summary = {name: spread([r["rows"][name] for _, r in runs]) for name in names}
    returned = [n for n in names if all(n in r["returns"] for _, r in runs)]  # where the env keeps a return
    returns = {name: spread([r["returns"][name] for _, r in runs]) for name in returned}
    pipelines = [runio.read_json(d / "pipeline.json") if (d / "pipeline.json").exists() else {} for d, _ in runs]
    out = {
        "task": first.get("task"),
        "unit": first.get("unit"),
        "n_seeds": len(runs),
        "rows": summary,
        **({"returns": returns} if returns else {}),  # the same rows' mean episode return
        "runs": [
            {
                "run": d.name,
                "seeds": seed_of(p),
                "rows": {n: r["rows"][n] for n in names},
                "flipped_experts": r["flipped_experts"],
                "n_experts": r["n_experts"],
                "cloning": r["records"]["table1.json"].get("cloning", {}).get("variant"),
            }
            for (d, r), p in zip(runs, pipelines, strict=True)
        ],
        "training_seed_keys": list(config.TRAINING_SEEDS),
    }
    provenance = {k: first[k] for k in ("device", "n_devices", "versions", "preset", "env") if k in first}
    wall = sum(float(p.get("wall_s", 0.0)) for p in pipelines)
    return {
        **out,
        **provenance,
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": command,
        "wall_s": wall,
    }


def publish_seeds(run_dirs, task: str, command: str, root: str | Path = ".") -> list[Path]:
    """Each run's records under results/<task>/seeds/<run>/ (results/seeds/<run>/ for the default
    task), and their summary as results/<task>/seeds.json."""
    root, written = Path(root), []
    record = seeds_record(run_dirs, command)
    registry.check_record_task(record["task"], task, "--seed-runs")
    results = root / "results" / registry.folder(task)
    for d in map(Path, run_dirs):
        for rel, name in (*RUN_RECORDS.items(), HELDOUT, PIPELINE):
            if (d / rel).exists():
                dest = results / "seeds" / d.name / name
                dest.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(d / rel, dest)
                written.append(dest)
    path = results / "seeds.json"
    runio.write_json(path, record)
    return [*written, path]
