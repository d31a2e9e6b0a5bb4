"""flexdyn.response against closed forms: first- and second-order step responses, sinusoids' spectra."""

import math

import numpy as np
import pytest
from scipy.optimize import brentq

from flexdyn import response

ZETA, OMEGA = 0.3, 2 * math.pi * 1.5  # damping ratio, natural frequency (rad/s)


def second_order(t, zeta=ZETA, omega=OMEGA):
    """Unit step response of omega^2 / (s^2 + 2 zeta omega s + omega^2)."""
    wd = omega * math.sqrt(1 - zeta**2)
    return 1 - np.exp(-zeta * omega * t) * (np.cos(wd * t) + zeta / math.sqrt(1 - zeta**2) * np.sin(wd * t))


def test_first_order_closed_forms():
    T = 0.4
    t = np.linspace(0.0, 12 * T, 200_001)
    y = 1 - np.exp(-t / T)
    # t90 - t10 = T ln(0.9 / 0.1); 2 % settling T ln 50; no overshoot (final value given: the exact 1)
    assert response.rise_time(t, y, y_final=1.0) == pytest.approx(T * math.log(9.0), rel=1e-6)
    assert response.settling_time(t, y, y_final=1.0) == pytest.approx(T * math.log(50.0), rel=1e-6)
    assert response.overshoot(t, y, y_final=1.0) == 0.0
    # with the last sample as final value (1 - e^-12) the rise time moves by ~e^-12 only
    assert response.step_response(t, y).rise_time == pytest.approx(T * math.log(9.0), rel=1e-4)


def test_second_order_overshoot_rise_settling():
    t = np.linspace(0.0, 8.0, 80_001)
    y = second_order(t)
    m = response.step_response(t, y, final_window=0.0)
    assert m.final_value == pytest.approx(1.0, abs=1e-6)
    # peak overshoot exp(-pi zeta / sqrt(1 - zeta^2)) (Ogata eq. 5-21)
    assert m.overshoot == pytest.approx(100 * math.exp(-math.pi * ZETA / math.sqrt(1 - ZETA**2)), rel=1e-5)
    # 10-90 % rise: crossings of the analytic response found by root finding
    t10 = brentq(lambda s: second_order(s) - 0.1, 1e-6, 0.5)
    t90 = brentq(lambda s: second_order(s) - 0.9, 0.01, 0.5)
    assert m.rise_time == pytest.approx(t90 - t10, rel=1e-5)
    # 2 % settling: the last time |y - 1| = 0.02, by root finding between the response's extrema
    wd = OMEGA * math.sqrt(1 - ZETA**2)
    extrema = np.arange(1, 40) * math.pi / wd
    last = max(k for k, te in enumerate(extrema) if abs(second_order(te) - 1) > 0.02)
    ts_exact = brentq(lambda s: abs(second_order(s) - 1) - 0.02, extrema[last], extrema[last + 1])
    assert response.settling_time(t, y, y_final=1.0) == pytest.approx(ts_exact, rel=1e-5)
    # and the textbook envelope estimate 4 / (zeta omega) is in the right range (envelope above the response)
    assert ts_exact <= -math.log(0.02 * math.sqrt(1 - ZETA**2)) / (ZETA * OMEGA)


def test_negative_step_and_offset_are_handled_like_positive():
    t = np.linspace(0.0, 8.0, 8001)
    y = second_order(t)
    a = response.step_response(t, y)
    b = response.step_response(t, 0.7 - 2.5 * y)  # starts at 0.7, moves to -1.8
    assert b.rise_time == pytest.approx(a.rise_time, rel=1e-9)
    assert b.settling_time == pytest.approx(a.settling_time, rel=1e-9)
    assert b.overshoot == pytest.approx(a.overshoot, rel=1e-9)
    assert b.final_value == pytest.approx(0.7 - 2.5 * y[-1])


def test_final_window_and_unsettled_response():
    t = np.linspace(0.0, 10.0, 10_001)
    y = 1.0 - np.exp(-5 * t) + 0.1 * np.sin(2 * math.pi * 2.0 * t) * (t > 1)  # ripples +-10 % to the end, mean 1
    assert response.final_value(t, y, final_window=2.0) == pytest.approx(1.0, abs=1e-3)
    # never stays in the 2 % band: settled only at the very end of the record (the last zero crossing of the ripple)
    assert response.settling_time(t, y, final_window=2.0) > 9.9
    # still outside the band at the last sample: not settled at all
    assert math.isnan(response.settling_time(t[:-100], y[:-100], final_window=2.0))
    with pytest.raises(ValueError):
        response.step_response(t, np.ones_like(t))  # no net change: no step metrics


def test_psd_parseval_and_sinusoid_peaks():
    dt = 1e-3
    t = np.arange(5000) * dt
    f1, f2, f3 = 2.83, 7.31, 23.1
    x = 3.0 * np.sin(2 * math.pi * f1 * t) + np.sin(2 * math.pi * f2 * t + 0.4)
    x += 0.2 * np.cos(2 * math.pi * f3 * t)
    f, P = response.psd(x, dt, n_fft=2**14)
    # the integral of the density is the mean power sum(A^2 / 2) (windowed, so to ~1 % over 5 s)
    assert np.sum(P) * (f[1] - f[0]) == pytest.approx((9.0 + 1.0 + 0.04) / 2, rel=1e-2)
    peaks, prom = response.resonance_peaks(f, P, 3, 1.0, 60.0)
    np.testing.assert_allclose(peaks, [f1, f2, f3], atol=0.02)  # a tenth of the 0.2 Hz bin
    # ranking is by prominence in decades (contrast with the spectrum around), not by height: asking for one
    # returns one of the tones, and min_prominence drops nothing real here (every tone stands out by decades)
    one, _ = response.resonance_peaks(f, P, 1, 1.0, 60.0)
    assert np.min(np.abs(one[0] - np.array([f1, f2, f3]))) < 0.02
    assert np.all(prom > 3.0)
    # band limits: a tone outside the band is not returned, and the band edge is not a peak
    # (the Hann window's side lobes are local maxima too, with deep nulls between them once zero-padded, so they
    # count as peaks; the tone's main lobe stands out most)
    mid, _ = response.resonance_peaks(f, P, 1, 5.0, 15.0)
    np.testing.assert_allclose(mid, [f2], atol=0.02)


def test_psd_of_vector_signal_is_rotation_invariant():
    rng = np.random.default_rng(1)
    x = rng.standard_normal((4096, 2))
    c, s = math.cos(0.7), math.sin(0.7)
    xr = x @ np.array([[c, -s], [s, c]]).T
    np.testing.assert_allclose(response.psd(x, 1e-3)[1], response.psd(xr, 1e-3)[1], rtol=1e-10)


def test_prominence_ignores_ripple_on_a_slope():
    f = np.linspace(0.0, 50.0, 5001)
    logP = -0.1 * f + 0.05 * np.sin(2 * math.pi * f / 0.5) + 2.0 * np.exp(-((f - 30.0) ** 2) / 2.0)
    peaks, prom = response.resonance_peaks(f, 10**logP, 1, 1.0, 49.0, min_prominence=0.5)
    assert peaks == pytest.approx([30.0], abs=0.1)
    assert prom[0] > 1.0
