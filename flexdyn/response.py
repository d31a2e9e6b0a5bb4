"""Step-response metrics and spectral peak picking for simulated (or measured) responses.

Host-side NumPy, for the tables papers 002 and 004 report: rise time, settling time and
percentage overshoot of a joint-angle response (paper 002, Table II) and the resonance
frequencies read from the power spectral density of an end-point acceleration (paper 002,
Table III). All times in s, frequencies in Hz; the signal's unit is carried through.

Definitions (the papers give none; these are the usual control-textbook ones, e.g. Ogata,
*Modern Control Engineering*, sec. 5-3, with the final value made explicit):

- **initial value** `y0`: the first sample, `y[0]`.
- **final value** `y_f`: the mean of the samples with `t >= t[-1] - final_window`
  (`final_window = 0` takes the last sample). A mean over a window rather than the last
  sample, because a lightly damped response still ripples at the end of the record.
- **step size** `A = y_f - y0`; every metric is relative to `|A|` and follows its sign, so a
  response that moves in the negative direction is handled like a positive one.
- **rise time**: the time between the first crossings of `y0 + 0.1 A` and `y0 + 0.9 A`
  (10-90 %), crossings located by linear interpolation between samples.
- **settling time**: the first time after which `|y - y_f| <= band |A|` for the rest of the
  record (`band = 0.02`: the 2 % criterion), located by linear interpolation on the last
  sample that is outside the band; 0 if the response never leaves the band.
- **overshoot**: `100 max(sign(A) (y - y_f)) / |A|` per cent, clipped at 0 (a response that
  never passes its final value has no overshoot).

Spectra: `psd` is the one-sided periodogram of the mean-removed signal with a Hann window,
density scaling (unit^2 / Hz, so the integral over frequency is the signal's variance),
optionally zero-padded. Its resolution is set by the record length `T`: the Hann main lobe
is `4 / T` Hz wide (zero-padding interpolates the same spectrum, it does not resolve more).
`resonance_peaks` takes the most prominent local maxima (in decades of the PSD) in a band, at least
`min_separation` apart, and refines each by a parabola through the three log-PSD samples
around it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = [
    "StepResponse",
    "final_value",
    "overshoot",
    "prominence",
    "psd",
    "resonance_peaks",
    "rise_time",
    "settling_time",
    "step_response",
]


def _as_series(t, y):
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    if t.ndim != 1 or y.shape != t.shape or t.size < 3:
        raise ValueError(f"expected 1-D t and y of the same length >= 3, got shapes {t.shape} and {y.shape}")
    if not np.all(np.diff(t) > 0):
        raise ValueError("t must be strictly increasing")
    return t, y


def final_value(t, y, final_window: float = 0.0) -> float:
    """Mean of `y` over the last `final_window` seconds of the record (the last sample if 0)."""
    t, y = _as_series(t, y)
    return float(np.mean(y[t >= t[-1] - final_window]))


def _step(t, y, final_window, y_final):
    t, y = _as_series(t, y)
    y_f = final_value(t, y, final_window) if y_final is None else float(y_final)
    amplitude = y_f - y[0]
    if amplitude == 0.0:
        raise ValueError("the response has no net change (final value == initial value): no step metrics")
    # normalised response: 0 at the start, 1 at the final value, whatever the direction
    return t, (y - y[0]) / amplitude, abs(amplitude)


def _first_crossing(t, s, level):
    above = np.nonzero(s >= level)[0]
    if above.size == 0:
        return np.nan
    k = above[0]
    if k == 0:
        return float(t[0])
    return float(t[k - 1] + (level - s[k - 1]) * (t[k] - t[k - 1]) / (s[k] - s[k - 1]))


def rise_time(t, y, final_window: float = 0.0, low: float = 0.1, high: float = 0.9, y_final=None) -> float:
    """Time (s) from the first crossing of `low` to the first crossing of `high` of the
    step (fractions of `y_f - y0`; 10-90 % by default). NaN if `high` is never reached."""
    t, s, _ = _step(t, y, final_window, y_final)
    return _first_crossing(t, s, high) - _first_crossing(t, s, low)


def settling_time(t, y, final_window: float = 0.0, band: float = 0.02, y_final=None) -> float:
    """Time (s, from `t[0]`) after which the response stays within `band` (fraction of
    `|y_f - y0|`; 2 % by default) of its final value until the end of the record."""
    t, s, _ = _step(t, y, final_window, y_final)
    err = np.abs(s - 1.0)
    outside = np.nonzero(err > band)[0]
    if outside.size == 0:
        return 0.0
    k = outside[-1]
    if k == t.size - 1:
        return np.nan  # still outside at the end of the record: not settled
    # linear interpolation of |error| between the last sample outside and the next one
    frac = (err[k] - band) / (err[k] - err[k + 1])
    return float(t[k] + frac * (t[k + 1] - t[k]) - t[0])


def overshoot(t, y, final_window: float = 0.0, y_final=None) -> float:
    """Percentage overshoot `100 max(y - y_f) / |y_f - y0|` in the direction of the step
    (0 if the response never passes its final value)."""
    t, s, _ = _step(t, y, final_window, y_final)
    return float(max(0.0, 100.0 * np.max(s - 1.0)))


class StepResponse(NamedTuple):
    """Rise time (s), settling time (s), overshoot (%), initial and final value of a response."""

    rise_time: float
    settling_time: float
    overshoot: float
    initial_value: float
    final_value: float


def step_response(t, y, final_window: float = 0.0, band: float = 0.02) -> StepResponse:
    """All step metrics of one response, with the definitions of the module docstring."""
    t, y = _as_series(t, y)
    y_f = final_value(t, y, final_window)
    return StepResponse(
        rise_time(t, y, y_final=y_f),
        settling_time(t, y, band=band, y_final=y_f),
        overshoot(t, y, y_final=y_f),
        float(y[0]),
        y_f,
    )


def psd(x, dt: float, n_fft: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One-sided power spectral density of a uniformly sampled signal.

    Hann-windowed periodogram of `x - mean(x)`, density scaling:
    `P(f) = c |FFT(w x)|^2 / (fs sum(w^2))` with `c = 2` except at 0 and Nyquist, so that
    `sum(P) df = var(x)` (Parseval; `df = fs / n_fft`). `x` may have trailing channel axes
    (e.g. the x and y components of an acceleration, shape `(T, 2)`): the PSDs of the
    channels are summed (the trace of the spectral matrix, which for a vector signal does
    not depend on the axes' orientation). `n_fft >= len(x)` zero-pads.

    **Returns:** `(f, P)`: frequencies (Hz) and PSD (unit^2/Hz).
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[0]
    if n < 4:
        raise ValueError(f"psd: need at least 4 samples, got {n}")
    n_fft = n if n_fft is None else int(n_fft)
    if n_fft < n:
        raise ValueError(f"psd: n_fft={n_fft} is shorter than the signal ({n} samples)")
    fs = 1.0 / float(dt)
    w = np.hanning(n)
    w = w.reshape((n,) + (1,) * (x.ndim - 1))
    spec = np.fft.rfft((x - x.mean(axis=0)) * w, n=n_fft, axis=0)
    P = np.abs(spec) ** 2 / (fs * np.sum(w**2))
    P[1 : (n_fft + 1) // 2] *= 2.0  # one-sided: fold the negative frequencies (not DC, not Nyquist)
    if P.ndim > 1:
        P = P.reshape(P.shape[0], -1).sum(axis=1)
    return np.fft.rfftfreq(n_fft, dt), P


def prominence(P, k) -> np.ndarray:
    """Topographic prominence of the samples `k` of `P` (in `P`'s unit): the height of each
    above the higher of the two lowest points between it and the nearest higher sample on
    either side (or the end of the array), as for mountain peaks (and `scipy.signal.peak_prominences`)."""
    P = np.asarray(P, dtype=float)
    out = []
    for i in np.atleast_1d(k):
        higher_left = np.nonzero(P[:i] > P[i])[0]
        lo = higher_left[-1] + 1 if higher_left.size else 0
        higher_right = np.nonzero(P[i + 1 :] > P[i])[0]
        hi = i + 1 + higher_right[0] if higher_right.size else P.size
        out.append(P[i] - max(P[lo : i + 1].min(), P[i:hi].min()))
    return np.asarray(out)


def resonance_peaks(
    f, P, n_peaks: int, fmin: float = 0.0, fmax: float = np.inf, min_prominence: float = 0.0, min_separation=0.0
):
    """Frequencies (Hz, ascending) of the `n_peaks` most prominent local maxima of a spectrum.

    Candidates are the local maxima of `P` strictly inside `[fmin, fmax]` (a band edge is
    not a peak). They are ranked by their prominence in decades, `prominence(log10 P)`
    computed over the band (how far a peak stands out of the spectrum around it, so the
    ripple of a window's side lobes on a steep slope does not count as a resonance), those
    below `min_prominence` decades dropped, and taken from the most prominent down, skipping
    any closer than `min_separation` Hz to one already taken. Each is refined by the vertex
    of the parabola through `log P` at the three samples around it (within a small fraction
    of a bin for the Hann window's main lobe). Fewer than `n_peaks` come back if there are
    fewer such maxima.

    **Returns:** `(frequencies, prominences)`, arrays ordered by frequency (Hz, decades).
    """
    f = np.asarray(f, dtype=float)
    P = np.asarray(P, dtype=float)
    if f.shape != P.shape or f.ndim != 1:
        raise ValueError(f"resonance_peaks: f and P must be 1-D of the same length, got {f.shape} and {P.shape}")
    logP = np.log10(np.maximum(P, np.finfo(float).tiny))
    band = np.nonzero((f >= fmin) & (f <= fmax))[0]
    if band.size < 3:
        return np.zeros(0), np.zeros(0)
    lo, hi = band[0], band[-1]
    k = np.arange(max(lo, 1), min(hi, f.size - 2) + 1)
    k = k[(logP[k] > logP[k - 1]) & (logP[k] >= logP[k + 1]) & (k > lo) & (k < hi)]
    prom = prominence(logP[lo : hi + 1], k - lo) if k.size else np.zeros(0)
    keep = prom >= min_prominence
    k, prom = k[keep], prom[keep]
    order = np.argsort(prom)[::-1]
    picked = []
    for j in order:
        if all(abs(f[k[j]] - f[k[p]]) >= min_separation for p in picked):
            picked.append(j)
        if len(picked) == n_peaks:
            break
    picked = sorted(picked, key=lambda j: k[j])
    if not picked:
        return np.zeros(0), np.zeros(0)
    kk, pp = k[picked], prom[picked]
    a, b, c = logP[kk - 1], logP[kk], logP[kk + 1]
    curv = a - 2.0 * b + c
    delta = np.where(curv < 0, 0.5 * (a - c) / np.where(curv < 0, curv, -1.0), 0.0)
    return f[kk] + delta * (f[kk + 1] - f[kk]), pp
