"""bumps_jax: Bottom-Up Meta-Policy Search on a simulated NAO, trained end to end in JAX and MuJoCo MJX."""

import contextlib as _contextlib
import io as _io
import os as _os
import sys as _sys

# Commands of `python -m bumps_jax` that render offscreen (argv[1:] -> whether it renders).
_RENDERS = {"render": lambda args: True, "video": lambda args: True,
            "kick": lambda args: any(a == "--gif" or a.startswith("--gif=") for a in args)}  # fmt: skip


def _command_line() -> tuple[str, list] | None:
    """(command, its arguments) when this process is `python -m bumps_jax <command> ...`, else None."""
    argv = list(getattr(_sys, "orig_argv", []))
    at = argv.index("-m") if "-m" in argv else -1
    if at < 0 or argv[at + 1 : at + 2] != ["bumps_jax"] or len(argv) < at + 3:
        return None
    return argv[at + 2], argv[at + 3 :]


def _choose_gl() -> None:
    """Pick MuJoCo's offscreen GL backend for a rendering command before mujoco is imported (which
    loads the backend MUJOCO_GL names once, at import): EGL, else OSMesa where only its library is
    present; neither found: left unset, and the command says so in one line before its work.
    Never where the user set MUJOCO_GL, nor for a command that does not render (with MUJOCO_GL
    set, importing mujoco loads that library, and a host without one could not even simulate)."""
    invoked = _command_line()
    if "MUJOCO_GL" in _os.environ or invoked is None:
        return
    command, args = invoked
    if command not in _RENDERS or not _RENDERS[command](args):
        return
    import ctypes.util  # noqa: PLC0415

    for backend, library in (("egl", "EGL"), ("osmesa", "OSMesa")):
        if ctypes.util.find_library(library):
            _os.environ["MUJOCO_GL"] = backend
            return


_choose_gl()

# MJX prints "Failed to import warp" to stdout when importing it on a machine without the
# optional Warp backend; every module here reaches MJX (directly or through brax), so import it
# once, quietly, first.
try:
    with _contextlib.redirect_stdout(_io.StringIO()):
        import mujoco.mjx  # noqa: F401
except (AttributeError, ImportError, OSError) as _err:  # the GL library MUJOCO_GL names is missing
    if "MUJOCO_GL" not in _os.environ:
        raise
    _message = (
        f"mujoco cannot load the GL backend MUJOCO_GL={_os.environ['MUJOCO_GL']} names ({type(_err).__name__}: "
        f"{str(_err).splitlines()[0] if str(_err) else ''}): unset MUJOCO_GL, or name one this host has (egl, osmesa)"
    )
    if _command_line() is not None:  # the command line: one line, no traceback
        _sys.exit(f"error: {_message}")
    raise ImportError(_message) from None
