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
from .jacobian import jacobian_blocks_at
from .result import FitResult


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
        the data determine the combination poorly (where `summary()`'s interval of a
        positive parameter, `log=True`'s, does not)."""
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
    if problem.per_log:
        raise ValueError(
            f"clustered_uncertainty: {', '.join(repr(n) for n, _ in problem.per_log)} is fitted per log "
            "(Parameter.per_log): each log's value is informed by that log (cluster) alone, whose score is zero at "
            "the optimum, so its cluster-robust variance would be zero. Use the FitResult's white-noise intervals"
        )
    n_params = len(result.names)
    if n_logs <= n_params:
        # the per-log scores sum to zero at the optimum: their outer products span at most
        # n_logs - 1 directions, and the others would get a variance of 0: intervals far too
        # narrow (tens of times, for as many logs as parameters)
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


#: `between_logs`: a parameter whose logs' values have a chi-square p-value below this
#: differs between the logs beyond their intervals
DISAGREEMENT_P = 0.01


@dataclasses.dataclass
class BetweenLogs:
    """Do independent fits of several logs (`identify.fit_independent`) agree? Per
    parameter (`names`, in the natural coordinate: `log theta` for log-scaled ones, where
    the standard error is relative):

    - `mean`, `mean_se`: the inverse-variance weighted mean of the logs' values (SI) and its
      standard error (SI, from the logs' own standard errors);
    - `chi2`, `dof = n - 1`, `p`: `chi2 = sum_l ((x_l - mean) / se_l)^2` and its p-value
      under the hypothesis that every log measures the same value with its stated error
      (chi-square with n - 1 degrees of freedom);
    - `birge`: `sqrt(chi2 / dof)` (the Birge ratio: ~1 when the spread is what the
      intervals say; the factor by which they understate it otherwise);
    - `spread`: the logs' relative standard deviation (log-scaled) or standard deviation
      (SI);
    - `differs`: `p < DISAGREEMENT_P`: the value changes from log to log (a parameter that
      really varies, such as a payload), or every log's intervals are too narrow (a model
      error common to the logs: compare `identify.clustered_uncertainty`).

    `logs`: the logs' names; `values`, `std_errors`: `(n_logs, n_params)`, SI. Logs whose
    fit did not converge or whose standard error is not finite are left out (`excluded`)."""

    names: list[str]
    logs: list[str]
    values: np.ndarray
    std_errors: np.ndarray
    log_scale: tuple[bool, ...]
    mean: np.ndarray
    mean_se: np.ndarray
    chi2: np.ndarray
    dof: np.ndarray
    p: np.ndarray
    birge: np.ndarray
    spread: np.ndarray
    excluded: dict
    # what was compared: independent fits, or the per-log values of one joint fit
    source: str = "independent fits (inverse-variance weighted mean, chi-square)"

    @property
    def differs(self) -> np.ndarray:
        return self.p < DISAGREEMENT_P

    def summary(self) -> str:
        """A table: each parameter's weighted mean, spread, chi-square test and verdict."""
        lines = [f"between the {len(self.logs)} logs' {self.source}:"]
        width = max(len(n) for n in self.names)
        for i, name in enumerate(self.names):
            spread = f"{100 * self.spread[i]:.3g} %" if self.log_scale[i] else f"{self.spread[i]:.4g}"
            verdict = (
                f"DIFFERS between logs beyond their intervals (x{self.birge[i]:.3g} their spread)"
                if self.differs[i]
                else "consistent"
            )
            lines.append(
                f"  {name:<{width}}  mean {self.mean[i]:.6g} +/- {self.mean_se[i]:.2g}, spread {spread}, "
                f"chi2 {self.chi2[i]:.3g} / {int(self.dof[i])} (p {self.p[i]:.2g}): {verdict}"
            )
        for name, why in self.excluded.items():
            lines.append(f"  (log {name!r} left out: {why})")
        if self.differs.any():
            lines.append(
                "  a parameter that differs either varies between the logs (a payload, a temperature) or every "
                "log's intervals are too narrow for the same reason (model error: see the residual tests)"
            )
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {
            "names": list(self.names),
            "logs": list(self.logs),
            "mean": self.mean.tolist(),
            "mean_se": self.mean_se.tolist(),
            "chi2": self.chi2.tolist(),
            "dof": self.dof.tolist(),
            "p": self.p.tolist(),
            "birge_ratio": self.birge.tolist(),
            "spread": self.spread.tolist(),
            "spread_is_relative": list(self.log_scale),
            "differs": self.differs.tolist(),
            "excluded": dict(self.excluded),
        }


def between_logs(results) -> BetweenLogs:
    """`BetweenLogs` of independent fits (`identify.fit_independent`'s results, one per
    log, or any `FitResult`s of the same parameters), or of the per-log parameters of one
    joint fit (a `FitResult` with `Parameter.per_log` ones: `_per_log_agreement`). Raises
    `ValueError` with fewer than two usable logs."""
    if isinstance(results, FitResult):
        return _per_log_agreement(results)
    results = list(results)
    if not results:
        raise ValueError("between_logs: no results")
    names = list(results[0].names)
    for r in results[1:]:
        if list(r.names) != names:
            raise ValueError(f"between_logs: the results fit different parameters ({names} and {list(r.names)})")
    log_scale = tuple(bool(v) for v in results[0].problem.log_scale)
    keep, logs, excluded = [], [], {}
    for r in results:
        label = ", ".join(r.problem.log_names)
        se = np.asarray(r.std_errors, float)
        if not r.converged:
            excluded[label] = "its fit did not converge" + (
                f" ({', '.join(r.at_bounds)} on a bound)" if r.at_bounds else ""
            )
        elif not np.all(np.isfinite(se) & (se > 0)):
            excluded[label] = "a standard error is not finite (a parameter the log does not determine)"
        else:
            keep.append(r)
            logs.append(label)
    if len(keep) < 2:
        raise ValueError(f"between_logs: {len(keep)} usable log(s); needs 2 ({excluded})")
    values = np.stack([np.asarray(r.values, float) for r in keep])
    se = np.stack([np.asarray(r.std_errors, float) for r in keep])
    log = np.asarray(log_scale)
    x = np.where(log, np.log(values), values)
    s = np.where(log, se / values, se)
    w = 1.0 / s**2
    mean_x = np.sum(w * x, axis=0) / np.sum(w, axis=0)
    mean_s = 1.0 / np.sqrt(np.sum(w, axis=0))
    chi2 = np.sum(((x - mean_x) / s) ** 2, axis=0)
    dof = np.full(len(names), len(keep) - 1)
    p = scipy.stats.chi2.sf(chi2, dof)
    mean = np.where(log, np.exp(mean_x), mean_x)
    return BetweenLogs(
        names=names,
        logs=logs,
        values=values,
        std_errors=se,
        log_scale=log_scale,
        mean=mean,
        mean_se=np.where(log, mean * mean_s, mean_s),
        chi2=chi2,
        dof=dof,
        p=p,
        birge=np.sqrt(chi2 / dof),
        spread=np.std(x, axis=0, ddof=1),
        excluded=excluded,
    )


def _per_log_agreement(result: FitResult) -> BetweenLogs:
    """Do a joint fit's per-log values of a parameter (`Parameter.per_log`) agree? In the
    natural coordinate `x` (`log theta` for positive parameters), with `C` the covariance
    of one parameter's `L` values (they are correlated through the shared parameters):
    the generalised least-squares common value `mean = 1^T C^-1 x / 1^T C^-1 1`, its
    standard error `(1^T C^-1 1)^-1/2`, and `chi2 = (x - mean)^T C^-1 (x - mean)` with `L - 1`
    degrees of freedom under "the same value in every log" (Aitken 1935). With a diagonal
    `C` (no shared parameter correlated with them) this is `between_logs`' weighted formula
    for independent fits."""
    problem = result.problem
    if not problem.per_log:
        raise ValueError(
            "between_logs: this fit has no per-log parameters (Parameter.per_log); pass the results of "
            "independent fits (identify.fit_independent) to compare logs"
        )
    if not result.converged:
        raise ValueError("between_logs: the fit did not converge; its covariance does not describe an optimum")
    if len(problem.log_names) < 2:
        raise ValueError(f"between_logs: the fit has {len(problem.log_names)} log; comparing needs 2")
    names, columns = [], []
    for name, index in problem.per_log:
        idx = np.asarray(index)
        values = np.asarray(result.values, float)[idx]
        se = np.asarray(result.std_errors, float)[idx]
        if not np.all(np.isfinite(se) & (se > 0)):
            raise ValueError(f"between_logs: a standard error of {name} is not finite (a log does not determine it)")
        log = bool(problem.log_scale[idx[0]])
        x = np.log(values) if log else values
        s = se / values if log else se
        cov = s[:, None] * np.asarray(result.correlation, float)[np.ix_(idx, idx)] * s[None, :]
        w = np.linalg.solve(cov, np.ones(len(idx)))  # C^-1 1
        mean_x = float(w @ x / w.sum())
        d = x - mean_x
        chi2 = float(d @ np.linalg.solve(cov, d))
        names.append(name)
        columns.append((values, se, log, mean_x, 1.0 / math.sqrt(w.sum()), chi2, float(np.std(x, ddof=1))))
    values, se, log, mean_x, mean_s, chi2, spread = (np.asarray(c) for c in zip(*columns))
    values, se = values.T, se.T  # (logs, parameters)
    dof = np.full(len(names), len(problem.log_names) - 1)
    mean = np.where(log, np.exp(mean_x), mean_x)
    return BetweenLogs(
        names=names,
        logs=list(problem.log_names),
        values=values,
        std_errors=se,
        log_scale=tuple(bool(v) for v in log),
        mean=mean,
        mean_se=np.where(log, mean * mean_s, mean_s),
        chi2=chi2,
        dof=dof,
        p=scipy.stats.chi2.sf(chi2, dof),
        birge=np.sqrt(chi2 / dof),
        spread=spread,
        excluded={},
        source="per-log values in one joint fit (generalised least-squares mean, chi-square with their covariance)",
    )
