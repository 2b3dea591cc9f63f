"""The trained policies a published run ships (assets/policies/), their reader, and `kick`.

    assets/policies/
      policies.json        format, the env config (physics step, backend), provenance, the nets'
                           architectures, the filter settings and the filtering choices
      meta_4x256.msgpack   params of each meta-policy (the filtered seed, `filter.net_seed`)
      meta_11x128.msgpack
      experts.msgpack      the experts' params stacked over tasks (observation statistics, policy)

Params are flax.serialization msgpack. `load` refuses policies made under another env config
than the caller's (as `kick_model.load_record` does for the prior): a policy trained at one
physics step or backend does not kick the same under another.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any, NamedTuple

import jax
import ml_collections
import numpy as np

from bumps_jax import records as env_records
from bumps_jax import runio
from bumps_jax.algo import filtering
from bumps_jax.tasks.kick import env as kick_env

FORMAT_VERSION = 1
MANIFEST = "policies.json"
ASSET_DIR = Path(__file__).resolve().parents[3] / "assets" / "policies"
HOW_TO_MAKE = "publish a paper run: python -m bumps_jax publish --run-dir runs/paper"


class Shipped(NamedTuple):
    """Policies read back from a shipped directory."""

    manifest: dict  # policies.json
    nets: dict  # net name -> params of one meta-policy (bc.MetaPolicy's)
    experts: dict  # the experts' params as a flax state dict, leaves (E, ...)


def _serialize(tree) -> bytes:
    from flax import serialization  # noqa: PLC0415

    return serialization.msgpack_serialize(serialization.to_state_dict(jax.tree.map(np.asarray, tree)))


def write(cfg, run_dir: str | Path, dest: str | Path) -> list[Path]:
    """Ship a finished run's meta-policies, experts and filtering choices into `dest`.

    The nets' architectures and training settings come from the meta stage's record, the seed
    and choices from the filter stage's; the experts are read with `cfg`'s experts section.
    ValueError naming the first missing record.
    """
    from bumps_jax.algo import bc  # noqa: PLC0415
    from bumps_jax.pipeline.stages import experts as experts_stage  # noqa: PLC0415
    from bumps_jax.pipeline.stages import filter as filter_stage  # noqa: PLC0415
    from bumps_jax.pipeline.stages import meta as meta_stage  # noqa: PLC0415

    run_dir, dest = Path(run_dir), Path(dest)
    table1 = runio.read_json(run_dir / "meta" / meta_stage.OUTPUT, "the meta-policies' record: run meta-train first")
    table2 = runio.read_json(run_dir / "filter" / filter_stage.OUTPUT, "the filter stage's record: run filter first")
    experts_record = runio.read_json(run_dir / "experts" / experts_stage.OUTPUT, "run train-experts first")
    env = kick_env.resolved(table1["env"])
    for what, record in (("filter", table2), ("experts", experts_record)):
        env_records.check_same_env(record.get("env"), env, f"the {what} record of {run_dir}", kick_env.resolved)
    runio.check_writable(dest)
    train_cfg = ml_collections.ConfigDict(table1["config"]["train"])
    obs_norm = bc.obs_norm_of_record(table1)
    net_seed = int(table2["config"]["net_seed"])
    written, nets = [], {}
    for net in meta_stage.NETS:
        depth, width = table1["config"]["nets"][net]
        _, params = bc.load_policy(run_dir / "meta" / net, depth, width, train_cfg)
        path = runio.write_bytes(dest / f"{net}.msgpack", _serialize(jax.tree.map(lambda a: a[net_seed], params)))
        nets[net] = {"depth": int(depth), "width": int(width), "file": path.name, "sha256": runio.sha256_of(path)}
        nets[net].update(bc.obs_norm_fields(obs_norm))  # the fixed map in front of the first layer
        written.append(path)
    family = experts_stage.load_family(cfg, run_dir)
    path = runio.write_bytes(dest / "experts.msgpack", _serialize(family.params))
    written.append(path)
    keep = ("context_range", "context_step", "width", "selection_repetitions", "net_seed")
    manifest = {
        "format_version": FORMAT_VERSION,
        "env": env,
        "physics_dt": env["physics_dt"],
        "impl": env["impl"],
        "nets": nets,
        "experts": {
            "file": "experts.msgpack",
            "sha256": runio.sha256_of(path),
            "tasks_m": [float(t) for t in family.tasks],
            "ppo_policy": {k: cfg.experts.ppo[k] for k in ("policy_hidden", "normalize_observations")},
        },
        "filter": {k: table2["config"][k] for k in keep},
        "filtering_choices": {
            "tasks_m": table2["tasks"],
            "chosen_contexts": table2["chosen_contexts"],
        },
        "trained_by": {k: table1.get(k) for k in ("device", "versions", "date", "command", "preset")},
        **runio.provenance(table1.get("preset", cfg.preset), 0.0, env),
    }
    heldout = run_dir / "heldout" / "heldout.json"
    if heldout.exists():
        record = runio.read_json(heldout)
        manifest["heldout_choices"] = {"targets_m": record["targets_m"], "chosen_contexts": record["chosen_contexts"]}
    written.append(runio.write_json(dest / MANIFEST, manifest))
    return written


def seal(directory: str | Path = ASSET_DIR) -> Path:
    """Record each shipped file's sha256 in `directory`'s policies.json (as `write` does), for a
    directory shipped before policies carried them; `load` checks them."""
    directory = Path(directory)
    manifest = runio.read_json(directory / MANIFEST, "a shipped-policies manifest")
    for entry in [*manifest["nets"].values(), manifest["experts"]]:
        entry["sha256"] = runio.sha256_of(directory / entry["file"])
    return runio.write_json(directory / MANIFEST, manifest)


def env_config(manifest: dict, overrides: dict | None = None) -> ml_collections.ConfigDict:
    """The env config the shipped policies were trained under, with dotted `overrides` ({"impl": "warp"})."""
    flat = {}

    def walk(d, prefix=""):
        for k, v in d.items():
            if isinstance(v, dict):
                walk(v, f"{prefix}{k}.")
            else:
                flat[f"{prefix}{k}"] = tuple(v) if isinstance(v, list) else v

    walk(manifest["env"])
    defaults = kick_env.default_config()
    flat = {k: v for k, v in flat.items() if k.split(".")[0] in defaults}  # keys of a newer env only
    return kick_env.make_config(None, {**flat, **(overrides or {})})


def kick_env_config(manifest: dict, overrides: dict | None, n_kicks: int, n_devices: int = 1):
    """The env config `kick` runs: the policies' own (`env_config`), with Warp's contact pool sized
    to the command's block of KICK_BLOCK episodes per device (whatever `n_kicks`) unless `overrides` set it. The pool is
    a capacity, not physics (records do not compare it); on a CPU every slot of a pool sized for
    the training run's thousands of episodes costs time at every step (half of `kick`'s time)."""
    pool = {"warp_contacts": kick_env.CONTACTS_PER_EPISODE * KICK_BLOCK * int(n_devices)}  # a block's episodes
    return env_config(manifest, {**pool, **(overrides or {})})


def load(directory: str | Path = ASSET_DIR, env_cfg=None) -> Shipped:
    """The shipped policies in `directory`; with `env_cfg`, ValueError naming the differing env keys
    if they were made under another env config. A missing directory says how to make one."""
    from flax import serialization  # noqa: PLC0415

    directory = Path(directory)
    if not (directory / MANIFEST).is_file():
        raise ValueError(f"no shipped policies in {directory}: {HOW_TO_MAKE}")
    manifest = runio.read_json(directory / MANIFEST, "a shipped-policies manifest")
    if manifest.get("format_version") != FORMAT_VERSION:
        raise ValueError(
            f"{directory / MANIFEST}: format_version {manifest.get('format_version')!r}, expected {FORMAT_VERSION}"
        )
    if env_cfg is not None:
        what = f"the shipped policies in {directory}"
        env_records.check_same_env(manifest.get("env"), env_cfg, what, kick_env.resolved)

    def read(entry):
        path = directory / entry["file"]
        if not path.is_file():
            raise ValueError(f"{runio.shown(path)}: missing from the shipped policies: {HOW_TO_MAKE}")
        data = path.read_bytes()
        if "sha256" in entry and hashlib.sha256(data).hexdigest() != entry["sha256"]:
            raise ValueError(
                f"{runio.shown(path)}: its sha256 is not the one {MANIFEST} records ({len(data)} bytes): "
                "the file is damaged, truncated or another policy's; restore it from the repository"
            )
        try:
            return serialization.msgpack_restore(data)
        except Exception as err:  # noqa: BLE001 (msgpack raises several kinds)
            raise ValueError(f"{runio.shown(path)}: not a shipped policy ({runio.error_reason(err)})") from None

    nets = {net: read(entry) for net, entry in manifest["nets"].items()}
    shipped = Shipped(manifest, nets, read(manifest["experts"]))
    for net, entry in manifest["nets"].items():  # a file of another net (no checksum to tell)
        width = {np.shape(leaf)[-1] for leaf in jax.tree.leaves(nets[net])}
        if int(entry["width"]) not in width:
            raise ValueError(
                f"{runio.shown(directory / entry['file'])}: holds no layer of width {entry['width']} "
                f"({net} in {MANIFEST}): another net's file?"
            )
    return shipped


# Episodes per device of one compiled call of `filtered_kicks` (its selection and its kicks): fixed,
# so that few kicks cost no more calls than many (a block of --kicks 2 made the selection 8x the calls).
KICK_BLOCK = 16


class Kicks(NamedTuple):
    """What `filtered_kicks` found and measured."""

    context: float  # m, the context chosen for the target
    candidates: np.ndarray  # (C,) m, the contexts it chose from
    selection_error: np.ndarray  # (C,) m, each candidate's mean error against the target
    distance: np.ndarray  # (N,) m, where each kick's ball came to rest along the kick line
    final_error: np.ndarray  # (N,) m, its distance to the target
    valid: np.ndarray  # (N,) bool
    keys: Any = None  # (N,) each kick's noise key: a kick replayed with its key is that kick


def filtered_kicks(
    shipped: Shipped, net: str, target: float, n_kicks: int, env_cfg, selection_repetitions: int = 4, seed: int = 0,
    progress=None,
) -> Kicks:  # fmt: skip
    """Filter a context for `target` (m) as the run did (its grid and width; `selection_repetitions`
    noisy kicks per candidate), then `n_kicks` fresh noisy kicks at the chosen context (`progress`:
    called (kicks done, n_kicks) after each call of them)."""
    from bumps_jax.algo import bc, sharding  # noqa: PLC0415
    from bumps_jax.pipeline import programs as meta_programs  # noqa: PLC0415

    f = shipped.manifest["filter"]
    task_range = tuple(env_cfg.task_range)
    targets = kick_env.check_targets([float(target)], task_range)
    grid = filtering.context_grid(*f["context_range"], f["context_step"])
    contexts = filtering.candidate_contexts(targets, grid)
    contexts = contexts[np.abs(contexts - targets[0]) <= f["width"] + 1e-6]
    entry = shipped.manifest["nets"][net]
    mesh = sharding.device_mesh(impl=env_cfg.impl)
    obs_norm = bc.obs_norm_of_record(entry)  # the net's fixed input map, shipped with it (None: none)
    program = meta_programs.meta_grid(env_cfg, entry["depth"], entry["width"], mesh, "kick", obs_norm)
    params = jax.tree.map(lambda a: np.asarray(a)[None], shipped.nets[net])
    sel_key, eval_key = filtering.noise_keys(seed)
    block = KICK_BLOCK * sharding.ways(mesh)  # one compiled program serves the selection and the kicks
    sel = filtering.filter_policy(
        program, params, contexts, targets, f["width"], selection_repetitions, sel_key,
        task_range=task_range, block=block, multiple=sharding.ways(mesh),
        **filtering.scoring(meta_programs.stage_env(env_cfg, "kick")),
    )  # fmt: skip
    context = float(sel.contexts[sel.chosen[0]])
    m = filtering.evaluate_chosen(program, params, [context], targets, n_kicks, eval_key, block, sharding.ways(mesh),
                                  progress)  # fmt: skip
    keys = filtering.stage_keys(eval_key, 1, n_kicks)  # evaluate_chosen's keys, kick by kick
    return Kicks(context, sel.contexts, sel.scores[0], m["distance"][0], m["final_error"][0], m["valid"][0] > 0, keys)


SHOWN_KICKS = 32  # the resting distances `kick` lists one by one; more are summed up above them


def describe(shipped: Shipped, net: str, target: float, kicks: Kicks, wall_s: float | None = None) -> list[str]:
    """The lines `kick` prints."""
    m = shipped.manifest
    trained = m.get("trained_by", {})
    lines = [
        f"{net} (shipped, trained on {trained.get('device', 'an unrecorded device')}, preset "
        f"{trained.get('preset')}), physics backend {m['impl']}, step {m['physics_dt'] * 1e3:g} ms",
        f"target {target:.3f} m: context {kicks.context:.2f} m chosen among {len(kicks.candidates)} within "
        f"+- {m['filter']['width']:g} m (its selection error {kicks.selection_error.min():.2f} m)",
        f"{len(kicks.distance)} noisy kicks: resting distance {kicks.distance.mean():.2f} +- "
        f"{kicks.distance.std():.2f} m, error {kicks.final_error.mean():.2f} +- {kicks.final_error.std():.2f} m, "
        f"valid {kicks.valid.mean():.2f}",
        "each kick (m): "
        + " ".join(f"{d:.2f}" for d in kicks.distance[:SHOWN_KICKS])
        + (f" ... ({len(kicks.distance)} in all)" if len(kicks.distance) > SHOWN_KICKS else ""),
    ]
    if wall_s is not None:
        lines.append(f"{wall_s:.1f} s, compiling included")
    return lines
