"""Goodness of fit against a model-free noise floor: does the fitted model explain the data
down to the sensor noise, or is it in a wrong basin (or missing an effect)?

A Levenberg-Marquardt fit that ends in a local minimum reports success: its steps have
stopped. Its cost alone cannot tell a wrong basin from the right one, because the noise
level that weights it is unknown (`identify.fit` re-estimates it from the residuals, so the
weighted cost is about the number of residuals at any optimum). A noise level estimated
from the data alone, without the model, can.

**Noise floor** (`noise_floor`): a difference-based estimator. The `ORDER`-th divided
difference of `ORDER + 1` consecutive samples (`ORDER` = 4),

    d_i = sum_j w_ij y_{i+j},   w_ij = 1 / prod_{m != j} (t_{i+j} - t_{i+m}),   j, m = 0..ORDER,

vanishes for any polynomial of degree below `ORDER`, and for additive white noise of
variance `sigma^2`, `E[d_i^2 / sum_j w_ij^2] = sigma^2`; the estimate is
`sqrt(mean(d_i^2 / sum_j w_ij^2))`. Order 2 is Gasser, Sroka & Jennen-Steinmetz's
pseudo-residual (1986, Biometrika 73, 625-633: the distance of each sample from the line
through its neighbours); on a uniform grid order `k` is the `k`-th difference normalised
by `sqrt(C(2k, k))`, the ordinary difference sequence, whose bias from the signal is the
smallest among difference sequences of its order (Dette, Munk & Wagner 1998, J. R. Stat.
Soc. B 60, 751-764). A smooth signal leaks in through its `ORDER`-th derivative: a sine of
amplitude `A` and frequency `f` sampled every `dt` adds
`A (2 sin(pi f dt))^k / sqrt(2 C(2k, k))` in quadrature (order `k`, uniform grid), so the
floor is an upper bound of the white noise, close to it for signals sampled well above
their frequencies. Order 4 rather than Gasser's 2, whose floor a swinging pendulum's
curvature dominates (docs/performance.md). Noise that is not white (a sensor's low-pass
filter correlating neighbouring samples) makes the floor smaller than the noise: a
first-order filter at a tenth of the sampling rate by a factor 0.59, at a twentieth by
0.42 (order 4; `tests/identify/test_noise_floor.py` has the closed form). The trace alone
cannot tell such noise from white noise plus signal leakage (the differences' lag-1
correlation hardly separates them: docs/performance.md), so no correction is made; a
fit's `poor_fit` warning says so.

**Ratio**: for each channel, the RMS of the fit's residuals over the floor (both pooled
over the logs, each log's floor from its own samples). A model that explains the data to
its white noise has a ratio about 1 (below 1 by the floor's signal leakage); a wrong basin
or a missing effect leaves the misfit in the residual. A channel is flagged when its ratio
exceeds `POOR_FIT` (2, i.e. the residual's variance 4 times the floor's); what 2 rests on
is in `identify.fit.fit`'s docstring (measured ratios of right and wrong basins).

A channel's floor never drops below `RESOLUTION` (1e-6) times its RMS: noise-free
(simulated) data then compare the fit's integration error with a 20-bit converter's
resolution instead of with zero.

**Quantisation.** A channel recorded with a step `q` (an encoder's count, an ADC's least
significant bit) carries the quantisation error `Q(y) - y`, which no model explains: for a
signal that crosses many steps it is uniform on `[-q/2, q/2]`, of standard deviation
`q / sqrt(12)` (Widrow & Kollar 2008, *Quantization Noise*, ch. 4-5; the error is then
nearly white). The difference estimator misses most of it when the signal moves less than a
step per sample: the error is then a sawtooth that stays put for many samples, smooth to
the 4th differences, and the floor came out 2.3x below `q / sqrt(12)` on a real encoder
(`tests/identify/test_noise_floor.py` simulates it). A declared step (`[sensors.<channel>]
resolution`, `identify.measurement.Sensor.resolution`) keeps the floor at least at
`q / sqrt(12)` (`series_floor`'s `resolution`): the floor is the noise a fit cannot go
below, so it is the larger of the two, not their sum (noise that dithers the signal
across steps is measured by the estimator, quantisation included).
"""

from __future__ import annotations

import math

import numpy as np

#: a channel is flagged when its residual RMS exceeds this many noise floors
POOR_FIT = 2.0
#: the order of the divided differences (module docstring)
ORDER = 4
#: the smallest floor, relative to the channel's RMS (see the module docstring)
RESOLUTION = 1e-6


def _check_series(t: np.ndarray, y: np.ndarray) -> None:
    if t.shape != y.shape or t.ndim != 1:
        raise ValueError(f"noise floor: t and y must be 1-D of the same length, got {t.shape} and {y.shape}")


def _weights(t: np.ndarray, order: int) -> tuple[list[np.ndarray], np.ndarray]:
    """The divided differences' weights `w_ij` (a list over `j` of arrays over `i`) at the
    strictly increasing times `t`, and their norms `sqrt(sum_j w_ij^2)`. The times are
    taken from their first: the differences of a ROS bag's stamps (1.7e9 s) would keep
    only 7 of their digits."""
    if np.any(np.diff(t) <= 0):
        raise ValueError("noise floor: t must be strictly increasing")
    t = t - t[0]
    n = len(t) - order
    ts = [t[j : j + n] for j in range(order + 1)]
    w = []
    for j in range(order + 1):
        prod = np.ones(n)
        for m in range(order + 1):
            if m != j:
                prod = prod * (ts[j] - ts[m])
        w.append(1.0 / prod)
    return w, np.sqrt(sum(wj**2 for wj in w))


def pseudo_residuals(t, y, order: int = ORDER) -> np.ndarray:
    """The normalised divided differences `d_i / sqrt(sum_j w_ij^2)` of order `order` of
    the samples `y` at times `t` (strictly increasing; module docstring): `len(t) - order`
    of them, each of variance `sigma^2` for white noise."""
    t, y = np.asarray(t, float), np.asarray(y, float)
    _check_series(t, y)
    n = len(t) - order
    if n <= 0:
        return np.zeros(0)
    w, norm = _weights(t, order)
    return sum(wj * y[j : j + n] for j, wj in enumerate(w)) / norm


#: `noise_floors` works through a long series this many samples at a time, so that its
#: temporaries (a dozen arrays of the chunk's length) stay small beside a 1 GB log
CHUNK = 1 << 20


def noise_floor(t, y, order: int = ORDER) -> float:
    """The model-free noise standard deviation of the samples `y` at times `t` (SI, the
    channel's unit; module docstring), 0 for `order` samples or fewer."""
    return noise_floors(t, [y], order)[0]


def noise_floors(t, ys, order: int = ORDER) -> list[float]:
    """`noise_floor` of each series of `ys` sampled at the same times `t`: the weights,
    which depend on the times alone, computed once for all of them. Overlapping chunks of
    `CHUNK` samples (each chunk's last `order` samples start the next), so a long log needs
    memory of one chunk, not of a dozen copies of the log."""
    t = np.asarray(t, float)
    ys = [np.asarray(y, float) for y in ys]
    for y in ys:
        _check_series(t, y)
    n = len(t) - order
    if n <= 0:
        return [0.0] * len(ys)
    totals = np.zeros(len(ys))
    for start in range(0, n, CHUNK):
        stop = min(start + CHUNK, n) + order
        w, norm = _weights(t[start:stop], order)
        m = stop - order - start
        for k, y in enumerate(ys):
            e = sum(wj * y[start + j : start + j + m] for j, wj in enumerate(w)) / norm
            totals[k] += float(np.dot(e, e))
    return [math.sqrt(total / n) for total in totals]


def quantisation_noise(resolution: float) -> float:
    """The standard deviation of uniform quantisation noise of step `resolution`:
    `resolution / sqrt(12)` (module docstring)."""
    return float(resolution) / math.sqrt(12.0)


def series_floor(t, y, resolution: float = 0.0) -> float:
    """The floor a fit of the samples `y` is judged against: `noise_floor`, at least
    `RESOLUTION` times their RMS (noise-free data) and at least the quantisation noise of
    the declared step `resolution` (SI, the channel's unit; 0: none declared)."""
    return series_floors(t, [y], [resolution])[0]


def series_floors(t, ys, resolutions) -> list[float]:
    """`series_floor` of each series of `ys` sampled at the same times `t`, with its
    declared step of `resolutions` (the weights computed once: `noise_floors`)."""
    ys = [np.asarray(y, float) for y in ys]
    floors = noise_floors(t, ys)
    out = []
    for y, floor, step in zip(ys, floors, resolutions, strict=True):
        rms = math.sqrt(float(np.dot(y, y)) / y.size) if y.size else 0.0
        out.append(max(floor, RESOLUTION * rms, quantisation_noise(step)))
    return out


def channel_floors(t, measured, valid, present, resolution=None) -> tuple[np.ndarray, np.ndarray]:
    """Per log and channel: the noise floor and the number of samples it stands for.

    `t` `(L, T)`, `measured` `(L, T, C)`, `valid` `(L, T)` (samples that exist),
    `present` `(L, C)` (channels a log records); `resolution` `(C,)`: each channel's
    declared quantisation step (SI, 0 for none; `series_floor`), or None for none. Returns
    `(floor, count)`, both `(L, C)`; 0 where a log does not record a channel."""
    t, measured = np.asarray(t, float), np.asarray(measured, float)
    valid, present = np.asarray(valid, bool), np.asarray(present, bool)
    L, _, C = measured.shape
    step = np.zeros(C) if resolution is None else np.asarray(resolution, float)
    floor, count = np.zeros((L, C)), np.zeros((L, C), int)
    for l in range(L):
        n = int(valid[l].sum())
        # (the valid samples are a log's first `n` unless `valid` says otherwise: views then)
        t_l, m_l = (t[l, :n], measured[l, :n]) if valid[l, :n].all() else (t[l, valid[l]], measured[l, valid[l]])
        recorded = np.flatnonzero(present[l])
        floors = series_floors(t_l, [m_l[:, j] for j in recorded], step[recorded])
        floor[l, recorded], count[l, recorded] = floors, n
    return floor, count


def pooled(mean_square, count) -> np.ndarray:
    """Per channel, the sample-weighted mean over the logs of `mean_square` `(L, C)` (each
    log's mean of a squared quantity, `count` `(L, C)` its samples): `(C,)`, NaN for a
    channel no log records."""
    mean_square, count = np.asarray(mean_square, float), np.asarray(count, float)
    n = count.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, np.sum(count * mean_square, axis=0) / n, np.nan)


def goodness(channels, residual_ms, floor, count) -> dict:
    """Per channel, pooled over the logs that record it (`pooled`): `{'residual_rms',
    'noise_floor', 'ratio', 'poor'}` (SI; `poor`: ratio above `POOR_FIT`). `residual_ms`
    `(L, C)`: each log's mean squared residual per channel; `floor`, `count`:
    `channel_floors`."""
    ms_all, f2_all = pooled(residual_ms, count), pooled(np.square(floor), count)
    out = {}
    for c, ms, f2 in zip(channels, ms_all, f2_all):
        if np.isnan(ms):
            continue
        ratio = float(np.sqrt(ms / f2)) if f2 > 0 else (0.0 if ms == 0 else float("inf"))
        out[c] = {
            "residual_rms": float(np.sqrt(ms)),
            "noise_floor": float(np.sqrt(f2)),
            "ratio": ratio,
            "poor": bool(ratio > POOR_FIT),
        }
    return out


def score(residual_ms, floor, count) -> float:
    """One number to compare two fits of the same logs (lower is better): the mean over
    the recorded channels of the squared ratio (`goodness`). Unlike the fit's cost it does
    not depend on the noise weights each fit re-estimated."""
    ms, f2 = pooled(residual_ms, count), pooled(np.square(floor), count)
    used = ~np.isnan(ms)
    return float(np.mean(ms[used] / np.maximum(f2[used], np.finfo(float).tiny)))


#: `declared_noise_warnings`: a declared noise this many times above or below the floor is
#: questioned. Generous: filtered sensor noise puts the floor below the noise (0.42x for a
#: first-order filter at a twentieth of the sampling rate) and a fast signal's leakage
#: puts it above.
NOISE_MISMATCH = 10.0


def declared_noise_warnings(declared: dict, quality: dict) -> list[str]:
    """Warnings for channels whose declared noise (`declared`: channel -> standard
    deviation, SI, or None when estimated) is more than `NOISE_MISMATCH` times its floor
    (`quality`: `goodness`' dict, e.g. `FitResult.fit_quality`), or less than 1 /
    `NOISE_MISMATCH` of it. A declared noise in the wrong unit is the usual cause (`"0.03"`
    meant as degrees and read as 0.03 rad is 57 times too large and widens every interval
    about 7x)."""
    from .units import display_unit

    out = []
    for c, sigma in declared.items():
        q = quality.get(c)
        if sigma is None or q is None or not q["noise_floor"] > 0:
            continue
        ratio = sigma / q["noise_floor"]
        if ratio > NOISE_MISMATCH or ratio < 1.0 / NOISE_MISMATCH:
            scale, unit = display_unit(c)
            out.append(
                f"the declared noise of {c} ({scale * sigma:.3g} {unit}) is {ratio:.3g} times the noise floor "
                f"estimated from the data ({scale * q['noise_floor']:.3g} {unit}): check its unit in [noise] "
                "(the fit weighs the channel, and sizes the intervals, by the declared value)"
            )
    return out
