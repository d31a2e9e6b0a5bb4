"""Solving the small symmetric positive-definite systems of the equations of motion.

`spd_solve(M, b)` solves `M x = b` for the generalised mass matrix `M` (n x n, n = the
chain's degrees of freedom, static). For small n it is a Cholesky factorisation written
out entry by entry (`M = L L^T`, then forward and back substitution):

    L_jj = sqrt(M_jj - sum_{k<j} L_jk^2),   L_ij = (M_ij - sum_{k<j} L_ik L_jk) / L_jj  (i > j)

about n^3/6 + n^2 multiply-adds on scalars, with no call into LAPACK / cuSOLVER. Under
`vmap` every one of these is an elementwise operation over the batch, which XLA fuses
with the rest of the right-hand side into a few kernels; a batched `cho_factor` is a
library call per right-hand side instead (a loop of tiny LAPACK calls on the CPU, several
kernel launches on a GPU), which dominated batched sweeps (`benchmarks/README.md`). Above
`UNROLL_MAX_DOF` the unrolled program grows as n^3 and compiles slowly, so larger systems
use `jax.scipy.linalg.cho_solve`. No pivoting is needed: `M` is symmetric positive
definite (it is the Hessian of the kinetic energy in the velocities).
"""

from __future__ import annotations

import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array, Float

UNROLL_MAX_DOF = 12


def cholesky_unrolled(M: Float[Array, "n n"]) -> list[list]:
    """Lower Cholesky factor of `M` as a nested list of scalars, `L[i][j]` for j <= i."""
    n = M.shape[0]
    L = [[None] * (i + 1) for i in range(n)]
    for j in range(n):
        s = M[j, j]
        for k in range(j):
            s = s - L[j][k] * L[j][k]
        ljj = jnp.sqrt(s)
        L[j][j] = ljj
        inv = 1.0 / ljj
        for i in range(j + 1, n):
            s = M[i, j]
            for k in range(j):
                s = s - L[i][k] * L[j][k]
            L[i][j] = s * inv
    return L


def spd_solve(M: Float[Array, "n n"], b: Float[Array, " n"]) -> Float[Array, " n"]:
    """`x` with `M x = b` for symmetric positive-definite `M` (see the module docstring).

    A non-positive-definite `M` gives NaN (the square root of a negative pivot), as
    `cho_factor` does; callers check the result (e.g. `simulate` raises on a non-finite state).
    """
    n = M.shape[0]
    if n > UNROLL_MAX_DOF:
        return jsl.cho_solve(jsl.cho_factor(M), b)
    L = cholesky_unrolled(M)
    z = []
    for i in range(n):  # L z = b
        s = b[i]
        for k in range(i):
            s = s - L[i][k] * z[k]
        z.append(s / L[i][i])
    x = [None] * n
    for i in reversed(range(n)):  # L^T x = z
        s = z[i]
        for k in range(i + 1, n):
            s = s - L[k][i] * x[k]
        x[i] = s / L[i][i]
    return jnp.stack(x)
