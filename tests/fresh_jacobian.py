"""The oracle for a fit's standard errors: a Jacobian computed afresh at its optimum.

A fit reads its standard errors from the last Levenberg-Marquardt linearisation
(`identify.fit._solve`); these helpers recompute the Jacobian at the returned optimum with
its own forward-mode solve over every sample (`identify.fit._jacobian_natural`) and compare.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import identify  # noqa: F401  (loads identify.fit)
import identify._fit.jacobian as jacobian_module
import identify._model.parameters as parameters_module


def fresh_covariance(result):
    """The dense covariance at `result`'s optimum from a Jacobian computed afresh there
    (`identify.fit._jacobian_natural`: its own forward-mode solve over every sample), the
    oracle for the standard errors a fit reads from its last Levenberg-Marquardt
    linearisation. Standard errors in natural coordinates (log ones for log-scale
    parameters)."""
    problem = result.problem
    x = parameters_module.x_from_z(problem, result.z.phys)
    sigma = jnp.asarray([result.sigma[c] for c in problem.channels])
    r, J, ok = jacobian_module._jacobian_natural(problem, x, result.z.y0, result.z.offset, sigma, result.step)
    assert bool(ok)
    return jacobian_module._dense_covariance(problem, r, J)


def assert_standard_errors_match(result, fresh, rtol=1e-8):
    """`result`'s standard errors (physical units) equal `fresh`'s (`fresh_covariance`)."""
    p = len(result.names)
    log = np.asarray(result.problem.log_scale)
    expected = np.where(log, np.asarray(result.values) * fresh.std_errors[:p], fresh.std_errors[:p])
    np.testing.assert_allclose(result.std_errors, expected, rtol=rtol)
    np.testing.assert_allclose(result.correlation, fresh.correlation, rtol=rtol, atol=1e-12)
    assert result.cost == pytest.approx(fresh.rss, rel=1e-10)
