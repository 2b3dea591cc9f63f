"""Spreading a batch axis (experts, episodes, searches) over devices and processes.

Every batched program of the pipeline is a `vmap` over independent items: experts in
training, episodes in filtering. `over_batch` jits such a function for a batch that is split
two ways:

- over processes (JAX's multi-controller runtime, `jax.distributed`): every process runs the
  same command, computes its own rows of the batch with its own program on its own devices,
  and the rows are gathered back to every process after the call (`process_allgather`), so the
  host code after a program call (progress, checkpoints, selection) runs the same everywhere;
- over the devices of one process: a one-axis `Mesh`. On several CPU devices each runs its
  slice as a `shard_map`. MJX's Warp physics runs on one GPU per process (a program stepping
  episodes on a second GPU of the process crashes it, mujoco-mjx 3.17, warp-lang 1.18), so with
  Warp on GPUs a process uses one GPU, and several GPUs are several processes (`launch`).

The batch must divide evenly over every device of every process (`ways`): `pad` repeats the
last item up to a multiple of it and callers drop the copies (`unpad`) before anything is
saved, so checkpoints and results do not depend on how many devices or processes made them.
"""

from __future__ import annotations

import os

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

AXIS = "batch"


def device_mesh(n_devices: int | None = None, impl: str | None = None) -> Mesh:
    """A one-axis mesh over the first `n_devices` of this process's devices (default: all that
    the physics can use).

    `impl` is the physics backend of the programs that will run on it (`env.impl`; None: no
    physics). With Warp on GPUs the default is one device and more is refused: a second GPU
    crashes Warp's physics (module docstring); start one process per GPU instead. On CPU
    devices Warp's calls are host callbacks and split like any other program.
    """
    devices = jax.local_devices()
    one_gpu = impl == "warp" and devices[0].platform == "gpu"
    n = (1 if one_gpu else len(devices)) if n_devices is None else int(n_devices)
    if not 1 <= n <= len(devices):
        raise ValueError(f"n_devices must be in [1, {len(devices)}] (the devices this process sees), got {n_devices!r}")
    if one_gpu and n > 1:
        raise ValueError(
            f"n_devices {n} with env.impl 'warp': MJX's Warp physics runs on one GPU per process "
            "(a second GPU crashes it); run one process per GPU (--processes)"
        )
    return Mesh(np.asarray(devices[:n]), (AXIS,))


def ways(mesh: Mesh) -> int:
    """How many slices a batch is split into: the mesh's devices in every process."""
    return mesh.size * jax.process_count()


def padded_size(n: int, mesh: Mesh) -> int:
    """The smallest multiple of `ways(mesh)` that holds `n` items."""
    return -(-int(n) // ways(mesh)) * ways(mesh)


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
    """Every leaf's first `n` rows (the real items; the rest are `pad`'s copies)."""
    return jax.tree.map(lambda x: x[:n], tree)


def own_rows(tree, axis: int = 0):
    """This process's equal share of every leaf's `axis` (the whole of it with one process)."""
    count, index = jax.process_count(), jax.process_index()
    if count == 1:
        return tree

    def rows(x):
        size = x.shape[axis]
        if size % count:
            raise ValueError(f"a batch of {size} does not split over {count} processes: pad it (sharding.pad)")
        k = size // count
        return x[(slice(None),) * axis + (slice(index * k, (index + 1) * k),)]  # host arrays stay on the host

    return jax.tree.map(rows, tree)


def gather(tree, axis: int = 0):
    """Every process's rows (`own_rows`) joined along `axis`, as host arrays on every process;
    as is with one process. One collective per dtype: the leaves of a dtype travel as one
    flat row per process."""
    count = jax.process_count()
    if count == 1:
        return tree
    from jax.experimental import multihost_utils  # noqa: PLC0415

    leaves, treedef = jax.tree.flatten(tree)
    host = [np.moveaxis(np.asarray(x), axis, 0) for x in leaves]
    joined = [None] * len(host)
    # The same order of collectives in every process: sorted, not a set's (whose order follows
    # Python's hash seed, which differs between processes).
    for dtype in sorted({x.dtype for x in host}, key=str):
        which = [i for i, x in enumerate(host) if x.dtype == dtype]
        rows = multihost_utils.process_allgather(np.concatenate([host[i].reshape(-1) for i in which]))
        start = 0
        for i in which:
            size = host[i].size
            parts = rows[:, start : start + size].reshape(count, *host[i].shape)  # (processes, rows, ...)
            joined[i] = np.moveaxis(np.concatenate(parts, axis=0), 0, axis)
            start += size
    return jax.tree.unflatten(treedef, joined)


def owner(i: int) -> int:
    """The process that computes item i of a few unequal items (nets of different shapes)."""
    return i % jax.process_count()


def own_items(items: list) -> list:
    """This process's share of a few unequal items (`owner`; all of them with one process)."""
    return [x for i, x in enumerate(items) if owner(i) == jax.process_index()]


def from_owners(trees: list) -> list:
    """Item i of `trees` as its `owner` holds it, as host arrays on every process, in one
    `gather` (as is with one process); every process passes trees of the same shapes."""
    if jax.process_count() == 1:
        return trees
    rows = gather([jax.tree.map(lambda x: np.asarray(x)[None], t) for t in trees])
    return [jax.tree.map(lambda x, i=i: x[owner(i)], row) for i, row in enumerate(rows)]


def barrier(name: str) -> None:
    """Wait until every process reaches the barrier `name` (nothing with one process)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils  # noqa: PLC0415

        multihost_utils.sync_global_devices(name)


def is_writer() -> bool:
    """Whether this process writes the run's files: the first of the processes (every process
    computes the same host values, so one copy is written)."""
    return jax.process_index() == 0


def initialize_distributed() -> None:
    """Join a multi-process job: every process runs the same command.

    Under SLURM `jax.distributed.initialize()` finds the coordinator, process count and id by
    itself; `launch` (and any other launcher) sets JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES and
    JAX_PROCESS_ID instead. Afterwards `jax.process_count()` is the number of processes, and each
    computes its share of every batch (`over_batch`). A job of one process starts no coordinator.
    """
    count, index = os.environ.get("JAX_NUM_PROCESSES"), os.environ.get("JAX_PROCESS_ID")
    if count is not None and int(count) == 1:
        return  # a job of one process (a branch of `--processes` or `--seeds`): nothing to join
    if count is None or index is None:
        try:
            jax.distributed.initialize()
        except ValueError as err:  # no launcher's environment to find the job in
            raise ValueError(
                f"--distributed: no multi-process job found ({err}): start each process under srun, or set "
                "JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES and JAX_PROCESS_ID; on one host use --processes N"
            ) from None
    else:
        jax.distributed.initialize(num_processes=int(count), process_id=int(index))


def over_batch(fn, mesh: Mesh, batched: tuple[bool, ...], out_axis: int = 0):
    """`fn` jitted for arguments whose leading axis (those flagged in `batched`; the others are
    given whole to every device) is a batch of independent items, every output's batch on axis
    `out_axis`. The batch must be a multiple of `ways(mesh)` (`pad`).

    Each process takes its rows (`own_rows`) and splits them over its mesh; the outputs of every
    process are gathered (`gather`), so every process gets the whole batch. On several CPU
    devices each runs `fn` on its own slice (`shard_map`: values `fn` closes over, such as a
    blank Warp episode with its contact pool, are copied to every device); elsewhere XLA's
    partitioner splits the program. `fn` must treat its items independently (a vmap).
    """
    in_specs = tuple(P(AXIS) if b else P() for b in batched)
    out_spec = P(*([None] * out_axis), AXIS)
    if mesh.size > 1 and mesh.devices.flat[0].platform == "cpu":
        # check_vma off: a scan whose carry starts from a replicated constant (the blank episode)
        # and becomes per-device is fine here, since every output is split over the batch anyway.
        fn = jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=out_spec, check_vma=False)
    program = jax.jit(
        fn,
        in_shardings=tuple(NamedSharding(mesh, s) for s in in_specs),
        out_shardings=NamedSharding(mesh, out_spec),
    )
    if jax.process_count() == 1:
        return program

    shardings = tuple(NamedSharding(mesh, s) for s in in_specs)

    def own(args):  # this process's rows of the batched arguments, placed on its mesh
        return tuple(
            jax.device_put(own_rows(a) if b else a, sharding)
            for a, b, sharding in zip(args, batched, shardings, strict=True)
        )

    def run(*args):
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(args)):
            return program(*args)  # traced (`jax.eval_shape`): the whole batch's shapes, nothing run
        return gather(program(*own(args)), out_axis)

    run.lower = lambda *args: program.lower(*own(args))  # what this process compiles
    return run


def run_padded(program, mesh: Mesh, *args):
    """`program` (an `over_batch` one whose arguments are all batched) on a batch of any size n:
    the arguments padded to a multiple of `ways(mesh)` and placed, the outputs' first n rows."""
    n = len(jax.tree.leaves(args)[0])
    return unpad(program(*place(pad(args, padded_size(n, mesh)), mesh)), n)


def place(tree, mesh: Mesh):
    """Put a batch (leading axis a multiple of `ways(mesh)`) split over the mesh's devices; with
    several processes it stays whole (each process's program takes its rows: `over_batch`).

    Calling a program always with inputs placed like this keeps jit's cache to one entry: an
    input laid out differently (e.g. fresh from the host) would compile the program again.
    """
    if jax.process_count() > 1:
        return tree
    return jax.device_put(tree, NamedSharding(mesh, P(AXIS)))
