"""The model-free noise floor (`identify.noise_floor`) against closed forms: white noise
(the estimator is unbiased), a sine's leakage `A (2 sin(pi f dt))^k / sqrt(2 C(2k, k))`,
the bias of first-order filtered noise, exact cancellation of a polynomial on an irregular
grid, the pooled ratio of several logs."""

from __future__ import annotations

from math import comb

import numpy as np
import pytest

from identify._data import noise_floor as nf


def _binomial(k: int) -> np.ndarray:
    """The k-th difference's coefficients, (-1)^(k-j) C(k, j)."""
    return np.array([(-1) ** (k - j) * comb(k, j) for j in range(k + 1)], float)


@pytest.mark.parametrize("order", [2, nf.ORDER])
def test_white_noise_on_an_irregular_grid_is_estimated_without_bias(order):
    """Gaussian noise of sd 0.3 on a line sampled at jittered times: the floor is 0.3 within
    5 standard errors. The normalised differences of neighbouring windows are correlated
    (`rho_m = sum_j b_j b_(j+m) / sum b^2` on a uniform grid), so the relative standard
    error of the floor is sqrt((1 + 2 sum_m rho_m^2) / (2 n)) (the jitter changes it little)."""
    rng = np.random.default_rng(0)
    n = 200_000
    t = np.cumsum(rng.uniform(0.5e-3, 1.5e-3, n))
    y = 2.0 - 7.0 * t + 0.3 * rng.standard_normal(n)
    b = _binomial(order)
    rho = [np.dot(b[: len(b) - m], b[m:]) / np.dot(b, b) for m in range(1, order + 1)]
    se = np.sqrt((1 + 2 * np.sum(np.square(rho))) / (2 * n))
    assert nf.noise_floor(t, y, order) == pytest.approx(0.3, rel=5 * se)


def test_a_polynomial_of_degree_below_the_order_leaves_no_floor():
    t = np.cumsum(np.random.default_rng(1).uniform(1e-3, 3e-3, 500))
    y = 0.4 + 3.0 * t - 2.0 * t**2 + 5.0 * t**3
    assert nf.noise_floor(t, y) < 1e-9 * np.std(y)
    assert nf.noise_floor(t, y, order=2) > 1e-6  # order 2 cancels only lines


@pytest.mark.parametrize("order", [2, nf.ORDER])
@pytest.mark.parametrize("f_hz, dt", [(10.0, 1e-3), (4.2, 4e-3), (40.0, 1e-3)])
def test_a_sines_leakage_is_its_closed_form(order, f_hz, dt):
    """Uniform samples of A sin(2 pi f t), noise-free: the k-th difference is a sine of
    amplitude A (2 sin(pi f dt))^k, so over whole periods the floor is
    A (2 sin(pi f dt))^k / sqrt(2 C(2k, k))."""
    A = 0.7
    t = np.arange(0.0, 50.0 / f_hz, dt)
    expected = A * (2 * np.sin(np.pi * f_hz * dt)) ** order / np.sqrt(2 * comb(2 * order, order))
    assert nf.noise_floor(t, A * np.sin(2 * np.pi * f_hz * t), order) == pytest.approx(expected, rel=2e-2)


@pytest.mark.parametrize("a", [0.53, 0.73])
def test_filtered_noise_makes_the_floor_smaller_by_its_closed_form(a):
    """AR(1) noise `e_i = a e_(i-1) + w_i` (a first-order low-pass; `a = exp(-2 pi fc dt)`:
    0.53 at a tenth of the sampling rate, 0.73 at a twentieth) has autocorrelation
    `a^|m|`, so the k-th difference's mean square is `var(e) sum_ij b_i b_j a^|i-j|`: the
    floor is `sqrt(sum_ij b_i b_j a^|i-j| / C(2k, k))` of the noise (0.59 and 0.42 at order
    4, the module docstring's)."""
    rng = np.random.default_rng(2)
    n = 400_000
    w = rng.standard_normal(n)
    e = np.empty(n)
    e[0] = w[0] / np.sqrt(1 - a**2)
    for i in range(1, n):
        e[i] = a * e[i - 1] + w[i]
    t = np.arange(n) * 1e-3
    k = nf.ORDER
    b = _binomial(k)
    i = np.arange(k + 1)
    factor = np.sqrt(b @ (a ** np.abs(i[:, None] - i[None, :])) @ b / comb(2 * k, k))
    assert nf.noise_floor(t, e) / np.std(e) == pytest.approx(factor, rel=0.02)
    assert factor == pytest.approx({0.53: 0.59, 0.73: 0.42}[a], abs=0.01)


@pytest.mark.parametrize("a", [0.0, 0.53, 0.95])
def test_filtered_noise_barely_moves_the_differences_lag_one_correlation(a):
    """Why the floor is not corrected for coloured noise (module docstring): the lag-1
    correlation of the normalised 4th differences of AR(1) noise is
    `sum_ij b_i b_j a^|i-j+1| / sum_ij b_i b_j a^|i-j|`, -0.8 for white noise and within
    0.05 of it for any `a`, against -0.71 for white noise plus a slow sine of 5 % of its
    variance."""
    import scipy.signal

    rng = np.random.default_rng(5)
    n = 400_000
    e = scipy.signal.lfilter([1.0], [1.0, -a], rng.standard_normal(n))[1000:]
    t = np.arange(e.size) * 1e-3
    b = _binomial(nf.ORDER)
    i = np.arange(nf.ORDER + 1)
    lag = i[:, None] - i[None, :]
    closed = (b @ (a ** np.abs(lag + 1)) @ b) / (b @ (a ** np.abs(lag)) @ b) if a else -0.8
    d = nf.pseudo_residuals(t, e)
    assert np.corrcoef(d[:-1], d[1:])[0, 1] == pytest.approx(closed, abs=0.01)
    assert -0.8 <= closed <= -0.75
    # white noise plus a sine whose leakage through the 4th difference has 5 % of the
    # noise's variance (leakage RMS A (2 sin(pi f dt))^4 / sqrt(140); A = 1000, f = 36 Hz)
    amp, dt = 1000.0, 1e-3
    f = np.arcsin((np.sqrt(0.05 * 2 * comb(8, 4)) / amp) ** 0.25 / 2) / (np.pi * dt)
    t = np.arange(n) * dt
    d = nf.pseudo_residuals(t, rng.standard_normal(n) + amp * np.sin(2 * np.pi * f * t))
    assert np.corrcoef(d[:-1], d[1:])[0, 1] == pytest.approx((-0.8 + 0.05) / 1.05, abs=0.01)


def test_goodness_pools_logs_by_their_samples_and_flags_a_poor_channel():
    """Two logs, two channels (log 1 records only the first): the pooled RMS and floor are
    the sample-weighted root mean squares; a channel whose residual is 4 floors is poor,
    one at 1.3 is not."""
    residual_ms = np.array([[1.0, 16.0], [2.0, 0.0]])
    floor = np.array([[1.0, 1.0], [1.0, 0.0]])
    count = np.array([[100, 100], [300, 0]])
    q = nf.goodness(("a", "b"), residual_ms, floor, count)
    assert q["a"]["residual_rms"] == pytest.approx(np.sqrt((100 * 1 + 300 * 2) / 400))
    assert q["a"]["noise_floor"] == pytest.approx(1.0)
    assert not q["a"]["poor"] and q["b"]["poor"] and q["b"]["ratio"] == pytest.approx(4.0)
    assert nf.score(residual_ms, floor, count) == pytest.approx(((100 + 600) / 400 + 16) / 2)


def test_channel_floors_skip_padding_and_missing_channels():
    """Padded samples (`valid` False) do not enter a log's floor; a channel a log does not
    record has floor and count 0; a constant channel's floor is `RESOLUTION` of its RMS."""
    rng = np.random.default_rng(3)
    t = np.tile(np.arange(1000) * 1e-3, (2, 1))
    measured = np.zeros((2, 1000, 2))
    measured[0, :, 0] = 0.1 * rng.standard_normal(1000)
    measured[0, 600:, 0] = 1e3  # padding of a shorter log: must not count
    measured[1, :, 0] = 5.0
    valid = np.ones((2, 1000), bool)
    valid[0, 600:] = False
    present = np.array([[True, False], [True, False]])
    floor, count = nf.channel_floors(t, measured, valid, present)
    assert floor[0, 0] == pytest.approx(nf.noise_floor(t[0, :600], measured[0, :600, 0]))
    assert 0.08 < floor[0, 0] < 0.12
    assert floor[1, 0] == pytest.approx(nf.RESOLUTION * 5.0)
    assert count.tolist() == [[600, 0], [1000, 0]] and floor[0, 1] == 0.0


def test_bad_samples_are_refused_with_a_message():
    with pytest.raises(ValueError, match="strictly increasing"):
        nf.noise_floor([0.0, 1.0, 1.0, 2.0, 3.0, 4.0], [0.0, 1.0, 2.0, 3.0, 4.0, 5.0])
    with pytest.raises(ValueError, match="same length"):
        nf.noise_floor([0.0, 1.0, 2.0], [0.0, 1.0])


def test_a_declared_noise_in_the_wrong_unit_is_questioned():
    """0.03 deg of white noise on a swing: declared as 0.03 (rad, the review's mistake) it is
    ~57 times the floor and questioned; declared right (0.03 deg), or estimated, it is not."""
    from identify._data.noise_floor import declared_noise_warnings, series_floor

    rng = np.random.default_rng(3)
    t = np.arange(2000) * 5e-3
    sigma = np.deg2rad(0.03)
    y = 0.5 * np.sin(2 * np.pi * 1.3 * t) + sigma * rng.normal(size=t.size)
    quality = {"theta1": {"noise_floor": series_floor(t, y)}}
    (warning,) = declared_noise_warnings({"theta1": 0.03}, quality)
    assert warning.startswith("the declared noise of theta1 (1.72 deg) is 5") and "check its unit" in warning
    assert declared_noise_warnings({"theta1": sigma}, quality) == []
    assert declared_noise_warnings({"theta1": None}, quality) == []
    assert len(declared_noise_warnings({"theta1": sigma / 20}, quality)) == 1  # too small, too


def _encoder_swing(offset=0.3, periods=4):
    """A slow swing, 20.25 counts in amplitude, recorded by a 4096-count encoder (step
    `q` = 2 pi / 4096 rad) at 1 kHz, moving at most 0.1 count per sample: `(t, y, q)`."""
    q, dt = 2 * np.pi / 4096, 1e-3
    amplitude = 20.25 * q
    omega = 0.1 * q / (amplitude * dt)
    t = np.arange(0.0, periods * 2 * np.pi / omega, dt)
    return t, offset + amplitude * np.sin(omega * t), q


@pytest.mark.parametrize("offset", [0.0, 0.3, 0.3 + 0.4 * 2 * np.pi / 4096])
def test_a_quantised_slow_signal_hides_its_quantisation_noise_unless_its_resolution_is_declared(offset):
    """The finding (a real encoder's floor 2.3x below its quantisation noise), simulated.
    The samples rounded to the step q carry the error Q(y) - y, uniform on [-q/2, q/2] for
    a signal crossing many steps (Widrow & Kollar 2008): RMS q / sqrt(12) (checked on the
    samples, within 5 % for these four periods). Between steps the staircase's 4th
    differences vanish; an isolated step of q adds q (1, -3, 3, -1) to the four that span
    it, so the floor is exactly q sqrt((20 / 70) T / (N - 4)) for T steps in N samples:
    here 0.46 of q / sqrt(12). Declared, the floor is q / sqrt(12)."""
    t, y, q = _encoder_swing(offset)
    counts = q * np.round(y / q)
    noise = q / np.sqrt(12)
    assert np.std(counts - y) == pytest.approx(noise, rel=0.05)
    steps = np.count_nonzero(np.diff(counts))
    assert np.max(np.abs(np.diff(counts))) == pytest.approx(q, rel=1e-9)  # one count at a time
    staircase = q * np.sqrt(20 / 70 * steps / (len(t) - 4))
    assert nf.noise_floor(t, counts) == pytest.approx(staircase, rel=0.005)
    assert nf.series_floor(t, counts) < 0.5 * noise  # the finding: more than 2x below
    assert nf.series_floor(t, counts, resolution=q) == pytest.approx(noise, rel=1e-12)
    assert nf.quantisation_noise(q) == noise
    # the same through channel_floors, per channel (a second channel without a resolution)
    measured = np.stack([counts, counts], axis=-1)[None]
    floor, _ = nf.channel_floors(t[None], measured, np.ones((1, len(t)), bool), np.ones((1, 2), bool), [q, 0.0])
    np.testing.assert_allclose(floor[0], [noise, nf.series_floor(t, counts)], rtol=1e-12)


def test_a_dithered_quantised_signal_is_measured_and_the_declared_step_changes_nothing():
    """Gaussian noise of sd q added before the rounding dithers the signal across the steps:
    the quantisation error is then uniform and independent of the signal and the noise
    (Widrow & Kollar 2008, ch. 5), the recorded noise of variance q^2 + q^2 / 12, which the
    estimator measures (within 4 standard errors: 1.146 / sqrt(n), the 4th differences'
    correlation, `identify.held_out.FLOOR_SE`). Declaring the step keeps that: the floor is
    the larger of the two, not their sum."""
    t, y, q = _encoder_swing()
    counts = q * np.round((y + q * np.random.default_rng(3).standard_normal(len(t))) / q)
    se = 1.146 / np.sqrt(len(t) - nf.ORDER)
    assert nf.noise_floor(t, counts) == pytest.approx(q * np.sqrt(1 + 1 / 12), rel=4 * se)
    assert nf.series_floor(t, counts, resolution=q) == nf.series_floor(t, counts)


@pytest.mark.parametrize("n", [5, 6, 7, 64, 65, 66, 67, 1000])
def test_the_floor_of_a_long_series_is_taken_in_chunks_without_changing_it(monkeypatch, n):
    """`noise_floor` works through overlapping chunks (`CHUNK` samples, small here): the
    same value as from all pseudo-residuals at once, for lengths about the chunk edges."""
    monkeypatch.setattr(nf, "CHUNK", 61)
    rng = np.random.default_rng(n)
    t = np.cumsum(rng.uniform(0.5, 1.5, n)) * 1e-3
    y = np.sin(7 * t) + rng.normal(0, 0.01, n)
    e = nf.pseudo_residuals(t, y)
    assert nf.noise_floor(t, y) == pytest.approx(float(np.sqrt(np.mean(e**2))), rel=1e-13)
    # several series at the same times: the weights once, each series' own floor
    z = np.cos(3 * t) + rng.normal(0, 0.1, n)
    e_z = nf.pseudo_residuals(t, z)
    assert nf.noise_floors(t, [y, z]) == pytest.approx([nf.noise_floor(t, y), np.sqrt(np.mean(e_z**2))], rel=1e-13)
    assert nf.series_floors(t, [y, z], [0.0, 1.0]) == pytest.approx([nf.series_floor(t, y), 1 / np.sqrt(12)])
