"""`flexdyn.stiffening`: the first-order geometric stiffening of a link's first mode against
the Rayleigh-Ritz solution of the axially loaded cantilever (tests/oracles.py) and the
published rotating-cantilever table (Hodges & Rutkowski, AIAA J. 19 (1981) 1459)."""

import math

import numpy as np
import oracles
import pytest

import flexdyn as fd
from flexdyn.stiffening import first_mode_stiffening

L, RHO, EI = 0.7, 0.5, 2.0  # m, kg/m, N m^2


def _ritz_slopes(mu: float, h: float = 1e-2):
    """d(omega~^2)/d(lam^2) (spin) and d(omega~^2)/d(gamma) (gravity, tension positive) at zero
    load, central differences of the Ritz oracle; a tip point mass `mu = M / (rho l)` pulls with
    its own centrifugal / weight force (`N = lam^2 ((1 - x^2)/2 + mu)`, `gamma ((1 - x) + mu)`).
    (The Ritz eigenvalues carry round-off of ~1e-9 relative, so the step is not smaller;
    the truncation error of the difference is below that here.)"""

    def w2(lam2, gamma):
        tension = lambda x: lam2 * ((1 - x * x) / 2 + mu) + gamma * ((1 - x) + mu)  # noqa: E731
        return oracles.axially_loaded_cantilever_frequencies(tension, 0.0, mu, 10)[0] ** 2

    return (w2(h, 0.0) - w2(-h, 0.0)) / (2 * h), (w2(0.0, h) - w2(0.0, -h)) / (2 * h), math.sqrt(w2(0.0, 0.0))


@pytest.mark.parametrize("mu", [0.0, 0.3, 1.0])
def test_first_mode_stiffening_matches_the_ritz_solution(mu):
    chain = fd.Chain([fd.FlexibleLink(L, RHO, EI, n_modes=3)], payload=fd.Payload(mu * RHO * L, 0.0))
    e = first_mode_stiffening(chain)["link1"]
    spin, gravity, w0 = _ritz_slopes(mu)
    # dimensionless: omega~^2 = omega^2 rho l^4 / EI, lam^2 = Omega^2 rho l^4 / EI, gamma = rho g l^3 / EI
    assert e.frequency == pytest.approx(w0 * math.sqrt(EI / (RHO * L**4)), rel=1e-9)
    assert e.spin == pytest.approx(spin, rel=1e-6)  # measured 7e-10 .. 3e-8 (spin and gravity)
    assert e.gravity * L == pytest.approx(gravity, rel=1e-6)


def test_southwell_coefficient_and_the_published_rotating_cantilever_table():
    e = first_mode_stiffening(fd.Chain([fd.FlexibleLink(L, RHO, EI, n_modes=2)]))["link1"]
    assert e.spin == pytest.approx(1.1933, abs=1e-4)  # Southwell's coefficient of the first mode
    # first order against the exact out-of-plane table (3.5160, 3.6816, 4.1373 at lam = 0, 1, 2)
    for lam, published in ((1.0, 3.6816), (2.0, 4.1373)):
        rate = lam * math.sqrt(EI / (RHO * L**4))
        predicted = math.sqrt(1.0 + e.relative_shift(spin_rate=rate)) * 3.5160
        assert predicted == pytest.approx(published, rel=2e-3)  # measured 5e-5 (lam 1), 5e-4 (lam 2)


def test_every_flexible_link_of_a_chain_and_only_those():
    flex = fd.FlexibleLink(L, RHO, EI, n_modes=2)
    stiff = fd.FlexibleLink(L, RHO, EI, n_modes=2, geometric_stiffening=True)
    chain = fd.Chain([flex, fd.RigidLink(0.3, 0.2), stiff])
    est = first_mode_stiffening(chain)
    assert sorted(est) == ["link1", "link3"]
    # the last link carries nothing: the uniform cantilever's value
    assert est["link3"].spin == pytest.approx(1.1933, abs=1e-4)
    assert est["link1"].spin > 0 and est["link1"].gravity > 0
    # the same first frequencies as the assembled chain's clamped-mass modes
    asm = fd.assemble(chain)
    assert est["link1"].frequency == pytest.approx(float(asm.links[0].frequency[0]), rel=1e-12)
    assert first_mode_stiffening(fd.Chain([fd.RigidLink(0.3, 0.2)])) == {}
    with pytest.raises(TypeError, match="expected a flexdyn.Chain"):
        first_mode_stiffening(fd.assemble(chain))


def test_the_hanging_strip_of_paper_000_is_predicted_to_first_order():
    """Paper 000's spring-steel strip, 0.30 m (the paper's) and 1.0 m long, hanging (rho g l^3
    / EI = 0.031 and 1.16; tests/flexdyn/test_chain.py section 9 checks the stiffened model
    itself): the first-order estimate of the rise of `omega_1^2` against the Ritz oracle's
    exactly loaded value (measured 1.5e-5 and 5.5e-4 apart, relative: the second-order term)."""
    g = 9.81
    strip = fd.rigs.flexible_pendulum(n_modes=4).links[0]
    rho, EI = float(strip.rho), float(strip.EI)
    for length, tol in ((0.30, 1e-4), (1.0, 3e-3)):
        link = fd.FlexibleLink(length, rho, EI, n_modes=4)
        e = first_mode_stiffening(fd.Chain([link]))["link1"]
        gamma = rho * g * length**3 / EI
        exact = oracles.axially_loaded_cantilever_frequencies(lambda x: gamma * (1 - x), 0.0, 0.0, 10)[0]
        shift = (exact / oracles.cantilever_roots(1)[0] ** 2) ** 2 - 1.0
        assert e.relative_shift(axial_gravity=g) == pytest.approx(shift, rel=tol), length
    assert np.isclose(e.relative_shift(), 0.0)
