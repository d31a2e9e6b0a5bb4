"""Intervals of fits to quantised channels: the sensors' rounding propagated through the fit.

`s^2 (J^T J)^-1` (`identify.covariance`) treats each residual as a new, independent draw.
A quantised channel (`Sensor.resolution`: an encoder's count, a gauge's ADC step) breaks
that in a way no correlation estimate along the log sees. Its rounding error is a fixed
function of the signal and of the sensor's zero, `e = q round((y + phi) / q) - (y + phi)`,
with `phi` the unknown phase of the count edges (where the encoder was homed, the gauge
nulled). Wherever the signal returns to the same values (a hub held still, a tip ringing
over a few counts, every log of one session), the errors repeat, at lags of a ringing
period or between logs. `identify/_fit/hac.py`'s bandwidth of a few samples misses that.
On the servo example the residuals were nearly white (lag-1 autocorrelation 0.02-0.1)
while the joint damping and dry friction scattered 1.6-1.7 times their white standard
errors over seeded phases.

So for a fit with quantised channels the shared parameters' covariance is that of the
linearised estimate under the sensors' own error model, by Monte Carlo over `draws`
phases (a linearised parametric bootstrap, with no refits):

    Cov_SS = c A^+ E[g g^T] A^+,   g = sum_l S~_l^T e_l,   A = sum_l S~_l^T S~_l,

- `S~_l = (I - P_l) S_l`: log `l`'s shared Jacobian columns with its own nuisances
  (initial state, offsets) projected out, as in `identify.covariance.clustered`;
- `e_l`: the weighted rounding errors of a draw about the fitted outputs `y = m + r sigma`.
  The phase is uniform over one count, one per channel shared by all logs (homed or
  nulled once). A channel whose offset is fitted per log has one phase per log (its zero
  moves between logs). Analog noise of variance `sigma^2 - q^2 / 12`, where the channel's
  noise level exceeds the rounding's, is added before rounding (it dithers the counts).
- channels without a resolution add their white part `sum_l S~_l,w^T S~_l,w`.
  Their weighted noise has unit variance, and it is independent of the rounding.
- `c = max(1, s^2)`: a residual above the noise model (model error) widens the intervals
  as in the white formula; the noise model never narrows them below it.

With no quantised channel this is the white formula with `s^2` floored at 1. The draws use
a fixed seed: the same fit gives the same intervals. Their Monte Carlo error is about
`1 / sqrt(2 draws)` of each standard error. The nuisances keep their white standard
errors. Checked against the spread of refits over seeded phases on the servo example
(`tests/identify/test_servo_flexible_link_coverage.py`) and against a Monte Carlo of
quantised straight-line fits (`tests/identify/test_rounding.py`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._data import measurement as meas
from .covariance import Covariance, _correlation, _Svd, projected_shared

#: Monte Carlo draws of the sensors' phases (and analog noise)
ROUNDING_DRAWS = 1000
#: the draws' seed: the intervals are reproducible
ROUNDING_SEED = 20261208
_CHUNK_VALUES = 10_000_000  # residuals x draws per batch (memory: ~3 arrays of this many doubles)


@dataclasses.dataclass(frozen=True)
class RoundingModel:
    """The sensors' error model over the residual grid `(L, T, C)`: each channel's step
    `q` (0: not quantised), noise level `sigma` (the fit's weights), and whether its phase
    is drawn per log."""

    q: np.ndarray  # (C,)
    sigma: np.ndarray  # (C,)
    per_log: np.ndarray  # (C,) bool

    @property
    def quantised(self) -> np.ndarray:
        return self.q > 0

    def errors(self, fitted: np.ndarray, rng: np.random.Generator, n: int) -> np.ndarray:
        """`n` draws of the weighted rounding errors about the outputs `fitted` `(L, T, C)`:
        `(n, L, T, C)`, 0 on the channels without a resolution."""
        L, T, C = fitted.shape
        q = np.where(self.quantised, self.q, 1.0)
        phase = rng.uniform(0.0, 1.0, (n, L, 1, C))
        phase = np.where(self.per_log, phase, phase[:, :1])  # one phase per channel unless per log
        analog = np.sqrt(np.clip(self.sigma**2 - self.q**2 / 12.0, 0.0, None))
        x = fitted[None] + phase * q
        noisy = x + rng.standard_normal((n, L, T, C)) * analog
        e = (q * np.round(noisy / q) - x) / self.sigma
        return np.where(self.quantised, e, 0.0)


def model_of(problem, sigma) -> RoundingModel | None:
    """The rounding model of `problem`'s channels (`Measurement`'s resolutions), or None
    when none is quantised."""
    q = meas.resolutions(problem.measurement, problem.channels)
    if not np.any(q > 0):
        return None
    per_log = np.zeros(len(problem.channels), bool)
    for _, c in problem.offset_free:
        per_log[c] = True
    return RoundingModel(q, np.asarray(sigma, float), per_log)


def rounding_covariance(model: RoundingModel, problem, blocks, cov: Covariance, *, draws: int = ROUNDING_DRAWS):
    """`cov` with its shared parameters' standard errors and correlation from the
    sensors' rounding (module docstring); `blocks` = `(r, S, U, slots, used)` at the
    optimum (`identify.jacobian.jacobian_blocks_at`), `r` `(L, T C)` ordered sample then
    channel. Parameters `cov` marks undetermined stay so."""
    r, S, U, slots, used = blocks
    L, n, P = S.shape
    C = len(model.q)
    T = n // C
    if P == 0:
        return cov
    used = np.asarray(used, bool)
    St = projected_shared(np.asarray(S), np.asarray(U), np.asarray(slots), used)  # (L, n, P)
    svd = _Svd.of(St.reshape(L * n, P), np.sqrt(np.sum(np.asarray(S) ** 2, axis=(0, 1))))
    bread = svd.normal_pinv()
    white = np.tile(~model.quantised, T)[None, :] & used  # (L, n): residuals of unquantised channels
    Sw = St * white[:, :, None]
    meat = np.einsum("lnp,lnq->pq", Sw, Sw)
    measured = np.asarray(problem.measured, float)  # (L, T, C)
    fitted = np.where(used.reshape(L, T, C), measured + np.asarray(r).reshape(L, T, C) * model.sigma, 0.0)
    rng = np.random.default_rng(ROUNDING_SEED)
    done = 0
    chunk = max(1, min(draws, _CHUNK_VALUES // max(L * n, 1)))
    while done < draws:
        k = min(chunk, draws - done)
        e = model.errors(fitted, rng, k).reshape(k, L, n) * used[None]
        g = np.einsum("klm,lmp->kp", e, St)  # (k, P)
        meat += g.T @ g / draws
        done += k
    c = max(1.0, cov.residual_variance)
    shared = c * bread @ meat @ bread
    undetermined = ~np.isfinite(cov.std_errors[:P])
    se = cov.std_errors.copy()
    se[:P] = np.where(undetermined, np.inf, np.sqrt(np.clip(np.diag(shared), 0.0, None)))
    return dataclasses.replace(cov, std_errors=se, correlation=_correlation(shared, undetermined), method="rounding")
