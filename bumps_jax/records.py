"""Comparing the env configs that records carry: what must match between a record and its reader."""

from __future__ import annotations

import json

import ml_collections

# Env keys that size MuJoCo Warp's buffers: they change no physics, so records may differ in them.
CAPACITY_KEYS = ("warp_contacts", "warp_constraints_per_world")
MISSING = "<missing>"  # what `lookup` and `differing_keys` read where a dict lacks a key


def env_key(env: ml_collections.ConfigDict | dict) -> dict:
    """The part of an env config (as records carry it: its task's `resolved_env`) that changes the
    physics or the scoring: what must match between a record and the run that reads it (the task
    list and range only choose targets)."""
    d = env.to_dict() if isinstance(env, ml_collections.ConfigDict) else dict(env)
    return {k: jsonable(v) for k, v in sorted(d.items()) if k not in ("tasks", "task_range", *CAPACITY_KEYS)}


def differing_keys(a: dict, b: dict, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two nested dicts (missing on one side included)."""
    out = []
    for k in sorted(set(a) | set(b)):
        va, vb = a.get(k, MISSING), b.get(k, MISSING)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += differing_keys(va, vb, f"{prefix}{k}.")
        elif jsonable(va) != jsonable(vb):
            out.append(f"{prefix}{k}")
    return out


def check_same_env(record_env: dict | None, env, what: str, resolve=dict) -> None:
    """ValueError naming the differing keys if `what` (a record or asset) was made under another
    env config than `env`; a record that names none is refused too. `resolve`: the task's
    `resolved_env`, applied to both (an older record may lack keys that have defaults now)."""
    if record_env is None:
        raise ValueError(f"{what} does not record the env config it was made under; remake it")
    mine, theirs = env_key(resolve(env)), env_key(resolve(record_env))
    diff = differing_keys(theirs, mine)
    if diff:
        shown = ", ".join(f"env.{k}: {lookup(theirs, k)} there, {lookup(mine, k)} here" for k in diff)
        raise ValueError(f"{what} was made under another env config ({shown})")


def lookup(d: dict, dotted: str):
    """The value at dotted key `dotted` of nested dict `d`, or MISSING."""
    for part in dotted.split("."):
        d = d.get(part, MISSING) if isinstance(d, dict) else MISSING
    return d


def jsonable(value):
    """Plain JSON data (tuples as lists, keys sorted, anything else as its string)."""
    return json.loads(json.dumps(value, default=str, sort_keys=True))
