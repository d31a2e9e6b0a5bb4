"""Levenberg-Marquardt's damping, started at the scale of the problem.

optimistix's `LevenbergMarquardt` damps its Gauss-Newton step with `lambda = 1 / step_size`
(`optx.ClassicalTrustRegion`), starting from `step_size = 1` whatever the scale of the
Gauss-Newton matrix `A = J^T J`. Our residuals are noise-weighted (`r / sigma`, hundreds to
thousands of samples per log), so `diag(A)` is of order `1e5`-`1e8` and `lambda = 1` is an
undamped Gauss-Newton step: from a guess 30 % off, it overshoots, and the trust region
rejects step after step, a factor `4` in `lambda` each, every rejected trial paying a full
residual evaluation and Jacobian.

`ScaledTrustRegion` is the same trust region with the textbook start (Madsen, Nielsen and
Tingleff, "Methods for non-linear least squares problems", 2nd ed., DTU 2004, Sec. 3.2,
Eq. 3.14 and Algorithm 3.16):

    lambda_0 = tau * max_i A_ii,   A = J(y_0)^T J(y_0),

with `tau = 1e-3` when the start may be far from the optimum (the book's advice, and the
value `1e-3 * 3.7e7 = 3.7e4` it gives on the benchmark's fit is where optimistix's
rejections ended up) and a small `tau` (say `1e-6`) when the start is believed good. After
the first step it updates `lambda` exactly as `optx.ClassicalTrustRegion` does.

It made the default fit's multi-start stage slower, so `identify.fit` uses it only for a
solve from a single start (`fit(first_damping=...)`); measurements in `docs/performance.md`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax.flatten_util import ravel_pytree


def max_gauss_newton_diagonal(jac, y) -> jax.Array:
    """`max_i (J^T J)_ii`, the largest squared column norm of the linear operator `jac`
    (input structure that of `y`), one Jacobian-vector product per column (sequential, so
    no `J` is formed)."""
    flat, unravel = ravel_pytree(y)

    def column_norm2(e):
        out, _ = ravel_pytree(jac.mv(unravel(e)))
        return jnp.sum(out**2)

    if flat.shape[0] == 0:
        return jnp.zeros((), flat.dtype)
    return jnp.max(jax.lax.map(column_norm2, jnp.eye(flat.shape[0], dtype=flat.dtype)))


class ScaledTrustRegion(optx.AbstractSearch):
    """`optx.ClassicalTrustRegion` whose first damping is `tau * max_i (J^T J)_ii` at the
    starting point (module docstring), not `1`. It holds an optimistix trust region
    (`inner`) and forwards to it, replacing only the first step size. `tau` may be a
    traced scalar, so that solves with different `tau` share one compiled program; `tau =
    0` is optimistix's start."""

    tau: jax.Array | float = 1e-3
    inner: optx.ClassicalTrustRegion = optx.ClassicalTrustRegion()

    def init(self, y, f_info_struct):
        return self.inner.init(y, f_info_struct)

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        step_size, accept, result, new_state = self.inner.step(first_step, y, y_eval, f_info, f_eval_info, state)

        def scaled():
            lam = self.tau * max_gauss_newton_diagonal(f_eval_info.jac, y_eval)
            # an all-zero Jacobian (or a non-finite one, which the solve reports anyway) keeps
            # optimistix's start
            return jnp.where(jnp.isfinite(lam) & (lam > 0), 1.0 / lam, step_size).astype(step_size.dtype)

        step_size = jax.lax.cond(first_step & (self.tau > 0), scaled, lambda: step_size)
        new_state = eqx.tree_at(lambda s: s.step_size, new_state, step_size)
        return step_size, accept, result, new_state
