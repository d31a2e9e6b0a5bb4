"""Tests of `flexdyn.scalarize` (a jaxpr evaluated one array element at a time).

Oracle: JAX's own evaluation of the same function, `vmap`ped over the batch that the
scalar program carries in each element. Folding is checked by counting the operations of
the scalar program.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from flexdyn.scalarize import eval_elementwise, is_constant, object_array

B = 5  # the batch that every traced element carries


def _scalarized(fn, *examples, constant=()):
    """`fn` evaluated by `eval_elementwise` on a batch: returns (batched outputs, oracle).
    Arguments whose index is in `constant` are passed as known numbers (entry 0)."""
    rng = np.random.default_rng(0)
    batch = [rng.uniform(0.5, 1.5, size=(B, *np.shape(x))) for x in examples]
    for i in constant:
        batch[i] = np.broadcast_to(batch[i][:1], batch[i].shape).copy()
    jaxpr = jax.make_jaxpr(fn)(*examples)
    args = []
    for i, x in enumerate(batch):
        shape = x.shape[1:]
        if i in constant:
            args.append(object_array((float(v) for v in x[0].reshape(-1)), shape))
        else:
            flat = x.reshape(B, -1)
            args.append(object_array((jnp.asarray(flat[:, j]) for j in range(flat.shape[1])), shape))
    outs = eval_elementwise(jaxpr, *args)
    got = []
    for out in outs:
        cols = [np.broadcast_to(np.asarray(v, dtype=float), (B,)) for v in out.reshape(-1)]
        got.append(np.stack(cols, axis=-1).reshape(B, *out.shape) if cols else np.zeros((B, *out.shape)))
    want = jax.vmap(fn)(*(jnp.asarray(x) for x in batch))
    want = [np.asarray(w) for w in (want if isinstance(want, (tuple, list)) else [want])]
    return got, want


CASES = {
    "dot_general with batch and contracting dims": (
        lambda a, b: lax.dot_general(a, b, (((2,), (1,)), ((0,), (0,)))),
        (np.ones((2, 3, 4)), np.ones((2, 4, 3))),
    ),
    "matmul, transpose, sum": (lambda a, b: jnp.sum(a @ b.T, axis=0), (np.ones((3, 4)), np.ones((2, 4)))),
    "pad: low, high, interior, negative": (
        lambda x: lax.pad(x, 0.5, ((1, -1, 2), (-1, 2, 0))),
        (np.ones((3, 4)),),
    ),
    "broadcast, reshape, squeeze, expand_dims": (
        lambda x: jnp.expand_dims(jnp.broadcast_to(x.reshape(2, 1, 3), (2, 4, 3)).sum(1), 0).squeeze(0),
        (np.ones(6),),
    ),
    "slice with strides, rev, concatenate": (
        lambda x: jnp.concatenate([x[1::2], x[::-1], x[:0]]),
        (np.ones(7),),
    ),
    "split, stack, iota": (
        lambda x: jnp.stack(jnp.split(x, [2, 5])[1:2] * 2) * jnp.arange(3.0),
        (np.ones(6),),
    ),
    "reductions": (
        lambda x: jnp.stack([x.max(0), x.min(0), x.prod(0), x.sum(0)]),
        (np.ones((3, 2)),),
    ),
    "integer powers": (lambda x: jnp.stack([x**2, x**3, x**-2, x**0, jnp.square(x)]), (np.ones(2),)),
    "transcendentals and binary": (
        lambda x, y: jnp.stack(
            [
                jnp.sin(x),
                jnp.cos(x),
                jnp.tan(x),
                jnp.tanh(x),
                jnp.exp(x),
                jnp.log(x),
                jnp.sqrt(x),
                lax.rsqrt(x),
                jnp.arctan2(x, y),
                x**y,
                jnp.maximum(x, y),
                jnp.minimum(x, y),
                x / y,
                -x,
                jnp.abs(x - y),
                jnp.sign(x - y),
                jax.nn.sigmoid(x),
            ]
        ),
        (np.ones(3), np.ones(3)),
    ),
    "comparisons, logic, select, convert": (
        lambda x, y: (
            jnp.where((x > y) & ~(x == y) | (x <= 0.7), x, y * 2.0)
            + (x >= y).astype(float)
            + jnp.where(x < y, 1.0, 0.0)
            + jnp.where(x != y, x, 3.0)
        ),
        (np.ones(4), np.ones(4)),
    ),
    "gather with known indices": (
        lambda x: x[jnp.array([2, 0, 2])] + x.reshape(2, 2)[:, jnp.array([1, 0, 1])].sum(0),
        (np.ones(4),),
    ),
    "jit and custom_jvp inlined, dynamic_slice with constant index": (
        lambda x: jax.jit(lambda z: jax.nn.relu(z - 1.0))(x) + lax.dynamic_slice(x, (1,), (3,)).sum(),
        (np.ones(4),),
    ),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_matches_jax(name):
    fn, examples = CASES[name]
    got, want = _scalarized(fn, *examples)
    assert len(got) == len(want)
    for g, w in zip(got, want):
        np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("name", ["dot_general with batch and contracting dims", "transcendentals and binary"])
def test_matches_jax_with_known_arguments(name):
    # The first argument known (a number per element): folded, the result unchanged.
    fn, examples = CASES[name]
    got, want = _scalarized(fn, *examples, constant=(0,))
    for g, w in zip(got, want):
        np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-13)


def _count_operations(fn, example, known):
    """Operations of the scalar program of `fn(known, x)` with `known` folded in."""
    jaxpr = jax.make_jaxpr(fn)(jnp.asarray(known), example)

    def scalar_program(xs):
        k = object_array((float(v) for v in np.ravel(known)), np.shape(known))
        x = object_array(xs, example.shape)
        return list(eval_elementwise(jaxpr, k, x)[0].reshape(-1))

    traced = jax.make_jaxpr(scalar_program)([jnp.zeros(B) for _ in range(example.size)])
    return len(traced.jaxpr.eqns), traced


def test_constants_folded():
    # A diagonal known matrix times a vector: n multiplications, no additions, no zeros.
    n = 6
    diag = np.diag(np.arange(2.0, 2.0 + n))
    count, _ = _count_operations(lambda M, x: M @ x, jnp.ones(n), diag)
    assert count == n
    # The identity, ones and zeros cost nothing: M @ x + 0 * x with M = I is x itself.
    count, traced = _count_operations(lambda M, x: M @ x + 0.0 * x, jnp.ones(n), np.eye(n))
    assert count == 0
    # Without folding, the generic program would do n^2 multiplications and n (n - 1) additions.


def test_known_numbers_follow_ieee():
    # Folded arithmetic on known numbers gives inf / nan as JAX would, not Python's exceptions.
    def fn(k, x):
        return jnp.stack([x / k[0], jnp.sqrt(k[1]) + x, jnp.log(k[0]) * x, k[1] ** 0.5 + x, 1.0 / k[0] + x])

    jaxpr = jax.make_jaxpr(fn)(jnp.ones(2), 1.0)
    (out,) = eval_elementwise(jaxpr, object_array([0.0, -1.0], (2,)), object_array([jnp.ones(B)], ()))
    got = np.stack([np.broadcast_to(np.asarray(v, dtype=float), (B,)) for v in out])
    with np.errstate(all="ignore"):
        want = np.asarray(fn(np.array([0.0, -1.0]), np.ones(B)))
    np.testing.assert_array_equal(got, want)


def test_unsupported_primitive_named():
    jaxpr = jax.make_jaxpr(lambda x: jnp.cumsum(x))(jnp.ones(3))
    with pytest.raises(NotImplementedError, match="cumsum"):
        eval_elementwise(jaxpr, object_array([jnp.ones(B)] * 3, (3,)))


def test_argument_shape_checked():
    jaxpr = jax.make_jaxpr(lambda x: x * 2.0)(jnp.ones(3))
    with pytest.raises(ValueError, match=r"shape \(2,\), expected \(3,\)"):
        eval_elementwise(jaxpr, object_array([1.0, 2.0], (2,)))


def test_is_constant():
    assert is_constant(1.0) and is_constant(2) and is_constant(True) and is_constant(np.float64(1.0))
    assert not is_constant(jnp.ones(B))


def test_a_reciprocal_square_root_is_refined_to_float64(monkeypatch):
    """In a Pallas kernel on a GPU, a float64 `lax.rsqrt` is a bare hardware approximation
    (`flexdyn.smallsolve.spd_solve_rsqrt`); the scalar program refines every one by a
    Householder step. Here `lax.rsqrt` is made 2^-22 wrong (relative) during the scalar
    evaluation: the program's result is still `1 / sqrt(x)` to 2 ulp (unrefined it would be
    off by ~2.4e-7)."""
    import flexdyn.scalarize as sc

    x = np.logspace(-200, 200, 41)
    jaxpr = jax.make_jaxpr(lambda v: lax.rsqrt(v))(np.ones(()))
    exact = jax.lax.rsqrt
    monkeypatch.setattr(sc.jax.lax, "rsqrt", lambda a: exact(a) * (1.0 + 2.0**-22))
    (out,) = eval_elementwise(jaxpr, object_array([jnp.asarray(x)], ()))
    got = np.asarray(out.item())
    np.testing.assert_allclose(got, 1.0 / np.sqrt(x), rtol=2 * np.finfo(float).eps, atol=0.0)
