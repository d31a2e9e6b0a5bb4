"""Clamped-mass assumed modes (flexdyn.modes) against independent references.

Oracles:
- `oracles.cantilever_roots` (1 + cos x cosh x = 0, Blevins table 8-1),
- `oracles.clamped_mass_roots` (paper 002 eq. 23 / Laura et al. 1974, tip mass + inertia),
- `_offset_mass_roots` below: a clamped beam carrying a rigid body with mass M, first
  moment S and inertia J about the tip, derived here from Hamilton's principle and
  solved in the textbook cos/sin/cosh/sinh basis (the library uses a different,
  exponential basis), with scipy's brentq,
- numpy Gauss-Legendre quadrature for the normalisation integrals.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import oracles
import pytest
from scipy.optimize import brentq

import flexdyn as fd
from flexdyn.modes import _bracket_and_bisect, _host_roots, clamped_mass_roots, evaluate_shapes, mode_shapes

# One compiled root finder per n (n is static); avoids eager op-by-op dispatch.
N = 5  # roots / shapes used throughout (one compilation each)
_roots = jax.jit(clamped_mass_roots, static_argnums=0)
_shapes = jax.jit(mode_shapes, static_argnums=0)
_evaluate = jax.jit(evaluate_shapes, static_argnums=3)
# d lam_k / d (mu, sigma, iota) by reverse mode (jax.grad); k is traced so that one
# compilation serves every root and parameter set.
_dlam = jax.jit(jax.grad(lambda p, k: clamped_mass_roots(N, p[0], p[1], p[2])[k]))

# (mu, sigma, iota) = (M/(rho l), S/(rho l^2), J/(rho l^3)); all physical (J M >= S^2).
OFFSET_CASES = [
    (0.5, 0.1, 0.05),
    (1.0, 0.5, 0.3),
    (2.0, -0.2, 0.1),  # body's centre of mass behind the tip (inboard)
    (0.3, 0.3, 0.35),
    (0.0, 0.0, 0.2),  # pure rotary inertia
]


# ---------------------------------------------------------------------------
# Independent offset-mass frequency equation (numpy / scipy only)
# ---------------------------------------------------------------------------
#
# Beam EI v'''' = rho w^2 v on [0, l], clamped at 0, carrying at x = l a rigid body
# whose kinetic energy is T_b = 1/2 (M v_t^2 + 2 S v_t v_xt + J v_xt^2) (v, v_x at l).
# Hamilton's principle gives at x = l
#     EI v'''(l) = -w^2 (M v + S v'),     EI v''(l) = w^2 (S v + J v').
# With xi = x / l, lam = beta l, w^2 = EI lam^4 / (rho l^4) and derivatives in xi:
#     phi''' + lam^4 (mu phi + sigma phi') = 0,   phi'' - lam^4 (sigma phi + iota phi') = 0.
# Clamped root: phi = A (cos - cosh) + B (sin - sinh). Each entry is divided by cosh(lam)
# (exact, no cancellation) and each row by a positive scale, leaving a bounded 2x2 det.


def _offset_det(lam, mu, sigma, iota):
    c, s = math.cos(lam), math.sin(lam)
    sech, th = 1.0 / math.cosh(lam), math.tanh(lam)
    # phi, phi'/lam, phi''/lam^2, phi'''/lam^3 at xi = 1, divided by cosh(lam); columns (A, B)
    p0 = np.array([c * sech - 1.0, s * sech - th])
    p1 = np.array([-s * sech - th, c * sech - 1.0])
    p2 = np.array([-c * sech - 1.0, -s * sech - th])
    p3 = np.array([s * sech - th, -c * sech - 1.0])
    shear = (p3 + lam * mu * p0 + lam**2 * sigma * p1) / (1.0 + lam * mu + lam**2 * abs(sigma))
    moment = (p2 - lam**2 * sigma * p0 - lam**3 * iota * p1) / (1.0 + lam**2 * abs(sigma) + lam**3 * iota)
    return shear[0] * moment[1] - shear[1] * moment[0]


def _offset_mass_roots(n, mu, sigma, iota, step=2e-3):
    roots, x = [], 1e-4
    f_prev = _offset_det(x, mu, sigma, iota)
    while len(roots) < n:
        x_next = x + step
        f_next = _offset_det(x_next, mu, sigma, iota)
        if f_prev * f_next < 0.0:
            roots.append(brentq(_offset_det, x, x_next, args=(mu, sigma, iota), xtol=1e-15, rtol=1e-15))
        x, f_prev = x_next, f_next
    return np.array(roots)


# ---------------------------------------------------------------------------
# Roots
# ---------------------------------------------------------------------------


def test_cantilever_roots():
    """Oracle: oracles.cantilever_roots (1 + cos x cosh x = 0). First 8 roots, 1e-10 rel."""
    got = np.asarray(_roots(8, 0.0, 0.0, 0.0))
    want = oracles.cantilever_roots(8)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=0)


@pytest.mark.parametrize(
    "mu, iota", [(0.1, 0.0), (1.0, 0.0), (5.0, 0.0), (0.0, 0.05), (0.5, 0.1), (2.0, 1.0), (0.2, 0.01)]
)
def test_clamped_mass_roots_against_paper_002_eq23(mu, iota):
    """Oracle: oracles.clamped_mass_roots (paper 002 eq. 23, tip mass + rotary inertia,
    sigma = 0). First 5 roots, 1e-9 rel."""
    got = np.asarray(_roots(N, mu, 0.0, iota))
    want = oracles.clamped_mass_roots(N, mu, iota)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=0)


@pytest.mark.parametrize("path", ["default", "device"])
def test_clamped_mass_roots_batched_over_extreme_loads(path):
    """Oracle: oracles.clamped_mass_roots (paper 002 eq. 23, brentq), load by load, for a
    `vmap`ped batch that spans light to very heavy tip bodies: the heavy ones push the first
    two roots towards 0 and close together (`mu = 1e3, iota = 10`: 0.233 and 0.800), where
    the grid scan must still bracket each one. First 6 roots, 1e-9 rel. Both root finders:
    `default` is this backend's (the host's NumPy on a CPU), `device` the JAX scan that an
    accelerator uses."""
    loads = [(0.0, 0.0), (1e-3, 0.0), (0.05, 1e-4), (1.0, 0.0), (30.0, 0.0), (1e3, 0.0), (0.0, 10.0), (1e3, 10.0)]
    mu, iota = (jnp.asarray(v) for v in zip(*loads))
    if path == "default":
        find = jax.vmap(lambda m, j: clamped_mass_roots(6, m, 0.0, j))
    else:
        find = jax.vmap(lambda m, j: _bracket_and_bisect(6, m, jnp.zeros_like(m), j))
    got = np.asarray(jax.jit(find)(mu, iota))
    for row, (m, j) in zip(got, loads):
        want = oracles.clamped_mass_roots(6, m, j)
        np.testing.assert_allclose(row, want, rtol=1e-9, atol=0, err_msg=f"mu={m}, iota={j}")


def test_host_and_device_root_finders_agree_with_a_body_offset():
    """The two root finders on tip bodies with a first moment (sigma != 0, one inboard):
    the same brackets, the same bisection, so the same roots to round-off."""
    mu, sigma, iota = (jnp.asarray(v) for v in zip(*OFFSET_CASES))
    device = jax.jit(jax.vmap(lambda m, s, j: _bracket_and_bisect(N, m, s, j)))(mu, sigma, iota)
    host = _host_roots(N, np.asarray(mu), np.asarray(sigma), np.asarray(iota))
    np.testing.assert_allclose(np.asarray(device), host, rtol=1e-12, atol=0)


def test_clamped_mass_roots_rejects_non_finite_loads():
    """A NaN tip-load ratio leaves the frequency equation without roots: an error naming
    it, not NaN roots."""
    with pytest.raises(Exception, match="fewer roots than modes"):
        jax.block_until_ready(_roots(N, jnp.nan, 0.0, 0.0))


def test_offset_determinant_reduces_to_paper_eq23():
    """Self-check of the test's own offset-mass determinant: with sigma = 0 its roots equal
    oracles.clamped_mass_roots (1e-11 rel), so its derivation shares the paper's conventions."""
    for mu, iota in [(0.0, 0.0), (1.0, 0.0), (0.5, 0.1), (2.0, 1.0)]:
        np.testing.assert_allclose(
            _offset_mass_roots(N, mu, 0.0, iota), oracles.clamped_mass_roots(N, mu, iota), rtol=1e-11, atol=0
        )


@pytest.mark.parametrize("mu, sigma, iota", OFFSET_CASES)
def test_offset_mass_roots(mu, sigma, iota):
    """Oracle: the offset-mass (S != 0) frequency equation derived in this file from
    Hamilton's principle, in the cos/sin/cosh/sinh basis (not the library's exponential
    basis), roots by brentq. First 5 roots, 1e-10 rel.

    Chosen over the 'clamped link + locked rigid link' construction because that one
    would go through flexdyn's own chain assembly and a finite joint stiffness."""
    got = np.asarray(_roots(N, mu, sigma, iota))
    want = _offset_mass_roots(N, mu, sigma, iota)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=0)


def test_offset_mass_physical_body():
    """Oracle: _offset_mass_roots for a physical rigid body (mass m_b, COM a distance e
    beyond the tip, inertia I_c about the COM: M = m_b, S = m_b e, J = I_c + m_b e^2).
    The roots move with e (the offset really enters the model)."""
    rho_l, l = 0.1, 0.5
    m_b, I_c = 0.05, 2e-4
    prev = None
    for e in (0.0, 0.02, 0.05, 0.1):
        mu, sigma, iota = m_b / rho_l, m_b * e / (rho_l * l), (I_c + m_b * e**2) / (rho_l * l**2)
        got = np.asarray(_roots(N, mu, sigma, iota))
        np.testing.assert_allclose(got, _offset_mass_roots(N, mu, sigma, iota), rtol=1e-10, atol=0)
        if prev is not None:
            assert np.all(np.abs(got - prev) > 1e-4 * prev), f"e={e}: roots {got} did not move from {prev}"
        prev = got


# ---------------------------------------------------------------------------
# Shapes: normalisation and boundary conditions
# ---------------------------------------------------------------------------

_GL_X, _GL_W = np.polynomial.legendre.leggauss(160)
_GL_X, _GL_W = 0.5 * (_GL_X + 1.0), 0.5 * _GL_W


def _derivs(lam, coef, xi):
    return [np.asarray(_evaluate(lam, coef, jnp.asarray(xi), k)) for k in range(4)]


@pytest.mark.parametrize("mu, sigma, iota", [(0.0, 0.0, 0.0)] + OFFSET_CASES[:3])
def test_shape_normalisation_and_root(mu, sigma, iota):
    """Oracle: numpy Gauss-Legendre quadrature (160 nodes) and the definitions:
    (1/l) int phi^2 = 1 (1e-12), phi(l) > 0, clamped root phi(0) = phi'(0) = 0 (1e-12
    relative to the shape's scale lam^k)."""
    n = N
    lam, coef = _shapes(N, mu, sigma, iota)
    lam_np = np.asarray(lam)
    phi = np.asarray(_evaluate(lam, coef, jnp.asarray(_GL_X), 0))  # (G, n)
    np.testing.assert_allclose(_GL_W @ phi**2, np.ones(n), rtol=0, atol=1e-12)
    d0, d1, _, _ = _derivs(lam, coef, np.array([0.0, 1.0]))
    assert np.all(d0[1] > 0), f"tip values not positive: {d0[1]}"
    np.testing.assert_allclose(d0[0], 0.0, atol=1e-12)
    np.testing.assert_allclose(d1[0] / lam_np, 0.0, atol=1e-12)


def test_free_end_conditions():
    """Oracle: the cantilever's free-end conditions phi''(1) = phi'''(1) = 0 (no tip load),
    first 5 modes, to 1e-11 relative to lam^2, lam^3 (the scale of those derivatives for unit RMS shapes)."""
    lam, coef = _shapes(N, 0.0, 0.0, 0.0)
    lam_np = np.asarray(lam)
    _, _, d2, d3 = _derivs(lam, coef, np.array([1.0]))
    np.testing.assert_allclose(d2[0] / lam_np**2, 0.0, atol=1e-11)
    np.testing.assert_allclose(d3[0] / lam_np**3, 0.0, atol=1e-11)


@pytest.mark.parametrize("mu, sigma, iota", OFFSET_CASES)
def test_tip_load_boundary_conditions(mu, sigma, iota):
    """Oracle: the tip-body boundary conditions (Hamilton's principle, see the header):
    phi''' + lam^4 (mu phi + sigma phi') = 0 and phi'' - lam^4 (sigma phi + iota phi') = 0
    at xi = 1, residuals relative to the size of their largest term, 1e-10."""
    lam, coef = _shapes(N, mu, sigma, iota)
    lam_np = np.asarray(lam)
    d0, d1, d2, d3 = (d[0] for d in _derivs(lam, coef, np.array([1.0])))
    l4 = lam_np**4
    shear = d3 + l4 * (mu * d0 + sigma * d1)
    moment = d2 - l4 * (sigma * d0 + iota * d1)
    shear_scale = np.abs(d3) + l4 * (abs(mu * d0) + np.abs(sigma * d1)) + lam_np**3
    moment_scale = np.abs(d2) + l4 * (abs(sigma * d0) + np.abs(iota * d1)) + lam_np**2
    np.testing.assert_allclose(shear / shear_scale, 0.0, atol=1e-10)
    np.testing.assert_allclose(moment / moment_scale, 0.0, atol=1e-10)


@pytest.mark.parametrize("mu, sigma, iota", [(0.0, 0.0, 0.0), (1.0, 0.5, 0.3)])
def test_mass_orthogonality_with_tip_body(mu, sigma, iota):
    """Oracle: eigenfunctions of a self-adjoint problem are orthogonal in the kinetic-energy
    inner product int phi_j phi_k + mu phi_j phi_k + sigma (phi_j phi_k' + phi_j' phi_k)
    + iota phi_j' phi_k' (at xi = 1); numpy quadrature, off-diagonal < 1e-11."""
    lam, coef = _shapes(N, mu, sigma, iota)
    phi = np.asarray(_evaluate(lam, coef, jnp.asarray(_GL_X), 0))
    d0, d1, _, _ = (d[0] for d in _derivs(lam, coef, np.array([1.0])))
    G = (
        (phi.T * _GL_W) @ phi
        + mu * np.outer(d0, d0)
        + sigma * (np.outer(d0, d1) + np.outer(d1, d0))
        + iota * np.outer(d1, d1)
    )
    off = G - np.diag(np.diag(G))
    assert np.max(np.abs(off)) < 1e-11, f"max off-diagonal {np.max(np.abs(off)):.2e}"


# ---------------------------------------------------------------------------
# Differentiability
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("mu, iota", [(0.5, 0.0), (1.0, 0.1)])
def test_root_derivative_wrt_mu(mu, iota):
    """Oracle: central finite differences of oracles.clamped_mass_roots (brentq to 1e-15),
    step 1e-4 mu. jax.grad of each of the first 4 roots w.r.t. mu, 1e-6 rel."""
    n = 4
    p = jnp.array([mu, 0.0, iota])
    grads = np.array([float(_dlam(p, k)[0]) for k in range(n)])
    h = 1e-4 * mu
    fd_ = (oracles.clamped_mass_roots(n, mu + h, iota) - oracles.clamped_mass_roots(n, mu - h, iota)) / (2 * h)
    np.testing.assert_allclose(grads, fd_, rtol=1e-6, atol=0)


def test_root_derivative_wrt_sigma_and_iota():
    """Oracle: central finite differences of the offset-mass determinant roots
    (_offset_mass_roots, brentq). jax.grad w.r.t. sigma and iota of the first 3 roots, 1e-6 rel."""
    mu, sigma, iota, n = 1.0, 0.3, 0.2, 3
    g = np.array([np.asarray(_dlam(jnp.array([mu, sigma, iota]), k)) for k in range(n)])  # (n, 3)
    h = 1e-5
    fd_s = (_offset_mass_roots(n, mu, sigma + h, iota) - _offset_mass_roots(n, mu, sigma - h, iota)) / (2 * h)
    fd_j = (_offset_mass_roots(n, mu, sigma, iota + h) - _offset_mass_roots(n, mu, sigma, iota - h)) / (2 * h)
    np.testing.assert_allclose(g[:, 1], fd_s, rtol=1e-6, atol=0)
    np.testing.assert_allclose(g[:, 2], fd_j, rtol=1e-6, atol=0)


def test_assembled_link_uses_clamped_mass_roots():
    """Oracle: oracles.clamped_mass_roots. A single flexible link with a tip payload
    (mass, inertia) assembles with lam equal to the paper-002 roots (1e-9) and
    frequency = lam^2 / l^2 sqrt(EI / rho) (1e-12 rel)."""
    l, rho, EI, M, J = 0.5, 0.2, 1.0, 0.1, 0.005
    chain = fd.Chain([fd.FlexibleLink(l, rho, EI, n_modes=3)], payload=fd.Payload(M, J))
    lm = eqx.filter_jit(fd.assemble)(chain).links[0]
    want = oracles.clamped_mass_roots(3, M / (rho * l), J / (rho * l**3))
    np.testing.assert_allclose(np.asarray(lm.lam), want, rtol=1e-9)
    np.testing.assert_allclose(np.asarray(lm.frequency), want**2 / l**2 * math.sqrt(EI / rho), rtol=1e-9)
    np.testing.assert_allclose(np.asarray(lm.tip_load), [M, 0.0, J], rtol=1e-14)
