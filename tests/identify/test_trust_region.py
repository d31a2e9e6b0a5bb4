"""Levenberg-Marquardt's scaled first damping (`identify.trust_region`).

Oracles: NumPy's column norms of the Jacobian for `max diag(J^T J)`, optimistix's own
`ClassicalTrustRegion` for every step after the first, the damped normal equations solved
by NumPy for the first trial step, and SciPy's `least_squares` for the optimum.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
import pytest
from scipy.optimize import least_squares

from identify._fit.trust_region import ScaledTrustRegion, max_gauss_newton_diagonal


def _info(J, r, y):
    """`FunctionInfo.ResidualJac` of the linear residuals `J y - r` at `y` (a dict)."""
    struct = jax.eval_shape(lambda: y)
    flat = lambda v: jnp.concatenate([v["a"], v["b"]])  # noqa: E731
    op = lx.FunctionLinearOperator(lambda v: J @ flat(v), struct)
    return optx.FunctionInfo.ResidualJac(J @ flat(y) - r, op)


def test_max_gauss_newton_diagonal_is_the_largest_squared_column_norm():
    rng = np.random.default_rng(0)
    J = rng.normal(size=(40, 5)) * np.array([1.0, 3e3, 0.2, 50.0, 1e-4])
    y = {"a": jnp.zeros(2), "b": jnp.zeros(3)}
    got = max_gauss_newton_diagonal(_info(jnp.asarray(J), jnp.zeros(40), y).jac, y)
    assert float(got) == pytest.approx(np.max(np.sum(J**2, axis=0)), rel=1e-12)


@pytest.mark.parametrize("tau", [1e-3, 1e-6, 0.5])
def test_first_damping_is_tau_times_the_largest_diagonal_entry(tau):
    rng = np.random.default_rng(1)
    J = jnp.asarray(rng.normal(size=(30, 5)) * 1e3)
    y = {"a": jnp.ones(2), "b": jnp.ones(3)}
    info = _info(J, jnp.asarray(rng.normal(size=30)), y)
    search = ScaledTrustRegion(tau=tau)
    state = search.init(y, info)
    step_size, accept, _, new_state = search.step(jnp.array(True), y, y, info, info, state)
    lam = tau * np.max(np.sum(np.asarray(J) ** 2, axis=0))
    assert bool(accept)
    assert float(step_size) == pytest.approx(1.0 / lam, rel=1e-12)
    assert float(new_state.step_size) == pytest.approx(1.0 / lam, rel=1e-12)


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])  # a rejected step, an ordinary one, a very good one
def test_later_steps_update_the_damping_as_optimistix_does(scale):
    rng = np.random.default_rng(2)
    J = jnp.asarray(rng.normal(size=(30, 5)))
    r = jnp.asarray(rng.normal(size=30))
    y = {"a": jnp.zeros(2), "b": jnp.zeros(3)}
    y_eval = {"a": scale * jnp.asarray([0.3, -0.2]), "b": scale * jnp.asarray([0.1, 0.4, -0.5])}
    info, info_eval = _info(J, r, y), _info(J, r, y_eval)
    ours, theirs = ScaledTrustRegion(tau=1e-3), optx.ClassicalTrustRegion()
    struct = info
    state = eqx.tree_at(lambda s: s.step_size, theirs.init(y, struct), jnp.array(0.37))
    a = ours.step(jnp.array(False), y, y_eval, info, info_eval, state)
    b = theirs.step(jnp.array(False), y, y_eval, info, info_eval, state)
    assert float(a[0]) == float(b[0])
    assert bool(a[1]) == bool(b[1])
    assert float(a[3].step_size) == float(b[3].step_size)


def test_tau_zero_is_optimistix_start():
    rng = np.random.default_rng(5)
    y = {"a": jnp.zeros(2), "b": jnp.zeros(3)}
    info = _info(jnp.asarray(rng.normal(size=(10, 5)) * 1e3), jnp.ones(10), y)
    ours, theirs = ScaledTrustRegion(tau=jnp.asarray(0.0)), optx.ClassicalTrustRegion()
    a = ours.step(jnp.array(True), y, y, info, info, ours.init(y, info))
    b = theirs.step(jnp.array(True), y, y, info, info, theirs.init(y, info))
    assert float(a[0]) == float(b[0]) == 1.0
    assert bool(a[1]) and bool(b[1])


def test_zero_jacobian_keeps_optimistix_start():
    y = {"a": jnp.zeros(2), "b": jnp.zeros(3)}
    info = _info(jnp.zeros((10, 5)), jnp.ones(10), y)
    search = ScaledTrustRegion(tau=1e-3)
    state = search.init(y, info)
    step_size, *_ = search.step(jnp.array(True), y, y, info, info, state)
    assert float(step_size) == 1.0


def _decay_problem():
    """Noise-weighted residuals of `a exp(-b t) + c` (sigma 1e-3, so `diag(J^T J) ~ 1e8`)."""
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 2.0, 200)
    sigma = 1e-3
    data = 1.5 * np.exp(-2.3 * t) + 0.2 + sigma * rng.normal(size=t.size)

    def residuals(p):
        return (p[0] * jnp.exp(-p[1] * t) + p[2] - data) / sigma

    return residuals, np.array([0.5, 6.0, -0.3])


def _solve(search, residuals, p0):
    solver = eqx.tree_at(lambda s: s.search, optx.LevenbergMarquardt(rtol=1e-6, atol=1e-9, norm=optx.rms_norm), search)
    sol = optx.least_squares(lambda p, _: residuals(p), solver, jnp.asarray(p0), max_steps=500)
    return np.asarray(sol.value), int(sol.stats["num_steps"])


def test_scaled_start_reaches_scipys_optimum_in_fewer_steps():
    residuals, p0 = _decay_problem()
    ref = least_squares(lambda p: np.asarray(residuals(p)), p0, method="lm", xtol=1e-14, ftol=1e-14, gtol=1e-14).x
    scaled, n_scaled = _solve(ScaledTrustRegion(tau=1e-3), residuals, p0)
    classic, n_classic = _solve(optx.ClassicalTrustRegion(), residuals, p0)
    np.testing.assert_allclose(scaled, ref, rtol=1e-6)
    np.testing.assert_allclose(classic, ref, rtol=1e-6)
    # optimistix starts at damping 1 against diag(J^T J) ~ 1e8 and rejects its way up
    assert n_scaled < n_classic
