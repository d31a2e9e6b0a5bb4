"""A jaxpr evaluated one array element at a time, with the constants folded.

`eval_elementwise(closed_jaxpr, *args)` runs the operations of a traced function (e.g. the
right-hand side of a chain for *one* trajectory) on NumPy object arrays whose elements are
scalars: either Python numbers (known when the program is built) or JAX arrays that all
have the same batch shape, one value per trajectory. Every array operation of the jaxpr
(`dot_general`, `reduce_sum`, `pad`, `slice`, ...) becomes the scalar operations it
stands for, written out, so the result is a program of elementwise operations over the
batch only:

- on a GPU, inside one Pallas kernel (`flexdyn.fused`), each thread integrates its own
  trajectory with no array shapes but the batch (the approach of DiffEqGPU's
  `EnsembleGPUKernel`, `../shared/PERFORMANCE.md`);
- with the known constants folded: `0 * x = 0`, `1 * x = x`, `0 + x = x`, products of
  constants computed once. The mass matrix of a chain has many structural zeros and
  constant modal integrals (`AssembledChain`), and the padding, broadcasting and
  one-hot selections of the generic program disappear.

Folding `0 * x` to `0` drops IEEE's `0 * nan = nan`; callers check the state they return
for non-finite values (`flexdyn.fused` does), which a NaN anywhere in it reaches.

Only the primitives that the chain's right-hand sides use are written out; any other one
raises `NotImplementedError` naming it. No control flow (`while`, `scan`, `cond`) may be
inside the traced function; `jit`, `custom_jvp` and `custom_vjp` calls are inlined.
"""

from __future__ import annotations

import itertools
import operator
from collections.abc import Callable

import jax
import jax.extend as jex
import jax.numpy as jnp
import numpy as np

from .smallsolve import refine_rsqrt

__all__ = ["eval_elementwise", "is_constant", "object_array"]

_CONSTANT_TYPES = (bool, int, float, np.bool_, np.integer, np.floating)


def is_constant(x) -> bool:
    """True for a scalar known when the program is built (a Python or NumPy number)."""
    return isinstance(x, _CONSTANT_TYPES)


def object_array(values, shape) -> np.ndarray:
    """A NumPy object array of `shape` holding `values` (an iterable, row-major), element
    by element (no stacking of JAX arrays)."""
    size = int(np.prod(shape, dtype=int))
    out = np.empty(size, dtype=object)
    for i, v in zip(range(size), values):
        out[i] = v
    return out.reshape(shape)


def _const_array(x) -> np.ndarray:
    a = np.asarray(x)
    return object_array((v.item() for v in a.reshape(-1)), a.shape)


# ---------------------------------------------------------------- folded scalar ops


def _add(a, b):
    if is_constant(a):
        if is_constant(b):
            return a + b
        if a == 0:
            return b
    elif is_constant(b) and b == 0:
        return a
    return a + b


def _sub(a, b):
    if is_constant(b):
        if is_constant(a):
            return a - b
        if b == 0:
            return a
    elif is_constant(a) and a == 0:
        return -b
    return a - b


def _mul(a, b):
    if is_constant(a):
        if is_constant(b):
            return a * b
        if a == 0:
            return 0.0
        if a == 1:
            return b
        if a == -1:
            return -b
    elif is_constant(b):
        if b == 0:
            return 0.0
        if b == 1:
            return a
        if b == -1:
            return -a
    return a * b


def _numpy(fn):
    """`fn` on known numbers in float64 with IEEE results (inf, nan), as JAX computes them,
    rather than Python's exceptions (`1.0 / 0.0`, `math.sqrt(-1.0)`) or complex powers."""

    def f(*args):
        with np.errstate(all="ignore"):
            return fn(*(np.float64(a) for a in args)).item()

    return f


_np_divide = _numpy(np.divide)


def _div(a, b):
    if is_constant(b):
        if is_constant(a):
            return _np_divide(a, b)
        if b == 1:
            return a
        return a * _np_divide(1.0, b)
    if is_constant(a) and a == 0:
        return 0.0
    return a / b


def _neg(a):
    return -a


def _integer_pow(a, y: int):
    if is_constant(a):
        return _numpy(lambda b: b**y)(a)
    if y == 0:
        return 1.0
    if y < 0:
        return _div(1.0, _integer_pow(a, -y))
    out = a
    for _ in range(y - 1):
        out = out * a
    return out


def _unary(const_fn, traced_fn):
    def f(a):
        return const_fn(a) if is_constant(a) else traced_fn(a)

    return f


def _binary(const_fn, traced_fn):
    def f(a, b):
        return const_fn(a, b) if (is_constant(a) and is_constant(b)) else traced_fn(a, b)

    return f


def _select(pred, *cases, dtype=None):
    if is_constant(pred):
        return cases[int(pred)]
    if len(cases) != 2:
        raise NotImplementedError("eval_elementwise: select_n with a traced index over more than two cases")
    if is_constant(cases[0]) and is_constant(cases[1]) and cases[0] == cases[1]:
        return cases[0]
    # known cases as strongly typed 0-d arrays of the output's dtype: Pallas's Triton lowering
    # of select_n gives a weakly typed literal case the predicate's type (bool)
    c0, c1 = (np.asarray(c, dtype=dtype) if is_constant(c) else c for c in cases)
    return jnp.where(pred, c1, c0)


def _logical(absorbing: bool, traced):
    """`and` (absorbing False) or `or` (absorbing True), folded when an operand is known:
    a known absorbing value decides the result, a known other value leaves the other operand."""

    def f(a, b):
        for known, other in ((a, b), (b, a)):
            if is_constant(known):
                return absorbing if bool(known) == absorbing else other
        return traced(a, b)

    return f


_and = _logical(False, jnp.logical_and)
_or = _logical(True, jnp.logical_or)


def _convert(a, dtype):
    dtype = np.dtype(dtype)
    if is_constant(a):
        return np.asarray(a).astype(dtype).item()
    return a.astype(dtype) if a.dtype != dtype else a


def _sign(a):
    return jnp.sign(a)


def _rsqrt(a):
    """`lax.rsqrt` to float64 precision anywhere: in a Pallas kernel on a GPU it is the bare
    `rsqrt.approx.f64` (~2^-22: `smallsolve.spd_solve_rsqrt`), so it is refined by one
    Householder step (`smallsolve.refine_rsqrt`; on the CPU, where it is exact, the step
    changes nothing)."""
    return refine_rsqrt(a, jax.lax.rsqrt(a))


_ELEMENTWISE: dict[str, Callable] = {
    "add": _add,
    "add_any": _add,
    "sub": _sub,
    "mul": _mul,
    "div": _div,
    "neg": _neg,
    "max": _binary(_numpy(np.maximum), jnp.maximum),
    "min": _binary(_numpy(np.minimum), jnp.minimum),
    "pow": _binary(_numpy(np.power), jnp.power),
    "atan2": _binary(_numpy(np.arctan2), jnp.arctan2),
    "sin": _unary(_numpy(np.sin), jnp.sin),
    "cos": _unary(_numpy(np.cos), jnp.cos),
    "tan": _unary(_numpy(np.tan), jnp.tan),
    "tanh": _unary(_numpy(np.tanh), jnp.tanh),
    "exp": _unary(_numpy(np.exp), jnp.exp),
    "log": _unary(_numpy(np.log), jnp.log),
    "sqrt": _unary(_numpy(np.sqrt), jnp.sqrt),
    "rsqrt": _unary(_numpy(lambda a: 1.0 / np.sqrt(a)), _rsqrt),
    "abs": _unary(abs, jnp.abs),
    "sign": _unary(_numpy(np.sign), _sign),
    "square": lambda a: _mul(a, a),
    "logistic": _unary(_numpy(lambda a: 1.0 / (1.0 + np.exp(-a))), jax.nn.sigmoid),
    "eq": _binary(operator.eq, operator.eq),
    "ne": _binary(operator.ne, operator.ne),
    "lt": _binary(operator.lt, operator.lt),
    "le": _binary(operator.le, operator.le),
    "gt": _binary(operator.gt, operator.gt),
    "ge": _binary(operator.ge, operator.ge),
    "and": _and,
    "or": _or,
    "not": _unary(operator.not_, jnp.logical_not),
    "select_n": _select,
    "copy": lambda a: a,
    "copy_p": lambda a: a,
}


def _sum(values):
    return _folded(_add)([0.0, *values])


def _map(fn, *arrays):
    shape = np.broadcast_shapes(*(a.shape for a in arrays))
    arrays = [np.broadcast_to(a, shape) for a in arrays]
    return object_array((fn(*xs) for xs in zip(*(a.reshape(-1) for a in arrays))), shape)


# ---------------------------------------------------------------- structural ops


def _pad(x, value, padding_config):
    for axis, (lo, hi, interior) in enumerate(padding_config):
        lo, hi, interior = int(lo), int(hi), int(interior)
        n = x.shape[axis]
        parts = []
        for i in range(n):
            parts.append(np.take(x, [i], axis=axis))
            if interior and i < n - 1:
                shape = list(x.shape)
                shape[axis] = interior
                parts.append(object_array(itertools.repeat(value), shape))
        body = np.concatenate(parts, axis=axis) if parts else np.take(x, [], axis=axis)
        if lo < 0:
            body = np.take(body, range(-lo, body.shape[axis]), axis=axis)
            lo = 0
        if hi < 0:
            body = np.take(body, range(0, body.shape[axis] + hi), axis=axis)
            hi = 0
        pieces = []
        for width in (lo,):
            shape = list(body.shape)
            shape[axis] = width
            pieces.append(object_array(itertools.repeat(value), shape))
        pieces.append(body)
        shape = list(body.shape)
        shape[axis] = hi
        pieces.append(object_array(itertools.repeat(value), shape))
        x = np.concatenate(pieces, axis=axis)
    return x


def _dot_general(a, b, dimension_numbers):
    (ca, cb), (ba, bb) = dimension_numbers
    ca, cb, ba, bb = (tuple(int(i) for i in d) for d in (ca, cb, ba, bb))
    fa = [i for i in range(a.ndim) if i not in ca and i not in ba]
    fb = [i for i in range(b.ndim) if i not in cb and i not in bb]
    at = np.transpose(a, ba + tuple(fa) + ca)
    bt = np.transpose(b, bb + tuple(fb) + cb)
    nb = int(np.prod([a.shape[i] for i in ba], dtype=int))
    na = int(np.prod([a.shape[i] for i in fa], dtype=int))
    nf = int(np.prod([b.shape[i] for i in fb], dtype=int))
    nk = int(np.prod([a.shape[i] for i in ca], dtype=int))
    A = at.reshape(nb, na, nk)
    B = bt.reshape(nb, nf, nk)
    out = object_array(
        (
            _sum(_mul(A[i, j, k], B[i, m, k]) for k in range(nk))
            for i in range(nb)
            for j in range(na)
            for m in range(nf)
        ),
        (nb, na, nf),
    )
    shape = [a.shape[i] for i in ba] + [a.shape[i] for i in fa] + [b.shape[i] for i in fb]
    return out.reshape(shape)


def _gather(x, indices, eqn):
    """`gather` with known indices (e.g. `y[jnp.array([0, 2])]`): which element of `x` each
    output takes is found by applying the same gather to the element numbers of `x`."""
    if not all(is_constant(v) for v in indices.reshape(-1)):
        raise NotImplementedError("eval_elementwise: gather with traced indices")
    index_dtype = eqn.invars[1].aval.dtype
    known = np.array([v for v in indices.reshape(-1)], dtype=index_dtype).reshape(indices.shape)
    params = dict(eqn.params)
    params["fill_value"] = -1.0
    with jax.ensure_compile_time_eval():
        numbers = jnp.arange(x.size, dtype=jnp.float64).reshape(x.shape)
        source = np.asarray(jax.lax.gather_p.bind(numbers, jnp.asarray(known), **params))
    fill = eqn.params.get("fill_value")
    fill = float("nan") if fill is None else fill
    flat = x.reshape(-1)
    return object_array((flat[int(j)] if j >= 0 else fill for j in source.reshape(-1)), source.shape)


def _reduce(fn, x, axes):
    axes = tuple(int(a) for a in axes)
    keep = [i for i in range(x.ndim) if i not in axes]
    xt = np.transpose(x, keep + list(axes))
    shape = [x.shape[i] for i in keep]
    flat = xt.reshape(int(np.prod(shape, dtype=int)), -1)
    return object_array((fn(list(row)) for row in flat), shape)


def _folded(op):
    """A reduction of a list of scalars by the folded binary `op`."""

    def f(values):
        out = values[0]
        for v in values[1:]:
            out = op(out, v)
        return out

    return f


def _call_jaxpr(params):
    for key in ("jaxpr", "call_jaxpr", "fun_jaxpr"):
        if key in params:
            return params[key]
    raise KeyError("no inner jaxpr")


_CALLS = {
    "jit",
    "pjit",
    "closed_call",
    "core_call",
    "remat",
    "checkpoint",
    "custom_jvp_call",
    "custom_vjp_call",
    "custom_vjp_call_jaxpr",
}


def _apply(eqn, invals):
    """The outputs (object arrays) of one equation on object-array inputs."""
    name = eqn.primitive.name
    p = eqn.params
    if name == "select_n":
        dtype = eqn.outvars[0].aval.dtype
        return [_map(lambda *a: _select(*a, dtype=dtype), *invals)]
    if name in _ELEMENTWISE:
        return [_map(_ELEMENTWISE[name], *invals)]
    if name == "integer_pow":
        return [_map(lambda a: _integer_pow(a, int(p["y"])), invals[0])]
    if name == "convert_element_type":
        return [_map(lambda a: _convert(a, p["new_dtype"]), invals[0])]
    if name in _CALLS:
        inner = _call_jaxpr(p)
        if hasattr(inner, "consts"):
            return eval_elementwise(inner, *invals)
        return _eval(inner, [], invals)
    x = invals[0] if invals else None
    if name == "broadcast_in_dim":
        shape, dims = tuple(p["shape"]), tuple(p["broadcast_dimensions"])
        expanded = [1] * len(shape)
        for src, dst in enumerate(dims):
            expanded[dst] = x.shape[src]
        return [np.broadcast_to(x.reshape(expanded), shape).copy()]
    if name == "reshape":
        return [x.reshape(tuple(p["new_sizes"]))]
    if name == "squeeze":
        return [np.squeeze(x, axis=tuple(int(d) for d in p["dimensions"]))]
    if name == "expand_dims":
        return [np.expand_dims(x, tuple(p["dimensions"]))]
    if name == "transpose":
        return [np.transpose(x, tuple(p["permutation"]))]
    if name == "rev":
        return [np.flip(x, axis=tuple(p["dimensions"]))]
    if name == "slice":
        strides = p["strides"] or (1,) * x.ndim
        index = tuple(slice(int(s), int(e), int(k)) for s, e, k in zip(p["start_indices"], p["limit_indices"], strides))
        return [x[index]]
    if name == "dynamic_slice":
        starts = [s.item() if isinstance(s, np.ndarray) else s for s in (i.reshape(()) for i in invals[1:])]
        if not all(is_constant(s) for s in starts):
            raise NotImplementedError("eval_elementwise: dynamic_slice with a traced index")
        index = tuple(
            slice(min(max(int(s), 0), n - k), min(max(int(s), 0), n - k) + k)
            for s, n, k in zip(starts, x.shape, p["slice_sizes"])
        )
        return [x[index]]
    if name == "gather":
        return [_gather(x, invals[1], eqn)]
    if name == "concatenate":
        return [np.concatenate(invals, axis=int(p["dimension"]))]
    if name == "stack":
        return [np.stack(invals, axis=int(p["axis"]))]
    if name == "split":
        sizes = [int(s) for s in p["sizes"]]
        return list(np.split(x, np.cumsum(sizes)[:-1], axis=int(p["axis"])))
    if name == "pad":
        return [_pad(x, invals[1].reshape(()).item(), p["padding_config"])]
    if name == "iota":
        shape, dim = tuple(p["shape"]), int(p["dimension"])
        values = np.broadcast_to(
            np.arange(shape[dim]).reshape([-1 if i == dim else 1 for i in range(len(shape))]), shape
        ).astype(p["dtype"])
        return [_const_array(values)]
    if name == "dot_general":
        return [_dot_general(invals[0], invals[1], p["dimension_numbers"])]
    if name == "reduce_sum":
        return [_reduce(_sum, x, p["axes"])]
    if name == "reduce_max":
        return [_reduce(_folded(_ELEMENTWISE["max"]), x, p["axes"])]
    if name == "reduce_min":
        return [_reduce(_folded(_ELEMENTWISE["min"]), x, p["axes"])]
    if name == "reduce_prod":
        return [_reduce(_folded(_mul), x, p["axes"])]
    raise NotImplementedError(
        f"eval_elementwise: the primitive {name!r} is not written out element by element "
        "(flexdyn.scalarize supports the operations of the chains' right-hand sides)"
    )


def _read(env, v):
    if isinstance(v, jex.core.Literal):
        return _const_array(v.val)
    return env[v]


def _eval(jaxpr, consts, args):
    env = {}
    for var, val in zip(jaxpr.constvars, consts):
        env[var] = val
    for var, val in zip(jaxpr.invars, args):
        if tuple(val.shape) != tuple(var.aval.shape):
            raise ValueError(f"eval_elementwise: argument of shape {val.shape}, expected {var.aval.shape}")
        env[var] = val
    for eqn in jaxpr.eqns:
        outs = _apply(eqn, [_read(env, v) for v in eqn.invars])
        for var, val in zip(eqn.outvars, outs):
            env[var] = val
    return [_read(env, v) for v in jaxpr.outvars]


def eval_elementwise(closed_jaxpr, *args: np.ndarray) -> list[np.ndarray]:
    """Evaluate `closed_jaxpr` on object arrays (module docstring), one per input variable
    and of its shape; returns one object array per output, of the output's shape. The
    jaxpr's own constants are folded in as known numbers."""
    consts = [_const_array(c) for c in closed_jaxpr.consts]
    return _eval(closed_jaxpr.jaxpr, consts, list(args))
