"""Provenance for every results file: device, package versions, date, command, wall time."""

from __future__ import annotations

import datetime
import json
import os
import sys
from importlib import metadata
from pathlib import Path

import jax

PACKAGES = ("jax", "jaxlib", "mujoco", "mujoco-mjx", "brax", "flax", "optax", "orbax-checkpoint", "evosax")


def device_name() -> str:
    """e.g. 'NVIDIA H100 80GB HBM3', or 'cpu'."""
    dev = jax.devices()[0]
    return "cpu" if dev.platform == "cpu" else str(dev.device_kind)


def versions() -> dict:
    out = {}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    out["python"] = sys.version.split()[0]
    return out


def provenance(preset: str, wall_s: float, command: str | None = None, physics_dt_s: float | None = None) -> dict:
    """The keys every results file carries (see the results contract in docs/), and the physics step
    its env ran at where one did: results made at different steps are not comparable."""
    record = {
        "device": device_name(),
        "n_devices": jax.device_count(),
        "versions": versions(),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": command or _command_line(),
        "preset": preset,
        "wall_s": round(float(wall_s), 3),
    }
    if physics_dt_s is not None:
        record["physics_dt_s"] = float(physics_dt_s)
    return record


def write_json(path: str | os.PathLike, payload: dict) -> Path:
    """Write atomically (temp file + rename): a killed run never leaves half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(payload, indent=2, default=float) + "\n")
    tmp.replace(path)
    return path


def save_figure(fig, path: str | os.PathLike) -> Path:
    """Save a matplotlib figure as PNG (tight layout, 120 dpi) and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _command_line() -> str:
    """How this process was started, as a user would type it (no absolute paths)."""
    script = Path(sys.argv[0]).resolve()
    package = Path(__file__).resolve().parent
    if script.parent == package:  # python -m bumps_jax[.module]
        head = "python -m bumps_jax" + ("" if script.stem == "__main__" else f".{script.stem}")
    elif sys.argv[0] in ("-c", ""):
        head = "python -c <inline>"
    else:
        try:
            head = f"python {script.relative_to(Path.cwd()).as_posix()}"
        except ValueError:
            head = f"python {script.name}"
    return " ".join([head, *sys.argv[1:]])
