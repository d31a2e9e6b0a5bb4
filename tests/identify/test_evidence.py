"""`identify.evidence`: the decay law of a free oscillation's half swings (oracles: the
closed-form free vibration with viscous damping and with dry friction), and the model
checks: the spin rates read from the simulated angle channels and the
geometric-stiffening check built on `flexdyn.stiffening` (whose coefficients are tested
against the Ritz oracle in tests/flexdyn/test_stiffening.py)."""

import math

import numpy as np
import oracles
import pytest

import flexdyn as fd
from identify._diagnose import evidence as ev

L, RHO, EI = 0.5, 0.2, 1.0  # paper 002's link as in test_fit's spinning-link fit
SCALE = math.sqrt(EI / (RHO * L**4))  # rad/s; the first clamped frequency is 3.5160 SCALE


def _traces(**channels):
    t = np.linspace(0.0, 2.0, 2001)
    return t, {"log1": {"t": t, "baseline": {c: f(t) for c, f in channels.items()}}}


def test_spin_rates_come_from_phi_or_the_sum_of_joint_angles():
    chain = fd.Chain([fd.RigidLink(0.3, 0.2), fd.RigidLink(0.3, 0.2), fd.RigidLink(0.3, 0.2)])
    _, traces = _traces(theta1=lambda t: 0.5 * np.sin(3.0 * t), theta2=lambda t: 2.0 * t, phi3=lambda t: -4.0 * t)
    rates = ev.link_spin_rates(chain, traces)
    assert rates["link1"] == pytest.approx(1.5, rel=1e-5)  # max |d theta1/dt| = 0.5 * 3
    assert rates["link2"] == pytest.approx(3.5, rel=1e-5)  # theta1 + theta2: 1.5 + 2 at t = 0
    assert rates["link3"] == pytest.approx(4.0, rel=1e-9)
    # no angle channel for a link: unknown, not zero
    _, tips = _traces(tip1=lambda t: 1e-3 * np.sin(t))
    assert ev.link_spin_rates(fd.Chain([fd.RigidLink(0.3, 0.2)]), tips) == {"link1": None}


def test_rms_spin_rates_pool_every_sample_of_every_log():
    """Closed forms: a sine swing a sin(w t) over whole periods has RMS rate a w / sqrt(2);
    a constant rate is its own RMS; two logs pool their squares sample by sample."""
    chain = fd.Chain([fd.RigidLink(0.3, 0.2), fd.RigidLink(0.3, 0.2)])
    w = 2 * np.pi  # 2 whole periods in the 2 s of `_traces`
    _, traces = _traces(theta1=lambda t: 0.5 * np.sin(w * t), phi2=lambda t: -4.0 * t)
    rms = ev.link_spin_rms(chain, traces)
    assert rms["link1"] == pytest.approx(0.5 * w / np.sqrt(2), rel=1e-3)
    assert rms["link2"] == pytest.approx(4.0, rel=1e-9)
    _, other = _traces(theta1=lambda t: 3.0 * t)
    both = {"a": traces["log1"], "b": other["log1"]}  # equal lengths: the mean of the two mean squares
    assert ev.link_spin_rms(chain, both)["link1"] == pytest.approx(np.sqrt(((0.5 * w) ** 2 / 2 + 9.0) / 2), rel=1e-3)
    assert ev.link_spin_rms(chain, both)["link2"] == pytest.approx(4.0, rel=1e-9)  # log b has no angle for it
    assert ev.link_spin_rms(chain, other)["link2"] is None  # unknown, not zero


def test_a_link_spinning_at_half_its_first_frequency_is_flagged_with_the_ei_bias():
    chain = fd.Chain([fd.FlexibleLink(L, RHO, EI, n_modes=2)])
    rate = 2.0 * SCALE  # lam = 2: 0.569 of the first clamped frequency
    (check,) = ev.stiffening_checks(chain, {"link1": rate})
    assert check["link"] == "link1" and check["flagged"]
    assert check["first_frequency_rad_s"] == pytest.approx(3.5160153 * SCALE, rel=1e-6)
    assert check["relative_shift_spin"] == pytest.approx(1.1933 * (2.0 / 3.5160153) ** 2, rel=1e-4)
    assert check["relative_shift_gravity"] == 0.0  # horizontal plane
    assert "geometric_stiffening = true" in check["message"] and "link1" in check["message"]
    # slow: below the threshold, not flagged
    (slow,) = ev.stiffening_checks(chain, {"link1": 0.05 * SCALE})
    assert not slow["flagged"] and "adequate" in slow["message"]
    # unknown rate: said so; gravity alone decides
    (unknown,) = ev.stiffening_checks(chain, {"link1": None})
    assert unknown["relative_shift_spin"] is None and not unknown["flagged"]
    assert "spin rate unknown" in unknown["message"]


def test_gravity_flags_a_long_floppy_vertical_link_and_stiffened_or_rigid_links_are_skipped():
    # paper 000's strip: at 0.30 m (the paper's pendulum) gravity changes omega_1^2 by 0.4 %,
    # at 1.0 m by 15 % (tests/flexdyn/test_stiffening.py, against the Ritz oracle)
    strip = fd.rigs.flexible_pendulum(n_modes=2).links[0]
    for length, flagged in ((0.30, False), (1.0, True)):
        link = fd.FlexibleLink(length, strip.rho, strip.EI, n_modes=2)
        (check,) = ev.stiffening_checks(fd.Chain([link], gravity=(0.0, -9.81)), {"link1": 0.0})
        assert check["flagged"] == flagged, check
    assert check["relative_shift_gravity"] == pytest.approx(0.147, abs=0.005)
    stiffened = fd.FlexibleLink(1.0, 0.4, 0.3, n_modes=2, geometric_stiffening=True)
    assert ev.stiffening_checks(fd.Chain([stiffened], gravity=(0.0, -9.81)), {"link1": 0.0}) == []
    assert ev.stiffening_checks(fd.Chain([fd.RigidLink(0.3, 0.2)]), {"link1": 5.0}) == []


@pytest.mark.parametrize("offset", [0.5, 1.0])
def test_a_link_at_the_end_of_a_spinning_link_feels_its_roots_centripetal_pull(offset):
    """Paper 002's link at the end of a rigid link of length R = offset * l, the pair spinning
    straight at Omega: the tension is N(x) = rho Omega^2 (R (l - x) + (l^2 - x^2)/2), so to
    first order omega_1^2 rises by (spin + R gravity) Omega^2. Oracle: the slope of the
    Ritz solution with that tension (tests/oracles.py); the angles are the traces a spinning
    chain would record."""
    chain = fd.Chain([fd.RigidLink(offset * L, 0.1), fd.FlexibleLink(L, RHO, EI, n_modes=2)])
    rate = 0.5 * SCALE
    t, traces = _traces(theta1=lambda t: rate * t, theta2=lambda t: 0.0 * t)
    accelerations = ev.link_root_accelerations(chain, traces)
    assert accelerations["link1"] == 0.0
    # central differences of the sampled angles: relative error (Omega dt)^2 / 12 = 1.7e-6
    assert accelerations["link2"] == pytest.approx(rate**2 * offset * L, rel=1e-5)
    (check,) = ev.stiffening_checks(chain, ev.link_spin_rates(chain, traces), accelerations)
    h = 1e-2
    w2 = lambda lam2: (
        oracles.axially_loaded_cantilever_frequencies(  # noqa: E731
            lambda x: lam2 * ((1 - x * x) / 2 + offset * (1 - x)), 0.0, 0.0, 10
        )[0]
        ** 2
    )
    slope = (w2(h) - w2(-h)) / (2 * h)  # d omega~^2 / d lam^2
    expected = slope * (rate / SCALE) ** 2 / w2(0.0)
    assert check["relative_shift_spin"] == pytest.approx(expected, rel=1e-5)
    assert "root accelerating" in check["message"]
    # without the angles of the links before it, the root's motion is unknown: left out
    _, partial = _traces(phi2=lambda t: rate * t)
    assert ev.link_root_accelerations(chain, partial)["link2"] is None


def test_joint_ringing_at_a_links_root_counts_by_its_mean_axial_pull():
    """Review (two-link arm, elastic joints): the peak of the raw second derivative of the
    first link's angle (45-78 Hz joint ringing) was counted as link 2's axial pull, a 64 %
    stiffening of its first mode. Oracle: link 1 ringing as `A sin(nu t)` with link 2 in
    line; its root's acceleration is `R A nu^2 sin(nu t)` across link 2 (bends it) and
    `-R (A nu cos(nu t))^2` along it, whose mean over the mode's period (many ringing
    periods) is `R A^2 nu^2 / 2`. The old measure, the peak of the acceleration's
    magnitude, `R A nu^2`, was 2/A = 200 times more."""
    R, A, nu = 0.3, 0.01, 2 * np.pi * 60.0
    chain = fd.Chain([fd.RigidLink(R, 0.1), fd.FlexibleLink(L, RHO, EI, n_modes=2)])
    t = np.arange(0.0, 4.0, 1e-4)
    traces = {"log1": {"t": t, "baseline": {"theta1": A * np.sin(nu * t), "theta2": 0.0 * t}}}
    raw = ev.link_root_accelerations(chain, traces)["link2"]
    assert raw == pytest.approx(R * A * nu**2 * A, rel=0.05)  # the axial part only: R (A nu)^2 at its peak
    (check,) = ev.stiffening_checks_of(chain, traces)
    assert 2 * np.pi / SCALE / 3.516 > 10 * 2 * np.pi / nu  # the mode's period spans many ringing periods
    assert check["root_acceleration_max_m_s2"] == pytest.approx(R * A**2 * nu**2 / 2, rel=0.05), check
    assert "% from its root's pull)" in check["message"], check["message"]


def _measured(x, t, rng, offset=0.09, noise=2e-3, lsb=1.5e-3):
    """`x(t)` as an encoder logs it: off its centre by `offset`, noisy, quantised by `lsb`
    (flat tops at the turning points, as on the real pendulum's logs)."""
    return np.round((x + offset + noise * rng.standard_normal(t.size)) / lsb) * lsb


def test_half_swings_of_a_viscously_damped_oscillation_decay_exponentially():
    """Oracle: `A e^(-zeta w t) cos(w_d t)` has half swings `A_k` with `log A_k` linear in
    t at slope `-zeta w` (each half swing is the mean of two extrema a constant ratio
    apart). The log's offset and quantised plateaus do not matter (the old envelope,
    |extrema| about the final mean, alternated between two sequences on such a log)."""
    rng = np.random.default_rng(0)
    w, zeta = 2 * np.pi * 1.27, 0.005
    t = np.arange(0.0, 12.0, 1e-3)
    x = 0.5 * np.exp(-zeta * w * t) * np.cos(w * math.sqrt(1 - zeta**2) * t)
    law = ev.decay_law(t, _measured(x, t, rng), noise=2e-3)
    assert law["best"] == "exponential" and law["r2"]["exponential"] > 0.999, law
    assert law["exponential_rate_per_s"] == pytest.approx(zeta * w, rel=0.02)
    assert law["n_half_swings"] == pytest.approx(2 * 1.27 * 12, abs=2)
    # an encoder's noise below its step, the noise not given (the report's plot of a
    # simulated trace): the step itself sets the hysteresis (found in review: 151 swings)
    law = ev.decay_law(t, _measured(x, t, rng, noise=3e-4))
    assert law["best"] == "exponential" and law["n_half_swings"] == pytest.approx(2 * 1.27 * 12, abs=2), law


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_release_from_rest_keeps_its_first_half_swing_and_a_start_mid_swing_adds_no_partial_one(seed):
    """Oracle: `A e^(-zeta w t) cos(w t + phase)`. Released from rest (phase 0) the log's
    first sample is the first turning point: the first half swing is `(A + A e^(-zeta pi))
    / 2` (half the drop from the release to the first minimum). Started mid-swing (phase
    0.2 pi or 0.5 pi) the start is not a turning point: every half swing is a whole one
    (within the decay of one half period of the previous), none the partial start."""
    w, zeta, amplitude = 2 * np.pi * 1.27, 0.005, 0.5
    t = np.arange(0.0, 12.0, 1e-3)
    decay = np.exp(-zeta * np.pi)  # per half period
    x = amplitude * np.exp(-zeta * w * t) * np.cos(w * t)
    tp, a = ev.swing_amplitudes(t, _measured(x, t, np.random.default_rng(seed)), noise=2e-3)
    assert a[0] == pytest.approx(0.5 * amplitude * (1 + decay), rel=0.01)
    assert tp[0] == pytest.approx(0.5 * np.pi / w, rel=0.05)
    assert len(a) == int(12.0 * w / np.pi)  # turning points at k pi / w, k = 0 .. 30
    for phase in (0.2 * np.pi, 0.5 * np.pi):
        x = amplitude * np.exp(-zeta * w * t) * np.cos(w * t + phase)
        tp, a = ev.swing_amplitudes(t, _measured(x, t, np.random.default_rng(seed)), noise=2e-3)
        whole = amplitude * np.exp(-zeta * w * tp) * 0.5 * (1 + 1 / decay)  # mean of its two extrema
        np.testing.assert_allclose(a, whole, rtol=0.02)


def test_half_swings_under_dry_friction_fall_linearly():
    """Oracle: Coulomb friction `F` on an oscillator of stiffness `k` (closed form, half
    period by half period): each half swing is about the centre `+-F/k` on the side it
    starts from, and the extrema fall by `2 F / k` per half period `pi / w`, so the half
    swings fall linearly at `2 (F/k) w / pi` per second."""
    rng = np.random.default_rng(1)
    w, a = 2 * np.pi * 1.27, 4e-3  # a = F / k, rad
    t = np.arange(0.0, 12.0, 1e-3)
    k = np.floor(t * w / np.pi).astype(int)  # half period index
    mag = 0.5 - 2 * a * k  # |extremum| starting half period k
    sign = (-1.0) ** k
    centre = sign * a
    x = centre + (sign * mag - centre) * np.cos(w * t - np.pi * k)
    law = ev.decay_law(t, _measured(x, t, rng), noise=2e-3)
    assert law["best"] == "linear" and law["r2"]["linear"] > 0.999, law
    assert -law["linear_slope_per_s"] == pytest.approx(2 * a * w / np.pi, rel=0.02)


def test_no_decay_law_is_named_for_an_envelope_none_fits():
    """Half swings of random sizes: no law reaches `DECAY_R2_MIN`, and it says so."""
    rng = np.random.default_rng(2)
    w = 2 * np.pi
    t = np.arange(0.0, 10.0, 1e-3)
    sizes = rng.uniform(0.2, 1.0, 40)
    x = sizes[np.floor(t * w / np.pi).astype(int)] * np.sin(w * t)
    law = ev.decay_law(t, x, noise=1e-3)
    assert law["best"] == "inconclusive" and max(law["r2"].values()) < ev.DECAY_R2_MIN, law


def test_a_spectrum_peak_of_white_noise_is_within_the_noise_and_a_line_above_it_is_significant():
    """Oracle: Fisher's test. Over 200 records of white Gaussian noise (2,000 samples), the
    largest residual peak is called significant in about PEAK_FALSE_ALARM = 1 % of them
    (binomial: at most 8 of 200 with probability > 0.999 if the rate is 1 %); a sinusoid of
    amplitude 0.3 sigma at 37.3 Hz (power 0.045 sigma^2 over 2,000 samples: ~15x the
    background of the Hann periodogram at its bin) is found at its frequency and called
    significant in every record; so is one 6x larger on AR(1) noise (coefficient 0.95),
    whose own steep spectrum is not called significant (at most 2 of 20 records)."""
    n = 2000
    t = np.arange(n) * 1e-3
    false = 0
    for seed in range(200):
        peaks = ev.spectrum_peaks(t, np.random.default_rng(seed).normal(size=n), [40.0])
        false += any(p["significant"] for p in peaks)
        assert all(p["above_background"] is None or p["above_background"] > 0 for p in peaks)
    assert false <= 8
    line = 0.3 * np.sin(2 * np.pi * 37.3 * t)
    ar_false = 0
    for seed in range(20):
        e = np.random.default_rng(seed).normal(size=n)
        peak = ev.spectrum_peaks(t, e + line, [40.0])[0]
        assert abs(peak["frequency_hz"] - 37.3) < 0.5 and peak["significant"] and peak["nearest_mode_hz"] == 40.0
        ar = np.zeros(n)
        for i in range(1, n):
            ar[i] = 0.95 * ar[i - 1] + e[i]
        ar_false += any(p["significant"] for p in ev.spectrum_peaks(t, ar, []))
        # (the AR spectrum is 18x white noise's at 37.3 Hz and 400x near 0 Hz: a line 6x
        # larger, among its 10 largest peaks)
        on_ar = [p for p in ev.spectrum_peaks(t, ar + 6 * line, [], n_peaks=10) if p["significant"]]
        assert any(abs(p["frequency_hz"] - 37.3) < 0.5 for p in on_ar)
    assert ar_false <= 2
    # a slow swing (3 periods in the log) is a trend: not judged, and said so
    slow = ev.spectrum_peaks(t, np.sin(2 * np.pi * 1.5 * t), [])[0]
    assert slow["significant"] is None and "a trend, not judged" in ev._peak_text(slow)
