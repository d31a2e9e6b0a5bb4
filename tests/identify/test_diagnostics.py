"""Residual tests (identify.diagnostics) and identifiability warnings (identify.fit).

Oracles: the statistics of white Gaussian noise (known distribution of the sample
autocorrelation and of the Ljung-Box statistic) and an analytically unidentifiable
parameter pair (a clamped beam's free vibration depends on EI and rho only through
sqrt(EI / rho)).
"""

import numpy as np
import pytest

import flexdyn as fd
import identify
from identify._diagnose import residual_tests as diagnostics


def test_white_noise_passes_whiteness_at_the_stated_rate(rng):
    """White Gaussian noise fails the 1 % Ljung-Box test in about 1 % of trials."""
    failures = sum(not diagnostics.whiteness(rng.standard_normal(2000))["white"] for _ in range(400))
    assert failures <= 12, f"{failures}/400 white sequences flagged as coloured (expected ~4)"


def test_coloured_residual_is_flagged(rng):
    """An AR(1) sequence with coefficient 0.3 (what a missed slow dynamic leaves behind)
    is not white, and the lags outside the 99 % band start at lag 1."""
    e = rng.standard_normal(2000)
    x = np.zeros_like(e)
    for k in range(1, len(e)):
        x[k] = 0.3 * x[k - 1] + e[k]
    out = diagnostics.whiteness(x)
    assert not out["white"]
    assert out["lags_outside_band"][0] == 1
    assert abs(out["autocorrelation"][0] - 0.3) < 4 / np.sqrt(len(x))


def test_input_correlation_detects_a_lagged_input_effect(rng):
    """A residual that contains the input delayed by 5 samples correlates with it at
    lag +5; an independent residual stays in the band (up to the 1 % false-alarm rate)."""
    u = rng.standard_normal(3000)
    r = 0.5 * np.roll(u, 5) + rng.standard_normal(3000)
    out = diagnostics.input_correlation(r, u)
    assert not out["independent"]
    lag = out["lags"][int(np.argmax(np.abs(out["cross_correlation"])))]
    assert lag == 5
    indep = diagnostics.input_correlation(rng.standard_normal(3000), u)
    assert len(indep["lags_outside_band"]) <= 2


@pytest.mark.slow  # 119 s in a 2-worker run (a degenerate fit wanders 62 steps); the warning's rule stays in CI
# (test_covariance)
def test_identifiability_warning_names_EI_and_rho_from_frequency_alone():
    """Free vibration of a (practically) clamped link measured at the tip: the response
    depends on EI and rho only through sqrt(EI/rho) (the mode shapes of a link without tip
    load do not depend on either), so the fit must warn that it cannot separate them,
    naming both, while EI/rho itself is well determined."""
    chain = fd.Chain(
        [fd.FlexibleLink(0.5, 0.2, 1.0, n_modes=1, damping_ratio=0.02)],
        hubs=[fd.Hub(inertia=1e6)],
    )
    t = np.arange(0.0, 1.0, 2e-3)
    rng = np.random.default_rng(3)
    log = identify.simulate_log(
        chain,
        t,
        initial={"q1_1": 1e-3},
        channels=("tip1",),
        noise={"tip1": 2e-5},
        rng=rng,
        fit_initial=("q1_1",),
    )
    params = [identify.Parameter("link1.EI", 1.2, 0.1, 10.0), identify.Parameter("link1.rho", 0.25, 0.02, 2.0)]
    problem = identify.make_problem(chain, params, [log], noise={"tip1": 2e-5})
    result = identify.fit(problem, params, n_stages=1, estimate_noise=False, max_steps=40)
    assert result.identifiability, "expected a warning that EI and rho cannot be separated"
    combo = result.identifiability[0]["combination"]
    assert "link1.EI" in combo and "link1.rho" in combo
    ratio = result.values[0] / result.values[1]
    assert ratio == pytest.approx(1.0 / 0.2, rel=1e-3)
