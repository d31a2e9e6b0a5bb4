"""Residual tests after a fit, as MATLAB's `resid` does: whiteness (autocorrelation)
and independence from the input (input-residual cross-correlation).

For `N` residuals of a white sequence the sample autocorrelation at each lag is
approximately normal with standard deviation `1/sqrt(N)`; we report the 99 %
band `2.576/sqrt(N)`, the lags outside it, and the Ljung-Box statistic
`Q = N (N + 2) sum_k rho_k^2 / (N - k)` with its chi-square p-value (lags
1..`max_lag`). The same band applies to the cross-correlation with the input
at lags `-max_lag..max_lag`.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

Z99 = 2.5758293035489004


def _xcorr(a: np.ndarray, b: np.ndarray, max_lag: int) -> np.ndarray:
    """Normalised cross-correlation `r_ab(k) = sum a[t+k] b[t] / (N sd_a sd_b)`, k = -max_lag..max_lag."""
    a = a - a.mean()
    b = b - b.mean()
    n = len(a)
    denom = n * a.std() * b.std()
    out = np.zeros(2 * max_lag + 1)
    if denom == 0:
        return out
    for i, k in enumerate(range(-max_lag, max_lag + 1)):
        out[i] = np.dot(a[max(k, 0) : n + min(k, 0)], b[max(-k, 0) : n - max(k, 0)]) / denom
    return out


def whiteness(residual: np.ndarray, max_lag: int = 25) -> dict:
    """Autocorrelation test of one residual sequence (uniformly sampled)."""
    residual = np.asarray(residual, float)
    n = len(residual)
    max_lag = int(min(max_lag, n // 4))
    rho = _xcorr(residual, residual, max_lag)[max_lag + 1 :]
    band = Z99 / np.sqrt(n)
    k = np.arange(1, max_lag + 1)
    q = float(n * (n + 2) * np.sum(rho**2 / (n - k)))
    p = float(stats.chi2.sf(q, max_lag))
    return {
        "lags": k.tolist(),
        "autocorrelation": rho.tolist(),
        "band99": float(band),
        "lags_outside_band": [int(x) for x in k[np.abs(rho) > band]],
        "ljung_box_q": q,
        "p_value": p,
        "white": bool(p > 0.01),
    }


def input_correlation(residual: np.ndarray, inp: np.ndarray, max_lag: int = 25) -> dict:
    """Cross-correlation of a residual with an input sequence."""
    residual = np.asarray(residual, float)
    n = len(residual)
    max_lag = int(min(max_lag, n // 4))
    r = _xcorr(residual, np.asarray(inp, float), max_lag)
    band = Z99 / np.sqrt(n)
    lags = np.arange(-max_lag, max_lag + 1)
    return {
        "lags": lags.tolist(),
        "cross_correlation": r.tolist(),
        "band99": float(band),
        "lags_outside_band": [int(x) for x in lags[np.abs(r) > band]],
        "independent": bool(np.all(np.abs(r) <= band)),
    }
