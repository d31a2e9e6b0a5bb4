"""Intervals of fits to quantised channels (`identify/_fit/rounding.py`) against a Monte
Carlo of the fits themselves: readings rounded to whole counts at a random phase of the
count edges, refitted by least squares each time, their estimates' spread compared with
the linearised propagation's standard error. The signal is a sine of a few counts' amplitude,
which returns to the same values every period, so the rounding errors repeat."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from identify._fit.covariance import Covariance
from identify._fit.rounding import RoundingModel, rounding_covariance

Q = 1.0  # one count
SIGMA = Q / np.sqrt(12.0)
T = 1500
AMPLITUDE = 2.3  # counts
OMEGA = 2 * np.pi * 0.013  # rad per sample: a period of ~77 samples
LEVELS = (0.0, 4.6)  # each log's offset (counts)
t = np.arange(T)
BASIS = np.sin(OMEGA * t)


def _readings(phases, analog=0.0, rng=None):
    noise = 0.0 if rng is None else analog * rng.standard_normal((len(LEVELS), T))
    y = AMPLITUDE * BASIS[None] + np.asarray(LEVELS)[:, None] + np.asarray(phases)[:, None]
    return Q * np.round((y + noise) / Q)


def _refit(m):
    """Least squares of the amplitude with an offset per log: the amplitude."""
    L = m.shape[0]
    X = np.zeros((L * T, 1 + L))
    X[:, 0] = np.tile(BASIS, L)
    for l in range(L):
        X[l * T : (l + 1) * T, 1 + l] = 1.0
    return np.linalg.lstsq(X, m.reshape(-1), rcond=None)[0][0]


def _blocks():
    L = len(LEVELS)
    S = np.broadcast_to(BASIS[None, :, None] / SIGMA, (L, T, 1)).copy()
    U = np.full((L, T, 1), 1.0 / SIGMA)
    slots = np.arange(L)[:, None]
    used = np.ones((L, T), bool)
    return S, U, slots, used


def _linearised(per_log: bool, analog: float = 0.0):
    S, U, slots, used = _blocks()
    y = AMPLITUDE * BASIS[None] + np.asarray(LEVELS)[:, None]
    measured = _readings(np.full(len(LEVELS), 0.3))  # any one realisation: the fitted outputs are y
    r = (y - measured) / np.hypot(SIGMA, analog)  # (model - measurement) / sigma
    sigma = np.hypot(SIGMA, analog)
    problem = SimpleNamespace(measured=measured[:, :, None])
    model = RoundingModel(np.array([Q]), np.array([sigma]), np.array([per_log]))
    white_se = sigma / np.sqrt(np.sum(BASIS**2) * len(LEVELS) - 0.0)
    cov = Covariance(1.0, len(LEVELS) * T, 1.0, np.array([white_se, 1.0, 1.0]), np.eye(1), np.ones(3), [])
    return rounding_covariance(model, problem, (r, S * SIGMA / sigma, U * SIGMA / sigma, slots, used), cov), white_se


def _monte_carlo(per_log: bool, analog: float = 0.0, trials: int = 3000):
    rng = np.random.default_rng(1)
    estimates = []
    for _ in range(trials):
        phase = rng.uniform(0, Q, len(LEVELS)) if per_log else np.full(len(LEVELS), rng.uniform(0, Q))
        estimates.append(_refit(_readings(phase, analog, rng if analog else None)))
    return np.std(estimates, ddof=1)


@pytest.mark.parametrize("per_log", [False, True])
def test_the_rounding_standard_error_matches_refits_over_random_count_phases(per_log):
    cov, white_se = _linearised(per_log)
    oracle = _monte_carlo(per_log)
    assert cov.method == "rounding"
    # the Monte Carlo's own error: ~1/sqrt(2 x 3000) = 1.3 % and ~1/sqrt(2 x 1000) = 2.2 %
    assert cov.std_errors[0] == pytest.approx(oracle, rel=0.08), (cov.std_errors[0], oracle, white_se)
    assert cov.std_errors[1:].tolist() == [1.0, 1.0]  # (the nuisances keep theirs)


def test_the_white_formula_is_off_where_the_rounding_repeats():
    """The case above, shared phase: the white formula's standard error is not the
    refits' spread (why the rounding model is used)."""
    cov, white_se = _linearised(False)
    oracle = _monte_carlo(False, trials=1000)
    assert abs(white_se / oracle - 1) > 0.3, (white_se, oracle)


def test_analog_noise_before_the_rounding_is_drawn_with_it():
    analog = 0.4 * Q
    cov, _ = _linearised(False, analog)
    oracle = _monte_carlo(False, analog, trials=2000)
    assert cov.std_errors[0] == pytest.approx(oracle, rel=0.08), (cov.std_errors[0], oracle)
