"""bumps_jax: Bottom-Up Meta-Policy Search on a simulated NAO, trained end to end in JAX and MuJoCo MJX."""

import contextlib as _contextlib
import io as _io

# MJX prints "Failed to import warp" to stdout when importing it on a machine without the
# optional Warp backend; every module here reaches MJX (directly or through brax), so import it
# once, quietly, first.
with _contextlib.redirect_stdout(_io.StringIO()):
    import mujoco.mjx  # noqa: F401
