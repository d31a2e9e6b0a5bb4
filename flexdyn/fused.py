"""Batched sweeps with the whole fixed-step integration of each trajectory in one kernel.

`rk4_sweep_final(chains, y0, t0, t1, torque, dt=...)` returns the final state of every
chain of a batch (a payload or hub-inertia sweep, say), integrated with classical RK4 on
the steps of `flexdyn.fixed_step.rk4_final` (cut at the input's jumps, `h <= dt`). It
computes `vmap(rk4_final)` differently:

- **One kernel for all steps** (`backend="pallas"`, the default on a GPU). On a GPU, a
  `vmap`ped `lax.scan` is a loop driven by the host, with ~100 kernel launches per step
  (`benchmarks/bench_gpu_sweep.py`). Here one Pallas (Triton) kernel runs all the steps.
  Each GPU thread holds one trajectory's state for the whole run, as DiffEqGPU's
  `EnsembleGPUKernel` does (`../shared/PERFORMANCE.md`).
- **The right-hand side written out on scalars** (`flexdyn.scalarize`). A thread has no
  8 x 8 matrices. So the right-hand side of one trajectory is traced once and evaluated
  element by element: the mass matrix, velocity terms and forces, and the unrolled
  Cholesky solve of `flexdyn.smallsolve` (in the kernel, `spd_solve_rsqrt`: no float64
  division or square root, each a call into a slow-path subroutine on a GPU). Its array
  operations become scalar multiply-adds over the batch.
  - The assembled scalars of the chain that are the same in every entry are folded in
    as numbers, with every `0 * x` and `1 * x`. These are the `AssembledChain`'s modal
    integrals, masses and stiffnesses.
  - The scalars that differ are read per trajectory: the swept parameters, and what
    depends on them (e.g. the clamped-mass mode shapes of a payload sweep).
  - For paper 004's arm, this leaves ~1,780 scalar operations per right-hand side,
    against ~4,400 counted in the generic program. The rigid pendulum has 174.

`backend="xla"` runs the same scalar program as ordinary JAX operations on `(B,)` arrays,
with one `lax.fori_loop` per piece between jumps. This is the default off a GPU, where
it is faster than `vmap(rk4_final)`. `backend="pallas", interpret=True` runs the kernel
through Pallas's interpreter on any device; it is slow, and meant for tests.

On a GPU the kernel runs one trajectory per thread; each warp runs at the latency of its
own instruction stream (the arm's right-hand side uses all 255 registers of a thread and
spills: `benchmarks/ptxas_fused.py`), so larger batches are nearly free up to ~4 warps
per SM. The call is one dispatch of one jitted program (gather of the varying scalars,
padding, kernel, finiteness check) after the batch's assembly: on a GPU each eager
operation is a launch. Measured times (4,096 of paper 004's arms x 5 s at 1 ms in
~51 ms on an H200): `benchmarks/README.md` and `docs/performance.md`.

Inputs: any whose evaluation is arithmetic on the time and the state, e.g. `BangBang`,
`PDTracking` (state feedback), `ZeroTorque`, or a `FunctionInput` of such formulas. A
`SampledTorque` is not supported: its interpolation searches the sample times, and the
error names the operation.

What this path does not do: saved time series, adaptive steps or gradients. For those
use `rk4_trajectory`, `simulate` or `flexdyn.batch.sweep` of them. The batch is traced
in one piece: with several GPUs, split it with `flexdyn.batch`.

The compiled program is cached on the structure and the folded constants. So a second
sweep over other values of the *same* swept parameters reuses it, while changing a
folded parameter compiles anew.

Checks, each a `ValueError` naming the batch entries (called inside a `jax.jit`, where
the values are not known on the host, `eqx.error_if` raises without naming them):
- every parameter of every entry, before anything is assembled (`chain.check_batch`);
- `dt` against RK4's stability limit of every entry about its initial state, as
  `simulate` checks one chain (`linear.rk4_growth`: one `2n x 2n` eigenproblem per
  entry, a small fraction of the sweep). Above the limit a mode grows from round-off
  and the final state can be finite but wrong;
- every final state finite.
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

from .chain import AssembledChain, Chain, assemble, check_batch
from .fixed_step import input_breaks, input_pieces, vector_field
from .inputs import SampledTorque
from .linear import RK4_MARGIN, rk4_growth
from .scalarize import eval_elementwise, is_constant, object_array
from .simulation import as_input

__all__ = ["rk4_sweep_final"]

_BACKENDS = ("auto", "pallas", "xla")
_SOLVES = ("auto", "unrolled", "rsqrt")
_CACHE_SIZE = 16
_cache: collections.OrderedDict = collections.OrderedDict()


def _segments(torque, t0: float, t1: float, dt: float):
    """(start, step, number of steps, last input time) of each piece between jumps: the
    steps of `rk4_final`."""
    return tuple(input_pieces(input_breaks(torque, t0, t1, caller="rk4_sweep_final"), dt))


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
        """Classical RK4 over every piece. `rows`, `y`: lists of arrays of the batch shape
        (or numbers); `like`: an array of the batch shape, given to every carried value.

        Each step is a loop over the four stages, one right-hand side in its body: a
        program a quarter the size of the stages written out, which Triton compiles
        in seconds rather than minutes. Stage `s` evaluates
        `k_s = f(t + c_s h, y + c_s h k_{s-1})` (`c = 0, 1/2, 1/2, 1`) and accumulates
        `b_s h k_s` (`b = 1/6, 1/3, 1/3, 1/6`): classical RK4, whose Butcher tableau
        has one nonzero `a_{s,s-1} = c_s` per row."""
        dtype = np.dtype(like.dtype).type  # strongly typed constants: see `_select` in scalarize

        def full(v):
            return jnp.zeros_like(like) + v if is_constant(v) else v

        y = [full(v) for v in y]
        for a, h, n, last in self.segments:

            def step(i, y, a=a, h=h, last=last):
                t = a + h * i.astype(like.dtype)

                def stage(s, carry):
                    acc, k = carry
                    c = jnp.where(s == 0, dtype(0.0), jnp.where(s == 3, dtype(1.0), dtype(0.5)))
                    b = jnp.where((s == 0) | (s == 3), dtype(1.0 / 6.0), dtype(1.0 / 3.0))
                    ys = [yi + (c * h) * ki for yi, ki in zip(y, k)]
                    k = [full(v) for v in self.rhs(rows, jnp.minimum(t + c * h, last), ys)]
                    return [ai + (b * h) * ki for ai, ki in zip(acc, k)], k

                acc, _ = jax.lax.fori_loop(0, 4, stage, (list(y), [jnp.zeros_like(like) for _ in y]))
                return acc

            y = jax.lax.fori_loop(0, n, step, y)
        return y


@eqx.filter_jit
def _assembled_scalars(chains, y0, torque, t0: float, dt: float):
    """One program for what a call needs before the kernel: the batch assembled; its array
    leaves flattened to one (B, K) array; the first entry's row (K,) and which of the K
    scalars are the same in every entry (K,); and each entry's RK4 growth factor at `dt`
    (`linear.rk4_growth` about its initial state, > 1: unstable). The input's shape is
    checked when this is traced (once per structure)."""
    asm = eqx.filter_vmap(assemble)(chains)
    n_state = 2 * asm.layout.n_dof
    n_batch = jax.tree_util.tree_leaves(eqx.filter(asm, eqx.is_array))[0].shape[0]
    y0 = jnp.broadcast_to(y0, (n_batch, n_state))
    tau0 = jax.vmap(lambda y: torque(t0, y))(y0)
    if tau0.shape[1:] != (asm.chain.n_links,):
        raise ValueError(
            f"torque: the input returns shape {tau0.shape[1:]}, expected ({asm.chain.n_links},): one torque [N m] "
            f"per joint (e.g. BangBang(amplitude=[...] with {asm.chain.n_links} value(s)))"
        )
    growth = eqx.filter_vmap(lambda a, y, t: rk4_growth(a, y, t, dt / RK4_MARGIN))(asm, y0, tau0)
    dynamic, static = eqx.partition(asm, eqx.is_array)
    leaves = jax.tree_util.tree_leaves(dynamic)
    flat = jnp.concatenate([leaf.reshape(leaf.shape[0], -1) for leaf in leaves], axis=1)
    return flat, flat[0], jnp.all(flat == flat[:1], axis=0), growth, asm


def _columns(first, same) -> tuple:
    """Per assembled scalar: ("const", value) where it is the same in every entry of the
    batch (when the values are concrete), else ("row", k), k numbering the varying ones."""
    if isinstance(first, jax.core.Tracer) or isinstance(same, jax.core.Tracer):
        return tuple(("row", k) for k in range(first.shape[0]))
    columns, k = [], 0
    for value, fixed in zip(first.tolist(), same.tolist()):
        if fixed:
            columns.append(("const", value))
        else:
            columns.append(("row", k))
            k += 1
    return tuple(columns)


def _structure_key(asm, torque, t0, t1, dt, n_state, columns):
    """A hashable key of everything the scalar program depends on but the varying values;
    None if some part is not hashable (then nothing is cached). The batched `asm` has the
    same tree structure and static part as one of its entries."""
    dynamic, static = eqx.partition(asm, eqx.is_array)
    torque_leaves, torque_def = jax.tree_util.tree_flatten(torque)
    if any(isinstance(x, jax.core.Tracer) for x in torque_leaves):
        return None  # a traced input: its values are not known, nothing to key on
    values = jax.device_get([x if eqx.is_array_like(x) else None for x in torque_leaves])
    torque_bytes = tuple(
        (np.asarray(v).dtype.str, np.asarray(v).shape, np.asarray(v).tobytes()) if eqx.is_array_like(x) else x
        for x, v in zip(torque_leaves, values)
    )
    key = (jax.tree_util.tree_structure(dynamic), static, torque_def, torque_bytes, t0, t1, dt, n_state, columns)
    try:
        hash(key)
    except TypeError:
        return None
    return key


def _plan(asm, torque, t0, t1, dt, template_y, columns, solve: str = "unrolled") -> _Plan:
    """The scalar program; `solve`: the mass-matrix solve (`fixed_step.vector_field`),
    `"rsqrt"` in the GPU kernel (no division or square root: `smallsolve.spd_solve_rsqrt`)."""
    dynamic, static = eqx.partition(asm, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dynamic)
    entry = [leaf[0] for leaf in leaves]

    def g(entry_leaves, t, y):
        one = eqx.combine(jax.tree_util.tree_unflatten(treedef, entry_leaves), static)
        return vector_field(one, torque, solve)(t, y)

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


def _pallas_runner(plan: _Plan, block: int, num_warps: int | None, interpret: bool):
    from jax.experimental import pallas as pl

    n_rows_padded = _next_pow2(max(plan.n_rows, 1))
    n_state_padded = _next_pow2(plan.n_state)

    def kernel(p_ref, y_ref, o_ref):
        rows = [p_ref[k, :] for k in range(plan.n_rows)]
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


_NON_FINITE = (
    "rk4_sweep_final: {which} non-finite (NaN/inf): dt is probably above the stability limit "
    "of the stiffest mode or joint (reduce dt), or a parameter is invalid (a NaN or negative mass/stiffness?)"
)


def _program(plan: _Plan, integrate: Callable, block: int | None) -> Callable:
    """The whole sweep as one jitted program of `(flat, y0)`: the varying scalars gathered
    from the assembled `flat` (B, K), the batch padded to whole programs of `block`
    (repeating the last entry: a valid input, dropped afterwards), `integrate(P, Y)` on
    the transposed arrays, and the finiteness check. One dispatch per call: on a GPU each
    eager operation is a launch, so host work around the kernel would cost more than
    the kernel."""
    varying = np.array([j for j, (kind, _) in enumerate(plan.columns) if kind == "row"], dtype=int)

    @jax.jit
    def run(flat, y0):
        n_batch = flat.shape[0]
        Y = jnp.broadcast_to(y0, (n_batch, plan.n_state)).T
        P = flat[:, varying].T if varying.size else jnp.zeros((1, n_batch), Y.dtype)
        n_padded = n_batch if block is None else -(-n_batch // block) * block
        if n_padded != n_batch:
            P = jnp.concatenate([P, jnp.repeat(P[:, -1:], n_padded - n_batch, axis=1)], axis=1)
            Y = jnp.concatenate([Y, jnp.repeat(Y[:, -1:], n_padded - n_batch, axis=1)], axis=1)
        out = integrate(P, Y)[:, :n_batch].T
        return out, ~jnp.all(jnp.isfinite(out), axis=1)

    return run


def _checked_step(flat, growth, dt: float):
    """`flat` if `dt` is within RK4's stability limit of every entry (`linear.rk4_growth`
    about its initial state, with `linear.RK4_MARGIN`, as `simulate` checks one chain).
    Above it a mode grows from round-off and the final state can be finite but wrong
    (no error). Concrete: a `ValueError` naming the entries; traced:
    `eqx.error_if`."""
    message = (
        "rk4_sweep_final: the fixed step dt = {dt:g} s is above RK4's stability limit for the stiffest mode "
        "at y0 of {which} (fd.stable_step(chain, y0, solver='rk4', safety=1.0) gives the limit of one entry; "
        "its default safety, 90 % of it): a mode would "
        "grow from round-off and the result be wrong; reduce dt"
    )
    unstable = growth > 1.0 + 1e-9
    if isinstance(growth, jax.core.Tracer):
        return eqx.error_if(flat, jnp.any(unstable), message.format(dt=dt, which="an entry of the batch"))
    bad = np.flatnonzero(np.asarray(unstable))
    if bad.size:
        raise ValueError(message.format(dt=dt, which=_entries(bad, growth.shape[0])))
    return flat


def _entries(bad: np.ndarray, total: int) -> str:
    """ "batch entries 3, 17 (of 4096)": the first ten indices of `bad`."""
    shown = ", ".join(str(k) for k in bad[:10]) + (f", ... ({bad.size} in all)" if bad.size > 10 else "")
    return f"batch entr{'y' if bad.size == 1 else 'ies'} {shown} (of {total})"


def _checked(out, bad):
    """`out` if every entry is finite. Concrete: a `ValueError` naming the entries (one
    transfer of B booleans); traced (inside the caller's `jit`): `eqx.error_if`, which
    cannot name them."""
    if isinstance(bad, jax.core.Tracer):
        return eqx.error_if(out, jnp.any(bad), _NON_FINITE.format(which="a final state is"))
    bad = np.flatnonzero(np.asarray(bad))
    if bad.size:
        raise ValueError(_NON_FINITE.format(which=f"the final state of {_entries(bad, out.shape[0])} is"))
    return out


def _runner(key, make_plan: Callable[[], _Plan], backend, block, num_warps, interpret) -> Callable:
    key = None if key is None else (key, backend, block, num_warps, interpret)
    if key is not None and key in _cache:
        _cache.move_to_end(key)
        return _cache[key]
    plan = make_plan()
    if backend == "xla":
        run = _program(plan, _xla_runner(plan), None)
    else:
        run = _program(plan, _pallas_runner(plan, block, num_warps, interpret), block)
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
    block: int = 32,
    num_warps: int | None = 1,
    interpret: bool = False,
    solve: str = "auto",
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
      program (`None`: Triton's default). The defaults, one warp of 32 threads with one
      trajectory each, are the configuration measured (`docs/performance.md`).
    - `solve`: the mass-matrix solve of the scalar program, `"unrolled"`
      (`smallsolve.spd_solve`), `"rsqrt"` (`smallsolve.spd_solve_rsqrt`: no division or
      square root) or `"auto"` (rsqrt in the Pallas kernel, unrolled on XLA: on a CPU
      the divisions are the faster).

    Raises `NotImplementedError` naming the operation when the chain's or the input's
    right-hand side uses one that `flexdyn.scalarize` does not write out (e.g. the
    interpolation of a `SampledTorque`); use `jax.vmap` of `fixed_step.rk4_final` there.
    """
    t0, t1, dt = float(t0), float(t1), float(dt)
    if not (dt > 0 and math.isfinite(dt)):
        raise ValueError(f"rk4_sweep_final: dt expected a step > 0 s, got {dt!r}")
    if not t1 > t0:
        raise ValueError(f"rk4_sweep_final: expected t1 > t0, got t0={t0!r}, t1={t1!r}")
    if backend not in _BACKENDS:
        raise ValueError(f"rk4_sweep_final: backend expected one of {_BACKENDS}, got {backend!r}")
    if solve not in _SOLVES:
        raise ValueError(f"rk4_sweep_final: solve expected one of {_SOLVES}, got {solve!r}")
    block = int(block)
    if block < 1 or block & (block - 1):
        raise ValueError(f"rk4_sweep_final: block expected a power of 2, got {block!r}")
    if backend == "auto":
        backend = "pallas" if jax.default_backend() == "gpu" else "xla"
    if solve == "auto":
        solve = "unrolled" if backend == "xla" else "rsqrt"
    leaves = [leaf for leaf in jax.tree_util.tree_leaves(eqx.filter(chains, eqx.is_array))]
    if not leaves or any(leaf.ndim == 0 for leaf in leaves):
        raise ValueError(
            "rk4_sweep_final: chains expected a batch (every array leaf with a leading batch axis, "
            "e.g. jax.vmap(build)(params)); got a single chain (use rk4_final)"
        )
    n_batch = int(leaves[0].shape[0])
    if any(int(leaf.shape[0]) != n_batch for leaf in leaves):
        raise ValueError("rk4_sweep_final: the chains' array leaves have different leading (batch) sizes")
    chain = chains.chain if isinstance(chains, AssembledChain) else chains
    check_batch(chain, "rk4_sweep_final")
    torque = as_input(torque, chain.n_links)
    n_state = 2 * chain.layout.n_dof
    y0 = jnp.asarray(y0, dtype=jnp.result_type(float))
    if y0.shape not in ((n_state,), (n_batch, n_state)):
        raise ValueError(
            f"rk4_sweep_final: y0 expected shape ({n_state},) or ({n_batch}, {n_state}) = [Q, Q_dot] "
            f"with Q = {list(chain.layout.names)}, got {tuple(y0.shape)}"
        )
    flat, first, same, growth, asm = _assembled_scalars(chains, y0, torque, t0, dt)
    if not isinstance(first, jax.core.Tracer):
        first, same, growth = jax.device_get((first, same, growth))  # one transfer
    flat = _checked_step(flat, growth, dt)
    columns = _columns(first, same)
    key = _structure_key(asm, torque, t0, t1, dt, n_state, columns)

    def make_plan():  # on a cache miss only
        return _plan(asm, torque, t0, t1, dt, jnp.zeros((n_state,), y0.dtype), columns, solve)

    try:
        run = _runner(None if key is None else (key, solve), make_plan, backend, block, num_warps, interpret)
        out, bad = run(flat, y0)
    except NotImplementedError as e:
        what = (
            f"the input ({type(torque).__name__}: its interpolation searches the sample times) has no scalar form ({e})"
            if isinstance(torque, SampledTorque)
            else str(e)
        )
        raise NotImplementedError(
            f"rk4_sweep_final: {what}. Use jax.vmap of flexdyn.fixed_step.rk4_final for this chain and input"
        ) from e
    return _checked(out, bad)
