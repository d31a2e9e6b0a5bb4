"""Free parameters and their coordinates.

A `Parameter` names a value of the chain or the measurement and bounds it. The optimiser works in
unbounded coordinates `z`; `x` are natural coordinates (log of a positive scale parameter, the value
otherwise) and `theta` the physical values (SI).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

Z95 = 1.959963984540054


@dataclasses.dataclass(frozen=True)
class Parameter:
    """A free parameter of a fit: its name (see `flexdyn.parameter_names`), initial
    guess and bounds (SI; `None` for unbounded).

    `per_log`: each log gets its own value (a payload that differs from log to log and
    is not known), while the other free parameters are shared by all logs. The problem
    then has one free parameter per log, named `name[log]` (`payload.mass[m20g]`), all
    with this guess and these bounds. Each log's simulation carries the tangents of the
    shared parameters and of its own values only."""

    name: str
    guess: float
    lower: float | None = None
    upper: float | None = None
    per_log: bool = False


class Bounds(NamedTuple):
    """Lower and upper bounds of free parameters in natural coordinates `x` (the log of a
    log-scale parameter's SI value, else the SI value), `-inf`/`inf` where unbounded. A
    `Problem` carries the same two fields, so the maps below take either. (The maps that
    need the names and log scales, `theta_from_x` and the like, take the `Problem`.)"""

    lower: np.ndarray
    upper: np.ndarray


def x_from_z(bounds: Bounds, z):
    """Natural coordinates `x` from unbounded `z`: `lo + (hi - lo) sigmoid(z)` between two
    bounds, `lo + softplus(z)` above one, `hi - softplus(-z)` below one, `z` unbounded."""
    lo, hi = bounds.lower, bounds.upper
    both = jnp.isfinite(lo) & jnp.isfinite(hi)
    only_lo = jnp.isfinite(lo) & ~jnp.isfinite(hi)
    only_hi = ~jnp.isfinite(lo) & jnp.isfinite(hi)
    safe_lo, safe_hi = jnp.where(jnp.isfinite(lo), lo, 0.0), jnp.where(jnp.isfinite(hi), hi, 1.0)
    bounded = safe_lo + (safe_hi - safe_lo) * jax.nn.sigmoid(z)
    return jnp.where(
        both,
        bounded,
        jnp.where(only_lo, safe_lo + jax.nn.softplus(z), jnp.where(only_hi, safe_hi - jax.nn.softplus(-z), z)),
    )


def z_from_x(bounds: Bounds, x):
    """The inverse of `x_from_z` (host-side; `x` kept 1e-9 of the range or 1e-12 inside a bound)."""
    lo, hi = np.asarray(bounds.lower), np.asarray(bounds.upper)
    x = np.asarray(x, float)
    z = x.copy()
    for i in range(len(x)):
        if np.isfinite(lo[i]) and np.isfinite(hi[i]):
            u = np.clip((x[i] - lo[i]) / (hi[i] - lo[i]), 1e-9, 1 - 1e-9)
            z[i] = np.log(u / (1 - u))
        elif np.isfinite(lo[i]):
            d = max(x[i] - lo[i], 1e-12)
            z[i] = d + np.log(-np.expm1(-d))  # softplus inverse
        elif np.isfinite(hi[i]):
            d = max(hi[i] - x[i], 1e-12)
            z[i] = -(d + np.log(-np.expm1(-d)))
    return z


#: `exp_natural`: a log-scale parameter's natural coordinate is clipped to +-this before
#: `exp`, so that the parameter stays finite and > 0 (1e-304 to 1e304)
LOG_CLIP = 700.0


def exp_natural(x):
    """A log-scale parameter from its natural coordinate: `exp(x)`, with `x` clipped to
    `+-LOG_CLIP` (the same value and derivative inside). A Levenberg-Marquardt trial
    point of an unbounded parameter far out would overflow to inf or underflow to 0, which
    the model's parameter checks refuse with an error that stops the fit (e.g.
    "joint1.rotor_inertia must be finite and > 0"); clipped, the trial point is merely a
    bad one, rejected."""
    return jnp.exp(jnp.clip(x, -LOG_CLIP, LOG_CLIP))


def theta_from_x(problem, x):
    """Physical values (SI) from natural coordinates `x`: `exp` of a log-scale parameter's
    (`problem.log_scale`, clipped by `exp_natural`), the others as they are."""
    if not problem.names:
        return jnp.zeros((0,), x.dtype)
    return jnp.stack([exp_natural(x[i]) if problem.log_scale[i] else x[i] for i in range(len(problem.names))])


def x_from_theta(problem, theta):
    """The inverse of `theta_from_x` (host-side)."""
    return np.array([np.log(v) if s else v for v, s in zip(theta, problem.log_scale)], float)


def dx_dz(bounds: Bounds, z_phys) -> np.ndarray:
    """`d x / d z` of `x_from_z` (elementwise), host-side."""
    lo, hi, z = np.asarray(bounds.lower), np.asarray(bounds.upper), np.asarray(z_phys, float)

    def sig(v):  # the logistic, to full relative precision in both tails, without overflow
        e = np.exp(-np.abs(v))
        return np.where(v >= 0, 1.0 / (1.0 + e), e / (1.0 + e))

    with np.errstate(invalid="ignore"):
        both = (hi - lo) * sig(z) * sig(-z)
    return np.where(
        np.isfinite(lo) & np.isfinite(hi),
        both,
        np.where(np.isfinite(lo), sig(z), np.where(np.isfinite(hi), sig(-z), 1.0)),
    )


# Beyond this |z| a two-sided parameter is within 3e-7 of its range from a bound, where
# JAX's derivative of the logistic, sigma (1 - sigma), loses digits in 1 - sigma (relative
# 1e-16 / (1 - sigma), 1e-9 here): the linearisation w.r.t. z would not give the natural
# Jacobian to full precision, so it is recomputed.
SIGMOID_Z_MAX = 15.0


def names_at_bounds(problem, xs: np.ndarray) -> list[str]:
    """Names of the parameters whose natural coordinate is on (within 0.1 % of the range
    of) a finite bound."""
    lo_b, hi_b = np.asarray(problem.lower), np.asarray(problem.upper)
    out = []
    for i, name in enumerate(problem.names):
        if np.isfinite(lo_b[i]) and np.isfinite(hi_b[i]):
            u = (xs[i] - lo_b[i]) / (hi_b[i] - lo_b[i])
            if u < 1e-3 or u > 1 - 1e-3:
                out.append(name)
        elif (np.isfinite(lo_b[i]) and xs[i] - lo_b[i] < 1e-6) or (np.isfinite(hi_b[i]) and hi_b[i] - xs[i] < 1e-6):
            out.append(name)
    return out
