"""Spreading a batch axis (experts, episodes) over devices with JAX's own sharding.

Every batched program of the pipeline is a `vmap` over independent items: experts in
training, episodes in filtering. `over_batch` jits such a function with its batch split over a
one-axis `Mesh`, each device computing its slice, with no communication. On one device the
mesh has one member and the program is the one that runs everywhere else.

How the split is made depends on the devices. On GPUs, XLA's SPMD partitioner splits the
program (`jit` with sharded inputs; a `shard_map` of the experts' trainer crashed XLA's
compiler on two H200s). It cannot split a foreign call, though: it gathers the whole batch onto
every device around each of Warp's physics calls, so every device would step every episode
(and overflow a contact pool sized for its share). That is no loss on GPUs, where Warp runs on
one GPU per process (`device_mesh`), but on several CPU devices, where Warp's calls are host
callbacks, each device runs its slice as a `shard_map`.

The batch must divide evenly over the devices: `pad` repeats the last item up to a multiple
of the mesh size and callers drop the copies (`unpad`) before anything is saved, so
checkpoints and results do not depend on how many devices made them.

Several hosts: start one process per host and call `jax.distributed.initialize()` before
anything else (see README, "Several GPUs and hosts"); `jax.devices()` then lists every
host's devices and `device_mesh()` spans them all (with JAX physics: MJX's Warp backend runs on
one GPU per process, `device_mesh`).
"""

from __future__ import annotations

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

AXIS = "batch"


def device_mesh(n_devices: int | None = None, impl: str | None = None) -> Mesh:
    """A one-axis mesh over the first `n_devices` devices (default: all that the physics can use).

    `impl` is the physics backend of the programs that will run on it (`env.impl`; None: no
    physics). MJX's Warp backend runs on one GPU per process: its physics call crashes the
    process (a segmentation fault) when a program steps episodes on a second GPU, whatever
    Warp's graph mode (measured with mujoco-mjx 3.17 and warp-lang 1.18 on two H200s). So with
    Warp on GPUs the default is one device, and more is refused. On CPU devices Warp's calls
    are host callbacks and split like any other program.
    """
    devices = jax.devices()
    one_gpu = impl == "warp" and devices[0].platform == "gpu"
    n = (1 if one_gpu else len(devices)) if n_devices is None else int(n_devices)
    if not 1 <= n <= len(devices):
        raise ValueError(f"n_devices must be in [1, {len(devices)}] (the devices visible), got {n_devices!r}")
    if one_gpu and jax.process_count() > 1:
        raise ValueError(
            f"{jax.process_count()} processes with env.impl 'warp': MJX's Warp physics runs on one GPU of "
            "one process; run without --distributed, or with env.impl=jax"
        )
    if one_gpu and n > 1:
        raise ValueError(
            f"n_devices {n} with env.impl 'warp': MJX's Warp physics runs on one GPU per process "
            "(a second GPU crashes it); use one device, or env.impl=jax to spread over GPUs"
        )
    return Mesh(np.asarray(devices[:n]), (AXIS,))


def padded_size(n: int, mesh: Mesh) -> int:
    """The smallest multiple of the mesh size that holds `n` items."""
    return -(-int(n) // mesh.size) * mesh.size


def pad(tree, size: int):
    """Every leaf's leading axis grown to `size` by repeating its last row."""

    def grow(x):
        extra = size - x.shape[0]
        if extra < 0:
            raise ValueError(f"cannot pad a batch of {x.shape[0]} down to {size}")
        if extra == 0:
            return x
        tail = jax.numpy.repeat(x[-1:], extra, axis=0)
        return jax.numpy.concatenate([x, tail], axis=0)

    return jax.tree.map(grow, tree)


def unpad(tree, n: int):
    """Every leaf's first `n` rows (the real items; the rest are `pad`'s copies).

    With several processes (hosts), each holds only its devices' rows: they are gathered first,
    so every process gets the whole batch as host arrays and the host code after a program
    call (progress, checkpoints, selection) runs the same everywhere.
    """
    return jax.tree.map(lambda x: x[:n], gather(tree))


def gather(tree):
    """The whole of every (possibly multi-host) array, on every process; as is with one process."""
    if jax.process_count() == 1:
        return tree
    from jax.experimental import multihost_utils  # noqa: PLC0415

    return multihost_utils.process_allgather(tree, tiled=True)


def initialize_distributed() -> None:
    """Join a multi-host job: one process per host, all running the same command.

    Under SLURM (or on TPU pods) `jax.distributed.initialize()` finds the coordinator, process
    count and id by itself; elsewhere set JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES and
    JAX_PROCESS_ID. Afterwards `jax.devices()` lists every host's devices.
    """
    jax.distributed.initialize()


def over_batch(fn, mesh: Mesh, batched: tuple[bool, ...], out_axis: int = 0):
    """`fn` jitted with the arguments flagged in `batched` split on their leading axis over
    `mesh`, the others replicated, and every output split on axis `out_axis`.

    `fn` must treat the items of its batch independently (a vmap), so each device's slice
    gives what the whole batch would. On several CPU devices each runs `fn` on its own slice
    (`shard_map`: values `fn` closes over, such as a blank Warp episode with its contact pool,
    are copied to every device); elsewhere XLA's partitioner splits the program (module
    docstring).
    """
    in_specs = tuple(P(AXIS) if b else P() for b in batched)
    out_spec = P(*([None] * out_axis), AXIS)
    if mesh.size > 1 and mesh.devices.flat[0].platform == "cpu":
        # check_vma off: a scan whose carry starts from a replicated constant (the blank episode)
        # and becomes per-device is fine here, since every output is split over the batch anyway.
        fn = jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=out_spec, check_vma=False)
    return jax.jit(
        fn,
        in_shardings=tuple(NamedSharding(mesh, s) for s in in_specs),
        out_shardings=NamedSharding(mesh, out_spec),
    )


def place(tree, mesh: Mesh):
    """Put a batch (leading axis a multiple of the mesh size) split over the mesh's devices.

    Calling a program always with inputs placed like this keeps jit's cache to one entry: an
    input laid out differently (e.g. fresh from the host) would compile the program again.
    """
    return jax.device_put(tree, NamedSharding(mesh, P(AXIS)))
