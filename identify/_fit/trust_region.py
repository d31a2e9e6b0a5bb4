"""Levenberg-Marquardt's damping, started at the scale of the problem.

optimistix's `LevenbergMarquardt` damps its Gauss-Newton step with `lambda = 1 / step_size`
(`optx.ClassicalTrustRegion`), starting from `step_size = 1` whatever the scale of the
Gauss-Newton matrix `A = J^T J`. Our residuals are noise-weighted (`r / sigma`, hundreds to
thousands of samples per log), so `diag(A)` is of order `1e5`-`1e8` and `lambda = 1` is an
undamped Gauss-Newton step: from a guess 30 % off, it overshoots, and the trust region
rejects step after step, a factor `4` in `lambda` each, every rejected trial paying a full
residual evaluation and Jacobian (measured on `benchmarks/bench_fit_vs_scipy.py`'s
single-shooting fit: 7 of its 22 steps were rejected before the first accepted one, at
`lambda ~ 1.6e4`).

`ScaledTrustRegion` is the same trust region with the textbook start (Madsen, Nielsen and
Tingleff, "Methods for non-linear least squares problems", 2nd ed., DTU 2004, Sec. 3.2,
Eq. 3.14 and Algorithm 3.16):

    lambda_0 = tau * max_i A_ii,   A = J(y_0)^T J(y_0),

with `tau = 1e-3` when the start may be far from the optimum (the book's advice, and the
value `1e-3 * 3.7e7 = 3.7e4` it gives on the benchmark's fit is where optimistix's
rejections ended up) and a small `tau` (say `1e-6`) when the start is believed good. After
the first step it updates `lambda` exactly as `optx.ClassicalTrustRegion` does.

Measured (`benchmarks/bench_fit_vs_scipy.py`, `benchmarks/bench_fit_convergence.py`, 16
guesses -50 %/+100 % off on every parameter):
- single shooting from the benchmark's guess: 10 steps instead of 22, the same optimum;
- single shooting from the 16 far guesses: 11 of 16 converge either way, median 1.40 s
  instead of 1.89 s; a growing horizon from one start: 16 of 16 instead of 12 of 16 (the
  undamped first steps of the short first stage jumped to a spurious optimum with the
  joint damping on its lower bound);
- in the fit's multi-start stage (8 starts on a short horizon) it made the default fit slower
  (median 134 instead of 84 iterations, 4.3 vs 3.9 s) for the same 16 of 16, so
  `identify.fit` uses it only for a solve from a single start (`fit(first_damping=...)`).
- Also tried: Nielsen's update of `lambda` after each step (`lambda *= max(1/3, 1 - (2 rho -
  1)^3)` on acceptance, doubling growth on rejection) on top of this start: the short first
  stage then walked to the damping's lower bound in 9 of 16 growing-horizon fits. Not used.
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


class ScaledTrustRegion(optx.ClassicalTrustRegion):
    """`optx.ClassicalTrustRegion` whose first damping is `tau * max_i (J^T J)_ii` at the
    starting point (module docstring), not `1`. `tau` may be a traced scalar, so that
    solves with different `tau` share one compiled program."""

    tau: jax.Array | float = 1e-3

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        step_size, accept, result, new_state = super().step(first_step, y, y_eval, f_info, f_eval_info, state)

        def scaled():
            lam = self.tau * max_gauss_newton_diagonal(f_eval_info.jac, y_eval)
            # an all-zero Jacobian (or a non-finite one, which the solve reports anyway) keeps
            # optimistix's start
            return jnp.where(jnp.isfinite(lam) & (lam > 0), 1.0 / lam, step_size).astype(step_size.dtype)

        # `tau = 0` (optimistix's start) skips the column norms
        step_size = jax.lax.cond(first_step & (self.tau > 0), scaled, lambda: step_size)
        new_state = eqx.tree_at(lambda s: s.step_size, new_state, step_size)
        return step_size, accept, result, new_state
