"""The one compiled Levenberg-Marquardt program (optimistix) every fit runs, with its budget checks."""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._model.parameters import theta_from_x, x_from_z
from .._model.problem import Problem
from .._model.residuals import (
    log_blocked,
    residuals as _residuals_from,
)
from .block_lm import BlockLevenbergMarquardt, Layout, read_blocks
from .trust_region import ScaledTrustRegion


def _unpack(args):
    problem, sigma, horizon, step = args
    return problem, lambda phys: theta_from_x(problem, x_from_z(problem, phys)), sigma, horizon, step


def _residual_fn(z, args):
    problem, theta_of, sigma, horizon, step = _unpack(args)
    return _residuals_from(problem, theta_of(z.shared), z.y0, z.offset, sigma, horizon, step)[0]


class _BudgetedLM(optx.AbstractLeastSquaresSolver):
    """Levenberg-Marquardt (`inner`) that also stops after `budget` steps, a traced
    integer, with the result `nonlinear_max_steps_reached` (what optimistix reports at
    its own static `max_steps`). The stages of a fit have different iteration budgets;
    as a traced value the budget does not recompile the fit's Levenberg-Marquardt
    program (a static one would, at seconds of XLA compilation per distinct budget:
    docs/performance.md)."""

    inner: optx.AbstractGaussNewton
    budget: jax.Array
    rtol: float = eqx.field(static=True)
    atol: float = eqx.field(static=True)
    norm: Callable = eqx.field(static=True)

    def __init__(self, inner: optx.AbstractGaussNewton, budget):
        self.inner = inner
        self.budget = jnp.asarray(budget, dtype=int)
        self.rtol, self.atol, self.norm = inner.rtol, inner.atol, inner.norm

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        return self.inner.init(fn, y, args, options, f_struct, aux_struct, tags), jnp.array(0)

    def step(self, fn, y, args, options, state, tags):
        inner_state, n = state
        y, inner_state, aux = self.inner.step(fn, y, args, options, inner_state, tags)
        return y, (inner_state, n + 1), aux

    def terminate(self, fn, y, args, options, state, tags):
        inner_state, n = state
        done, result = self.inner.terminate(fn, y, args, options, inner_state, tags)
        capped = jnp.invert(done) & (n >= self.budget)
        return done | capped, optx.RESULTS.where(capped, optx.RESULTS.nonlinear_max_steps_reached, result)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return self.inner.postprocess(fn, y, aux, args, options, state[0], tags, result)


# From this many logs with nuisances on, a Levenberg-Marquardt step is solved block by block
# (`identify.block_lm`): from there on it is faster than optimistix's dense QR, below it
# slower and longer to compile (docs/performance.md, "Joint fits of many logs").
BLOCK_SOLVE_MIN_LOGS = 8


def _blocked(problem: Problem) -> bool:
    """Whether `problem`'s Levenberg-Marquardt steps and covariance are solved block by block."""
    return problem.t.shape[0] >= BLOCK_SOLVE_MIN_LOGS and bool(problem.y0_free or problem.offset_free)


def _levenberg_marquardt(problem: Problem, rtol: float, atol: float, tau=0.0):
    """Levenberg-Marquardt for `problem`, its first damping `tau * max diag(J^T J)`
    (`identify.trust_region`)."""
    if _blocked(problem):
        solver = BlockLevenbergMarquardt(rtol, atol, Layout.of(problem), norm=optx.rms_norm)
    else:
        solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol, norm=optx.rms_norm)
    return eqx.tree_at(lambda s: s.search, solver, ScaledTrustRegion(tau=tau))


# same value as `_residual_fn`; each Levenberg-Marquardt step linearises it in one
# forward-mode solve per log, with that log's nuisances only (`identify.residuals`)
_residual_fn_lm = log_blocked(_unpack)


@eqx.filter_jit
def _solve(problem: Problem, z0, sigma, horizon, step, budget, tau, max_steps: int, rtol: float, atol: float):
    # Termination on the RMS (not the max) of the residual change: converged when the
    # residuals move by less than `rtol` of their size on average, i.e. the step is a
    # small fraction of a standard error (not when every single residual is frozen).
    # At most `budget` (traced) iterations, `max_steps` (static) >= every budget used.
    # First damping `tau * max diag(J^T J)` (`tau` traced).
    # Returns the solution, optimistix's result, the number of steps, the cost and the
    # linearisation at the solution, `(r, S, U)` (`identify.block_lm.read_blocks`, w.r.t.
    # `z`): optimistix keeps the residuals and the linear map of the last accepted point,
    # which is the solution, so the standard errors need no second Jacobian program (a
    # sizeable part of a cold fit's compilation: docs/performance.md) and no final residual
    # evaluation (another diffrax solve). Needs >= 1 step (the first
    # is always accepted); `fit` checks its budgets.
    solver = _BudgetedLM(_levenberg_marquardt(problem, rtol, atol, tau), budget)
    args = (problem, sigma, horizon, step)
    sol = optx.least_squares(_residual_fn_lm, solver, z0, args=args, max_steps=max_steps, throw=False)
    lin = read_blocks(Layout.of(problem), sol.value, sol.state[0].f_info)
    return sol.value, sol.result, sol.stats["num_steps"], jnp.sum(lin.r**2), (lin.r, lin.S, lin.U)


def _check_budgets(**budgets):
    # `_solve` reads the standard errors' linearisation from the last accepted step
    for name, value in budgets.items():
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"fit: {name} expected a whole number of Levenberg-Marquardt steps >= 1, got {value!r}")


def _check_damping(first_damping):
    if not (np.isfinite(first_damping) and first_damping >= 0):
        raise ValueError(
            f"fit: first_damping must be a finite number >= 0 (0: optimistix's start), got {first_damping!r}"
        )


def _result_name(result) -> str:
    if result == optx.RESULTS.successful:
        return "successful"
    for name in ("nonlinear_max_steps_reached", "max_steps_reached"):
        if name in optx.RESULTS._name_to_item and result == getattr(optx.RESULTS, name):
            return "max_steps_reached"
    return "failed"
