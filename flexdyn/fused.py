"""Batched sweeps with the whole fixed-step integration of each trajectory in one kernel.

`rk4_sweep_final(chains, y0, t0, t1, torque, dt=...)` returns the final state of every
chain of a batch (a payload or hub-inertia sweep, say), integrated with classical RK4 on
the steps of `flexdyn.fixed_step.rk4_final` (cut at the input's jumps, `h <= dt`). It is
`vmap(rk4_final)` computed differently:

- **One kernel for all steps** (`backend="pallas"`, the default on a GPU). A `vmap`ped
  `lax.scan` runs on a GPU as a host-driven loop of ~100 kernel launches per step (XLA
  cannot fuse the right-hand side of a generic chain into one); measured on an H200,
  4,096 trajectories x 5,000 steps took 24 s, ~5 ms per step, 1/2000 of the float64
  FLOP bound (`benchmarks/bench_gpu_sweep.py`). Here a single Pallas (Triton) kernel
  integrates all steps: each GPU thread holds one trajectory's state in registers for
  the whole run, as DiffEqGPU's `EnsembleGPUKernel` does (`../shared/PERFORMANCE.md`).
- **The right-hand side written out on scalars** (`flexdyn.scalarize`). A thread has no
  8 x 8 matrices, so the right-hand side of one trajectory (mass matrix, velocity terms,
  forces, the unrolled Cholesky solve of `flexdyn.smallsolve`) is traced once and
  evaluated element by element, its array operations becoming scalar multiply-adds over
  the batch. The chain's assembled constants (`AssembledChain`: modal integrals, masses,
  stiffnesses) that are the same in every entry of the batch are folded in as numbers,
  with every `0 * x` and `1 * x`; those that differ (the swept ones, and what depends on
  them, e.g. the clamped-mass mode shapes of a payload sweep) are read per trajectory.
  For paper 004's arm this leaves ~1,800 scalar operations per right-hand side, against
  ~5,400 counted in the generic program.

`backend="xla"` runs the same scalar program as ordinary JAX operations on `(B,)`
arrays (one `lax.fori_loop` per piece between jumps); `backend="pallas", interpret=True`
runs the kernel through Pallas's interpreter on any device (slow: for tests).

What this path does not do: saved time series, adaptive steps or gradients (use
`rk4_trajectory`, `simulate` or `flexdyn.batch.sweep` of them). The batch is traced in
one piece: with several GPUs, split it with `flexdyn.batch`. The compiled kernel is cached
on the structure and the folded constants, so a second sweep over other values of the
*same* swept parameters reuses it, while changing a folded parameter compiles anew.

Raises if any final state is non-finite (a step above the stability limit of the
stiffest mode, or an invalid parameter), as `rk4_final` does.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .chain import AssembledChain, Chain, assemble
from .fixed_step import _breaks, vector_field
from .scalarize import eval_elementwise, is_constant, object_array
from .simulate import _check_torque_shape, as_input

__all__ = ["rk4_sweep_final"]

_BACKENDS = ("auto", "pallas", "xla")
_CACHE_SIZE = 16
_cache: collections.OrderedDict = collections.OrderedDict()


def _segments(torque, t0: float, t1: float, dt: float):
    """(start, step, number of steps, last input time) of each piece between jumps."""
    breaks = _breaks(torque, t0, t1, caller="rk4_sweep_final")
    out = []
    for a, b in zip(breaks[:-1], breaks[1:]):
        n = max(1, math.ceil((b - a) / dt - 1e-9))
        out.append((a, (b - a) / n, n, float(np.nextafter(b, a))))
    return tuple(out)


def _next_pow2(n: int) -> int:
    return 1 if n <= 1 else 2 ** math.ceil(math.log2(n))


@dataclasses.dataclass(frozen=True)
class _Plan:
    """What the scalar program needs to know, fixed when it is built: the traced
    right-hand side of one entry, which assembled scalars are folded (and their values),
    and the pieces of the step table."""

    jaxpr: object
    leaf_shapes: tuple
    columns: tuple  # per scalar: ("const", value) or ("row", k)
    n_rows: int
    n_state: int
    segments: tuple

    def rhs(self, rows, t, y):
        """`[Q_dot, Q_ddot]` (a list of scalars) from the swept rows, time and state lists."""
        args, i = [], 0
        for shape in self.leaf_shapes:
            size = int(np.prod(shape, dtype=int))
            vals = []
            for kind, v in self.columns[i : i + size]:
                vals.append(v if kind == "const" else rows[v])
            args.append(object_array(vals, shape))
            i += size
        args.append(object_array([t], ()))
        args.append(object_array(y, (self.n_state,)))
        (out,) = eval_elementwise(self.jaxpr, *args)
        return list(out)

    def integrate(self, rows, y, like):
        """Classical RK4 over every piece; `rows`, `y`: lists of arrays of the batch shape
        (or numbers); `like`: an array of the batch shape, to give every carried value it."""
        from .scalarize import _add, _mul

        def lin(y, k, c):
            return [_add(a, _mul(c, b)) for a, b in zip(y, k)]

        def full(v):
            return jnp.zeros_like(like) + v if is_constant(v) else v

        y = [full(v) for v in y]
        for a, h, n, last in self.segments:

            def step(i, y, a=a, h=h, last=last):
                t = a + h * i.astype(like.dtype)
                k1 = self.rhs(rows, jnp.minimum(t, last), y)
                k2 = self.rhs(rows, jnp.minimum(t + 0.5 * h, last), lin(y, k1, 0.5 * h))
                k3 = self.rhs(rows, jnp.minimum(t + 0.5 * h, last), lin(y, k2, 0.5 * h))
                k4 = self.rhs(rows, jnp.minimum(t + h, last), lin(y, k3, h))
                out = []
                for yi, a1, a2, a3, a4 in zip(y, k1, k2, k3, k4):
                    incr = _add(_add(a1, _mul(2.0, a2)), _add(_mul(2.0, a3), a4))
                    out.append(full(_add(yi, _mul(h / 6.0, incr))))
                return out

            y = jax.lax.fori_loop(0, n, step, y)
        return y


@eqx.filter_jit
def _assembled_scalars(chains):
    """The batch assembled, and its array leaves flattened to one (B, K) array."""
    asm = eqx.filter_vmap(assemble)(chains)
    dynamic, static = eqx.partition(asm, eqx.is_array)
    leaves = jax.tree_util.tree_leaves(dynamic)
    flat = jnp.concatenate([leaf.reshape(leaf.shape[0], -1) for leaf in leaves], axis=1)
    return flat, asm


def _columns(flat) -> tuple:
    """Per assembled scalar: ("const", value) where it is the same in every entry of the
    batch (when the values are concrete), else ("row", k), k numbering the varying ones."""
    try:
        values = np.asarray(flat)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return tuple(("row", k) for k in range(flat.shape[1]))
    same = np.all(values == values[:1], axis=0)
    columns, k = [], 0
    for j in range(values.shape[1]):
        if same[j]:
            columns.append(("const", float(values[0, j])))
        else:
            columns.append(("row", k))
            k += 1
    return tuple(columns)


def _structure_key(asm, torque, t0, t1, dt, n_state, columns):
    """A hashable key of everything the scalar program depends on but the varying values;
    None if some part is not hashable (then nothing is cached)."""
    one = jax.tree_util.tree_map(lambda x: x[0] if eqx.is_array(x) else x, asm)
    dynamic, static = eqx.partition(one, eqx.is_array)
    torque_leaves, torque_def = jax.tree_util.tree_flatten(torque)
    torque_bytes = tuple(
        (np.asarray(x).dtype.str, np.asarray(x).shape, np.asarray(x).tobytes()) if eqx.is_array_like(x) else x
        for x in torque_leaves
    )
    key = (jax.tree_util.tree_structure(dynamic), static, torque_def, torque_bytes, t0, t1, dt, n_state, columns)
    try:
        hash(key)
    except TypeError:
        return None
    return key


def _plan(asm, torque, t0, t1, dt, template_y, columns) -> _Plan:
    dynamic, static = eqx.partition(asm, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dynamic)
    entry = [leaf[0] for leaf in leaves]

    def g(entry_leaves, t, y):
        one = eqx.combine(jax.tree_util.tree_unflatten(treedef, entry_leaves), static)
        return vector_field(one, torque)(t, y)

    return _Plan(
        jaxpr=jax.make_jaxpr(g)(entry, jnp.asarray(float(t0)), template_y),
        leaf_shapes=tuple(tuple(leaf.shape[1:]) for leaf in leaves),
        columns=columns,
        n_rows=sum(1 for kind, _ in columns if kind == "row"),
        n_state=int(template_y.shape[0]),
        segments=_segments(torque, t0, t1, dt),
    )


def _xla_runner(plan: _Plan):
    @jax.jit
    def run(P, Y):
        rows = [P[k] for k in range(plan.n_rows)]
        y = [Y[i] for i in range(plan.n_state)]
        return jnp.stack(plan.integrate(rows, y, Y[0]))

    return run


class _RowsFromRef:
    """The swept scalars of one program's trajectories, loaded from the kernel's input where
    each right-hand side uses them (not held in registers across the loop)."""

    def __init__(self, ref):
        self.ref = ref

    def __getitem__(self, k):
        return self.ref[k, :]


def _pallas_runner(plan: _Plan, block: int, num_warps: int | None, interpret: bool, reload: bool):
    from jax.experimental import pallas as pl

    n_rows_padded = _next_pow2(max(plan.n_rows, 1))
    n_state_padded = _next_pow2(plan.n_state)

    def kernel(p_ref, y_ref, o_ref):
        rows = _RowsFromRef(p_ref) if reload else [p_ref[k, :] for k in range(plan.n_rows)]
        y = [y_ref[i, :] for i in range(plan.n_state)]
        out = plan.integrate(rows, y, y[0])
        for i in range(plan.n_state):
            o_ref[i, :] = out[i]

    compiler_params = None
    if not interpret:
        from jax.experimental.pallas import triton as pltriton

        compiler_params = pltriton.CompilerParams(num_warps=num_warps, num_stages=1)

    @jax.jit
    def run(P, Y):
        n = Y.shape[1]
        P = jnp.pad(P, ((0, n_rows_padded - P.shape[0]), (0, 0)))
        Y = jnp.pad(Y, ((0, n_state_padded - Y.shape[0]), (0, 0)))
        out = pl.pallas_call(
            kernel,
            out_shape=jax.ShapeDtypeStruct((n_state_padded, n), Y.dtype),
            grid=(n // block,),
            in_specs=[
                pl.BlockSpec((n_rows_padded, block), lambda i: (0, i)),
                pl.BlockSpec((n_state_padded, block), lambda i: (0, i)),
            ],
            out_specs=pl.BlockSpec((n_state_padded, block), lambda i: (0, i)),
            interpret=interpret,
            compiler_params=compiler_params,
        )(P, Y)
        return out[: plan.n_state]

    return run


def _runner(key, make_plan: Callable[[], _Plan], backend, block, num_warps, interpret, reload) -> Callable:
    key = None if key is None else (key, backend, block, num_warps, interpret, reload)
    if key is not None and key in _cache:
        _cache.move_to_end(key)
        return _cache[key]
    plan = make_plan()
    run = _xla_runner(plan) if backend == "xla" else _pallas_runner(plan, block, num_warps, interpret, reload)
    if key is not None:
        _cache[key] = run
        while len(_cache) > _CACHE_SIZE:
            _cache.popitem(last=False)
    return run


def rk4_sweep_final(
    chains: Chain | AssembledChain,
    y0: Float[Array, "... 2n"],
    t0: float,
    t1: float,
    torque,
    *,
    dt: float,
    backend: str = "auto",
    block: int = 64,
    num_warps: int | None = None,
    interpret: bool = False,
    reload: bool = False,
) -> Float[Array, "B 2n"]:
    """Final states `[Q, Q_dot]` (B, 2n) at `t1` (s) of a batch of chains from `y0` at
    `t0`, by classical RK4 with steps of at most `dt` (s) between the input's jumps (module
    docstring).

    **Arguments:**
    - `chains`: a batch of chains of one structure (array leaves with a leading axis `B`,
      e.g. `jax.vmap(build)(params)` or `flexdyn.batch` stacking), assembled or not.
    - `y0`: one initial state (2n,) for all, or one per chain (B, 2n).
    - `t0`, `t1`, `dt`: Python floats (they fix the loop lengths); `torque`: an input
      (`flexdyn.inputs`, shared by the batch) whose jump times are concrete.
    - `backend`: `"pallas"` (one kernel, GPU; `interpret=True` anywhere), `"xla"`, or
      `"auto"` (pallas on a GPU, else xla).
    - `block`: trajectories per GPU program (a power of 2); `num_warps`: Triton warps per
      program (default: Triton's); `reload`: read the swept scalars from memory at each
      right-hand side instead of holding them in registers for the whole run.
    """
    t0, t1, dt = float(t0), float(t1), float(dt)
    if not (dt > 0 and math.isfinite(dt)):
        raise ValueError(f"rk4_sweep_final: dt expected a step > 0 s, got {dt!r}")
    if not t1 > t0:
        raise ValueError(f"rk4_sweep_final: expected t1 > t0, got t0={t0!r}, t1={t1!r}")
    if backend not in _BACKENDS:
        raise ValueError(f"rk4_sweep_final: backend expected one of {_BACKENDS}, got {backend!r}")
    block = int(block)
    if block < 1 or block & (block - 1):
        raise ValueError(f"rk4_sweep_final: block expected a power of 2, got {block!r}")
    if backend == "auto":
        backend = "pallas" if jax.default_backend() == "gpu" else "xla"
    leaves = [leaf for leaf in jax.tree_util.tree_leaves(eqx.filter(chains, eqx.is_array))]
    if not leaves or any(leaf.ndim == 0 for leaf in leaves):
        raise ValueError(
            "rk4_sweep_final: chains expected a batch (every array leaf with a leading batch axis, "
            "e.g. jax.vmap(build)(params)); got a single chain (use rk4_final)"
        )
    n_batch = int(leaves[0].shape[0])
    if any(int(leaf.shape[0]) != n_batch for leaf in leaves):
        raise ValueError("rk4_sweep_final: the chains' array leaves have different leading (batch) sizes")
    flat, asm = _assembled_scalars(chains)
    one = jax.tree_util.tree_map(lambda x: x[0] if eqx.is_array(x) else x, asm)
    torque = as_input(torque, one.chain.n_links)
    n_state = 2 * one.layout.n_dof
    y0 = jnp.asarray(y0, dtype=jnp.result_type(float))
    if y0.shape == (n_state,):
        y0 = jnp.broadcast_to(y0, (n_batch, n_state))
    if y0.shape != (n_batch, n_state):
        raise ValueError(
            f"rk4_sweep_final: y0 expected shape ({n_state},) or ({n_batch}, {n_state}) = [Q, Q_dot] "
            f"with Q = {list(one.layout.names)}, got {tuple(y0.shape)}"
        )
    _check_torque_shape(torque, t0, y0[0], one.chain.n_links)
    columns = _columns(flat)
    key = _structure_key(asm, torque, t0, t1, dt, n_state, columns)
    run = _runner(
        key, lambda: _plan(asm, torque, t0, t1, dt, y0[0], columns), backend, block, num_warps, interpret, reload
    )
    varying = np.array([j for j, (kind, _) in enumerate(columns) if kind == "row"], dtype=int)
    P = flat[:, varying].T if varying.size else jnp.zeros((1, n_batch), y0.dtype)
    n_padded = -(-n_batch // block) * block if backend == "pallas" else n_batch
    Y = y0.T
    if n_padded != n_batch:  # repeat the last entry: a valid input, dropped afterwards
        P = jnp.concatenate([P, jnp.repeat(P[:, -1:], n_padded - n_batch, axis=1)], axis=1)
        Y = jnp.concatenate([Y, jnp.repeat(Y[:, -1:], n_padded - n_batch, axis=1)], axis=1)
    out = run(P, Y)[:, :n_batch].T
    return eqx.error_if(
        out,
        ~jnp.all(jnp.isfinite(out)),
        "rk4_sweep_final: a final state is non-finite (NaN/inf): dt is probably above the stability limit "
        "of the stiffest mode or joint (reduce dt), or a parameter is invalid (a NaN or negative mass/stiffness?)",
    )
