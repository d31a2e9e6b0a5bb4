"""Uncertainty that survives model error: cluster-robust intervals, clusters = logs.

`FitResult`'s intervals are `s^2 (J^T J)^-1`: right when the residuals are white noise,
far too narrow when they are mostly model error, as on real rigs (the residual of a
viscous pendulum model on a real pendulum is a slow, smooth misfit, correlated over whole
swings). `clustered_uncertainty(result)` makes no assumption about how the residuals of one
log are correlated, only that different logs are independent: the sandwich estimator of
Liang & Zeger (1986, Biometrika 73:13) with each log a cluster and its nuisances (initial
state, offsets) profiled out (`identify.covariance.clustered`):

    Cov = L/(L-1) A^+ (sum_l g_l g_l^T) A^+,   A = sum_l S~_l^T S~_l,   g_l = S~_l^T r_l

`S~_l`: log `l`'s Jacobian of the shared parameters with its own nuisance columns projected
out; `g_l`: its score at the optimum. Intervals: `x +- t_{L-1, (1+level)/2} SE` in the
natural coordinate (`log theta` for positive parameters), Student's t with `L - 1` degrees
of freedom because the variance is estimated from `L` clusters. Use it with several logs:
with 4 logs the interval is wide and itself uncertain (3 degrees of freedom); with 20-30
it is a usable error bar. `tests/identify/test_covariance.py` checks the estimator against
the sampling distribution of a Monte-Carlo experiment with correlated noise.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
import scipy.stats

from . import covariance
from .fit import FitResult, jacobian_blocks_at


@dataclasses.dataclass
class ClusteredUncertainty:
    """Cluster-robust standard errors and intervals of a fit's shared parameters.

    `names`, `values` (SI, as in the `FitResult`), `std_errors` (same units as the values),
    `ci_low`, `ci_high` (at `level`), `dof = n_logs - 1` (of the t quantile),
    `covariance` (natural coordinates: `log theta` for log-scaled parameters, in the order
    of `names`), `log_scale`."""

    names: list[str]
    values: np.ndarray
    std_errors: np.ndarray
    ci_low: np.ndarray
    ci_high: np.ndarray
    level: float
    n_logs: int
    dof: int
    covariance: np.ndarray
    log_scale: tuple[bool, ...]
    # what the data do not determine (`identify.covariance.NullSpace`); None: everything
    null_space: covariance.NullSpace | None = None

    def interval(self, fn, h: float = 1e-6, *, log: bool = False) -> tuple[float, float, float]:
        """Value and interval of a combination `fn(values: dict) -> float` of the
        parameters (delta method in natural coordinates, central differences of step `h`);
        an infinite interval where the data do not determine the combination.

        `log=True`, for a combination that is positive by nature (an inertia, a damping, a
        ratio of them): the delta method on `ln fn`, `fn exp(+-q SE(ln fn))`, an interval
        that stays positive and, for a single positive parameter, is the one `summary()`
        gives. Without it the interval is symmetric in `fn` and can reach below zero when
        the data determine the combination poorly (found in review: a joint damping's
        interval [-3.7e-6, 2.5e-5] N m s/rad beside the summary's [2.8e-6, 4.1e-5])."""
        is_log = np.asarray(self.log_scale)
        x0 = np.where(is_log, np.log(self.values), self.values)

        def of(x):
            return float(fn(dict(zip(self.names, np.where(is_log, np.exp(x), x).tolist()))))

        f0 = of(x0)
        if log and not f0 > 0:
            raise ValueError(f"interval(log=True): the combination must be positive, it is {f0!r} at the estimate")
        g = (lambda x: math.log(of(x))) if log else of
        grad = np.array([(g(x0 + h * e) - g(x0 - h * e)) / (2 * h) for e in np.eye(len(x0))])
        if self.null_space is not None and not self.null_space.determines(grad):
            se = float("inf")  # the combination moves along a direction the data do not see
        else:
            se = float(np.sqrt(max(grad @ self.covariance @ grad, 0.0)))
        q = scipy.stats.t.ppf(0.5 + self.level / 2, self.dof)
        if log:
            return f0, f0 * math.exp(-q * se), f0 * math.exp(q * se)
        return f0, f0 - q * se, f0 + q * se

    def summary(self) -> str:
        pct = f"{100 * self.level:g}%"
        lines = [
            f"cluster-robust uncertainty ({self.n_logs} logs as clusters, t with {self.dof} dof)",
            f"{'parameter':<28} {'value':>12} {'std err':>10} {pct + ' CI':>25}",
        ]
        for i, n in enumerate(self.names):
            ci = covariance.interval_text(self.ci_low[i], self.ci_high[i], self.std_errors[i])
            d = max(5, covariance.digits(self.values[i], self.std_errors[i]))
            lines.append(f"{n:<28} {self.values[i]:>12.{d}g} {self.std_errors[i]:>10.3g} {ci:>25}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {
            "method": "cluster-robust sandwich (Liang & Zeger 1986), clusters = logs, CR1, Student t",
            "n_logs": self.n_logs,
            "dof": self.dof,
            "level": self.level,
            "parameters": [
                {
                    "name": n,
                    "value": float(self.values[i]),
                    "std_error": float(self.std_errors[i]),
                    "ci": [float(self.ci_low[i]), float(self.ci_high[i])],
                }
                for i, n in enumerate(self.names)
            ],
        }


def clustered_uncertainty(result: FitResult, level: float = 0.95) -> ClusteredUncertainty:
    """Cluster-robust standard errors and intervals of `result`'s shared parameters, each
    log a cluster (module docstring). Uses the Jacobian the fit's covariance came from
    (`FitResult.jacobian_blocks`), else recomputes it at the optimum (one forward-mode
    solve per log). Raises `ValueError` with no more logs than free parameters (the
    covariance would be singular) or a `level` outside (0, 1)."""
    if not 0.0 < level < 1.0:
        raise ValueError(f"clustered_uncertainty: level expected a probability in (0, 1), got {level!r}")
    problem = result.problem
    n_logs = int(problem.t.shape[0])
    if n_logs < 2:
        raise ValueError(
            "clustered_uncertainty: needs at least 2 logs (each log is a cluster); this fit has "
            f"{n_logs}. Cut a long log into segments, or use the FitResult's white-noise intervals"
        )
    n_params = len(result.names)
    if n_logs <= n_params:
        # the per-log scores sum to zero at the optimum: their outer products span at most
        # n_logs - 1 directions, and the others would get a variance of 0 (found in review:
        # 3 logs, 3 parameters, an interval 60x too narrow that missed the truth)
        raise ValueError(
            f"clustered_uncertainty: {n_logs} log{'s' if n_logs != 1 else ''} (clusters) for {n_params} free "
            "parameters; the cluster-robust "
            f"covariance has rank at most {n_logs - 1}, so some combinations of the parameters would get a "
            "variance of zero and intervals far too narrow. It needs more logs than free parameters (5 or more is "
            "better: `identify fit` uses it from 5); cut long logs into segments, or use the FitResult's "
            "white-noise intervals"
        )
    x = np.array([np.log(v) if lg else v for v, lg in zip(result.values, problem.log_scale)], float)
    blocks = result.jacobian_blocks
    if blocks is None:
        sigma = jnp.asarray([result.sigma[c] for c in problem.channels], dtype=float)
        blocks = jacobian_blocks_at(problem, jnp.asarray(x), result.z, sigma, result.step)
    cov, null = covariance.clustered(*blocks, null_space=True)
    se_nat = np.where(null.undetermined(), np.inf, np.sqrt(np.clip(np.diag(cov), 0.0, None)))
    q = scipy.stats.t.ppf(0.5 + level / 2, n_logs - 1)
    log = np.asarray(problem.log_scale)
    values = np.asarray(result.values, float)
    se = np.where(log, values * se_nat, se_nat)
    lo = np.where(log, np.exp(x - q * se_nat), x - q * se_nat)
    hi = np.where(log, np.exp(x + q * se_nat), x + q * se_nat)
    return ClusteredUncertainty(
        names=list(result.names),
        values=values,
        std_errors=se,
        ci_low=lo,
        ci_high=hi,
        level=float(level),
        n_logs=n_logs,
        dof=n_logs - 1,
        covariance=cov,
        log_scale=tuple(bool(v) for v in problem.log_scale),
        null_space=null,
    )
