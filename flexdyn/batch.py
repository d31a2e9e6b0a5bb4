"""Batches of independent runs (payload sweeps, per-log fits) spread over all devices.

A batch is any pytree whose array leaves share a leading axis `B` (one entry per run:
stacked chains, initial states, parameter vectors). `sweep(fn, batch)` evaluates `fn` on
every entry, vectorised with `vmap` on each device and split across the devices of a 1-D
`Mesh` of `jax.devices()` with `shard_map`: the batch is padded to a multiple of the device
count (by repeating its last entry, so the padding is a valid input), each device runs its
share, and the padding is dropped. One device (a laptop, CI) is the plain vmapped call;
several GPUs, or a CPU split with `XLA_FLAGS=--xla_force_host_platform_device_count=N`,
need no code change.

Each device runs its own vmapped program, so an adaptive solver's lockstep (every entry
waits for the slowest, see `vmap` of `diffrax.diffeqsolve`) is per device, not global.
`sharded_vmap(fn, in_axes)` is the same for a function of several arguments, some batched
and some shared (`identify.fit_independent`'s stage steps).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._checks import runtime_check_message
from .chain import AssembledChain, Chain, check_batch

BATCH_AXIS = "batch"

try:  # jax >= 0.6 exports shard_map at the top level (`check_vma`); older ones under experimental
    _shard_map = functools.partial(jax.shard_map, check_vma=False)
except AttributeError:  # pragma: no cover - old jax
    from jax.experimental.shard_map import shard_map as _old_shard_map

    _shard_map = functools.partial(_old_shard_map, check_rep=False)


def batch_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A 1-D mesh (axis `"batch"`) over `devices` (default: all of `jax.devices()`)."""
    devices = jax.devices() if devices is None else list(devices)
    if not devices:
        raise ValueError("batch_mesh: expected at least one device")
    return Mesh(np.array(devices), (BATCH_AXIS,))


def batch_size(batch) -> int:
    """The common leading dimension of the array leaves of `batch`."""
    leaves = jax.tree_util.tree_leaves(batch)
    arrays = [x for x in leaves if eqx.is_array(x)]
    if not arrays:  # (a list of floats: say so, not "got leading sizes []")
        shown = repr(batch) if len(repr(batch)) <= 60 else repr(batch)[:57] + "..."
        raise ValueError(
            f"batch: expected arrays with a leading (batch) dimension, got no array at all ({shown}); "
            "Python numbers are held static: pass jnp.asarray(...), e.g. jnp.asarray([0.1, 0.2, 0.3])"
        )
    if any(jnp.ndim(x) == 0 for x in arrays):
        raise ValueError(
            "batch: every array leaf needs a leading (batch) dimension; got a scalar leaf "
            "(pass values shared by every entry as `shared` arguments instead)"
        )
    sizes = {int(jnp.shape(x)[0]) for x in arrays}
    if len(sizes) != 1:
        raise ValueError(
            f"batch: expected array leaves sharing one leading (batch) dimension, got leading sizes {sorted(sizes)}"
        )
    return sizes.pop()


def pad_batch(batch, multiple: int):
    """`(padded, n)`: the batch padded along its leading axis to a multiple of `multiple` by
    repeating its last entry, and the original size `n`."""
    n = batch_size(batch)
    extra = -n % multiple

    def pad(x):
        if not eqx.is_array(x) or extra == 0:
            return x
        return jnp.concatenate([x, jnp.repeat(x[-1:], extra, axis=0)], axis=0)

    return jax.tree_util.tree_map(pad, batch), n


def unpad_batch(tree, n: int):
    """The first `n` entries of every array leaf (undoes `pad_batch`)."""
    return jax.tree_util.tree_map(lambda x: x[:n] if eqx.is_array(x) else x, tree)


def shard_batch(batch, mesh: Mesh | None = None):
    """`(sharded, n)`: the batch padded to a multiple of the mesh's device count and placed
    with a `NamedSharding` that splits its leading axis over the mesh (a no-op split on one
    device). Feed it to a `jit`ted, `vmap`ped function: XLA partitions the batch. `n` is
    the size before padding (drop the rest with `unpad_batch`)."""
    mesh = batch_mesh() if mesh is None else mesh
    padded, n = pad_batch(batch, mesh.size)
    sharding = NamedSharding(mesh, PartitionSpec(BATCH_AXIS))
    return jax.tree_util.tree_map(lambda x: jax.device_put(x, sharding) if eqx.is_array(x) else x, padded), n


@functools.lru_cache(maxsize=64)
def _sharded_vmap(fn: Callable, mesh: Mesh) -> Callable:
    """`jit(shard_map(vmap(fn)))`: batched first argument split over the mesh, the other
    arguments replicated. Cached per (fn, mesh) so repeated sweeps reuse the compiled program."""
    batched_spec, replicated = PartitionSpec(BATCH_AXIS), PartitionSpec()

    @eqx.filter_jit
    def run(batch, shared):
        dyn_b, static_b = eqx.partition(batch, eqx.is_array)
        dyn_s, static_s = eqx.partition(shared, eqx.is_array)

        def per_device(db, ds):
            s = eqx.combine(ds, static_s)
            f = lambda element: fn(eqx.combine(element, static_b), *s)
            out = jax.vmap(f)(db)
            return out

        in_specs = (
            jax.tree_util.tree_map(lambda _: batched_spec, dyn_b),
            jax.tree_util.tree_map(lambda _: replicated, dyn_s),
        )
        return _shard_map(per_device, mesh=mesh, in_specs=in_specs, out_specs=batched_spec)(dyn_b, dyn_s)

    return run


def sharded_vmap(fn: Callable, in_axes: tuple, mesh: Mesh | None = None) -> Callable:
    """`fn` vmapped over the arguments whose `in_axes` entry is 0 (the others, `None`,
    given to every entry), compiled once, with the batch split over the mesh's devices by
    `shard_map`: each device runs the vmapped program on its share with no communication.
    The batched arguments' leading size must be a multiple of the device count
    (`shard_batch` pads). Non-array leaves of the arguments and of the outputs are held
    static (as `eqx.filter_vmap`); every array output gets a leading batch axis.

    Unlike a vmapped `jit` fed sharded arrays (XLA's automatic partitioning), an adaptive
    solver's loop runs on each device on its own: a device whose entries finish stops, and
    nothing in the loop is replicated across devices (found: `identify.fit_independent` on
    4 forced CPU devices printed 16 XLA "[SPMD] Involuntary full rematerialization"
    warnings from the partitioned stage-step program)."""
    return _vmap_sharded(fn, tuple(in_axes), batch_mesh() if mesh is None else mesh)


@functools.lru_cache(maxsize=64)
def _vmap_sharded(fn: Callable, in_axes: tuple, mesh: Mesh) -> Callable:
    batched, replicated = PartitionSpec(BATCH_AXIS), PartitionSpec()

    @eqx.filter_jit
    def run(*args):
        if len(args) != len(in_axes):
            raise TypeError(f"sharded_vmap: {len(in_axes)} in_axes for {len(args)} arguments")
        dyn, static = eqx.partition(args, eqx.is_array)
        in_specs = tuple(
            jax.tree_util.tree_map(lambda _, ax=ax: batched if ax == 0 else replicated, d)
            for d, ax in zip(dyn, in_axes)
        )
        out_static = []

        def per_device(*d):
            out = eqx.filter_vmap(fn, in_axes=in_axes)(*eqx.combine(d, static))
            out_dyn, out_st = eqx.partition(out, eqx.is_array)
            out_static.append(out_st)
            return out_dyn

        out_dyn = _shard_map(per_device, mesh=mesh, in_specs=in_specs, out_specs=batched)(*dyn)
        return eqx.combine(out_dyn, out_static[0])

    return run


def sweep(fn: Callable, batch, *shared: Any, devices: Sequence[jax.Device] | None = None):
    """`fn` applied to every entry of `batch`, vmapped and sharded over the devices.

    **Arguments:**
    - `fn`: `fn(entry, *shared) -> pytree of arrays`, written for one entry (one chain,
      one initial state, ...). Pass the same function object each time to reuse the
      compiled program.
    - `batch`: pytree whose array leaves have a leading batch axis `B` (non-array leaves
      are held static, as `eqx.filter_jit` does).
    - `shared`: further arguments given to every entry unchanged (replicated on every device).
    - `devices`: the devices to split over (default: all of `jax.devices()`).

    A `Chain` (or `AssembledChain`) in `batch` is checked on the host first: a bad
    parameter is named with its batch entries. Chains built inside `fn` from a batch of
    numbers are checked only inside the computation, where the error cannot say which
    entry (sweep's `RuntimeError` says what failed and this): build them outside
    (`jax.vmap(build)(params)`) to have it named. The call waits for its result.

    Returns the outputs stacked along a leading axis of size `B`, sharded over the devices
    (a `jax.Array`; `np.asarray` gathers it). The same values as `jax.vmap(fn)` up to
    rounding: each device runs the same program on its share.
    """
    for leaf in jax.tree_util.tree_leaves(batch, is_leaf=lambda x: isinstance(x, (Chain, AssembledChain))):
        if isinstance(leaf, (Chain, AssembledChain)):  # a bad entry named, not "must be finite" under vmap
            check_batch(leaf.chain if isinstance(leaf, AssembledChain) else leaf, "sweep")
    mesh = batch_mesh(devices)
    sharded, n = shard_batch(batch, mesh)
    shared = tuple(shared)
    try:
        out = jax.block_until_ready(_sharded_vmap(fn, mesh)(sharded, shared))
    except RuntimeError as e:
        reason = runtime_check_message(e)
        if reason is None:
            raise
        # (inside `fn` under vmap the check cannot say which entry failed)
        raise RuntimeError(
            f"sweep: an entry of the batch failed a check inside fn: {reason}. Under vmap the check cannot "
            "say which entry: build the chains outside fn (chains = jax.vmap(build)(params)) and sweep over "
            "them, and sweep names the bad entries before running"
        ) from e
    return unpad_batch(out, n)
