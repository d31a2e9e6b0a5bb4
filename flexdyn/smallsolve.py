"""Solving the small symmetric positive-definite systems of the equations of motion.

`spd_solve(M, b)` solves `M x = b` for the generalised mass matrix `M` (n x n, n = the
chain's degrees of freedom, static). For small n it is a Cholesky factorisation written
out entry by entry (`M = L L^T`, then forward and back substitution):

    L_jj = sqrt(M_jj - sum_{k<j} L_jk^2),   L_ij = (M_ij - sum_{k<j} L_ik L_jk) / L_jj  (i > j)

about n^3/6 + n^2 multiply-adds on scalars, with no call into LAPACK / cuSOLVER. Under
`vmap` every one of these is an elementwise operation over the batch, which XLA fuses
with the rest of the right-hand side into a few kernels; a batched `cho_factor` is a
library call per right-hand side instead (a loop of tiny LAPACK calls on the CPU, several
kernel launches on a GPU), which dominated batched sweeps (`docs/performance.md`). Above
`UNROLL_MAX_DOF` the unrolled program grows as n^3 and compiles slowly, so larger systems
use `jax.scipy.linalg.cho_solve`. No pivoting is needed: `M` is symmetric positive
definite (it is the Hessian of the kinetic energy in the velocities).
"""

from __future__ import annotations

import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jax import lax
from jaxtyping import Array, Float

UNROLL_MAX_DOF = 12


def cholesky_unrolled(M: Float[Array, "n n"], rsqrt: bool = False) -> tuple[list[list], list]:
    """Lower Cholesky factor of `M` as a nested list of scalars, `L[i][j]` for j <= i, and
    the reciprocals of its diagonal, `1 / L[j][j]`. `rsqrt`: each pivot's reciprocal from
    `lax.rsqrt`, and `L_jj = s / sqrt(s)` as `s` times it (no division or square root:
    `spd_solve_rsqrt`); else `L_jj = sqrt(s)` and its reciprocal by division."""
    n = M.shape[0]
    L = [[None] * (i + 1) for i in range(n)]
    inv = [None] * n
    for j in range(n):
        s = M[j, j]
        for k in range(j):
            s = s - L[j][k] * L[j][k]
        if rsqrt:
            inv[j] = lax.rsqrt(s)
            L[j][j] = s * inv[j]
        else:
            L[j][j] = jnp.sqrt(s)
            inv[j] = 1.0 / L[j][j]
        for i in range(j + 1, n):
            s = M[i, j]
            for k in range(j):
                s = s - L[i][k] * L[j][k]
            L[i][j] = s * inv[j]
    return L, inv


def _unrolled_solve(M, b, rsqrt: bool):
    """`M x = b` by `cholesky_unrolled`, then forward and back substitution, dividing by the
    diagonal (or, with `rsqrt`, multiplying by its reciprocal)."""
    n = M.shape[0]
    if n > UNROLL_MAX_DOF:
        return jsl.cho_solve(jsl.cho_factor(M), b)
    L, inv = cholesky_unrolled(M, rsqrt)
    pivot = (lambda s, i: s * inv[i]) if rsqrt else (lambda s, i: s / L[i][i])
    z = []
    for i in range(n):  # L z = b
        s = b[i]
        for k in range(i):
            s = s - L[i][k] * z[k]
        z.append(pivot(s, i))
    x = [None] * n
    for i in reversed(range(n)):  # L^T x = z
        s = z[i]
        for k in range(i + 1, n):
            s = s - L[k][i] * x[k]
        x[i] = pivot(s, i)
    return jnp.stack(x)


def spd_solve(M: Float[Array, "n n"], b: Float[Array, " n"]) -> Float[Array, " n"]:
    """`x` with `M x = b` for symmetric positive-definite `M` (see the module docstring).

    A non-positive-definite `M` gives NaN (the square root of a negative pivot), as
    `cho_factor` does; callers check the result (e.g. `simulate` raises on a non-finite state).
    """
    return _unrolled_solve(M, b, rsqrt=False)


def refine_rsqrt(s, y):
    """`y`, an approximation of `1 / sqrt(s)` with relative error `e`, improved by one step
    of the third-order Householder iteration for `y^-2 = s`: with `r = 1 - s y^2`,
    `y (1 + r/2 + 3 r^2/8)`, whose relative error is `~(5/16) e^3` (rounding aside): from
    `e = 2^-22` to a few units in the last place of a float64. `flexdyn.scalarize` applies it
    to every `lax.rsqrt` of a scalar program (`spd_solve_rsqrt`)."""
    r = 1.0 - (s * y) * y
    return y + y * (r * (0.5 + 0.375 * r))


def spd_solve_rsqrt(M: Float[Array, "n n"], b: Float[Array, " n"]) -> Float[Array, " n"]:
    """`spd_solve` without a division or a square root: each pivot's reciprocal square root
    `1 / L_jj` comes from `lax.rsqrt`, `L_jj = s / sqrt(s)` is `s` times it, and the
    substitutions multiply by it. For the GPU kernel of `flexdyn.fused`: there a float64
    division or square root is a Newton sequence with a call into a slow-path subroutine,
    while `lax.rsqrt` lowers to `rsqrt.approx.f64` (Triton's libdevice `__nv_rsqrt`; in SASS
    one hardware approximation, `MUFU.RSQ64H`, with no refinement), which `flexdyn.scalarize`
    refines there (`refine_rsqrt`). Elsewhere `lax.rsqrt` is accurate as it stands (exact on
    the CPU; within 1 ulp in XLA on a GPU). On the GPU it shortens the kernel
    (`benchmarks/ptxas_fused.py`); on the CPU the divisions are faster
    (`benchmarks/bench_solve_forms.py`), so `spd_solve` keeps them (both measured:
    `docs/performance.md`). A non-positive-definite `M` gives NaN or inf."""
    return _unrolled_solve(M, b, rsqrt=True)
