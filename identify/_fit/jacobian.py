"""The Jacobian and covariance at the optimum, in natural coordinates."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._model.parameters import SIGMOID_Z_MAX, dx_dz, theta_from_x, x_from_z
from .._model.problem import Problem
from .._model.residuals import (
    FAILED_RESIDUAL,
    log_jacobian,
    used_mask,
)
from . import covariance, rounding
from .block_lm import Layout
from .covariance import Covariance
from .levenberg_marquardt import _blocked
from .steps import SimulationFailed


@eqx.filter_jit
def _jacobian_natural(problem: Problem, x, y0_free, offset_free, sigma, step):
    """Weighted residuals, their Jacobian w.r.t. (x, y0_free, offsets) and whether every
    log's simulation succeeded, full horizon; one forward-mode solve per log
    (`identify.residuals.log_jacobian`)."""

    theta_of = lambda x_: theta_from_x(problem, x_)  # noqa: E731
    jac = log_jacobian(problem, theta_of, x, y0_free, offset_free, sigma, None, step)
    return jac.r.reshape(-1), jac.dense(len(problem.y0_free), len(problem.offset_free)), jnp.all(jac.ok)


@eqx.filter_jit
def _jacobian_blocks(problem: Problem, x, y0_free, offset_free, sigma, step):
    """As `_jacobian_natural`, the blocks (`identify.residuals.LogJacobian`), no dense `J`."""
    theta_of = lambda x_: theta_from_x(problem, x_)  # noqa: E731
    return log_jacobian(problem, theta_of, x, y0_free, offset_free, sigma, None, step)


def _dense_covariance(problem: Problem, r, J) -> Covariance:
    """`identify.covariance.dense` of the residuals that count."""
    used = np.asarray(problem.valid[:, :, None] & problem.present[:, None, :]).reshape(-1)
    return covariance.dense(problem.names, problem.log_scale, np.asarray(r)[used], np.asarray(J)[used])


def _covariance_at(problem: Problem, x, z, sigma, step, lin=None, horizon=None) -> tuple[Covariance, tuple]:
    """The covariance at the optimum: block by block (`identify.covariance.blocked`, no
    dense Jacobian) when the Levenberg-Marquardt steps were (`BLOCK_SOLVE_MIN_LOGS` logs
    with nuisances), else from the dense Jacobian, the shared parameters' from the
    sensors' rounding where a channel is quantised (`identify/_fit/rounding.py`); and the
    blocks it came from (`jacobian_blocks_at`, kept on the `FitResult` for
    `identify.clustered_uncertainty`).

    `lin`, `horizon`: the linearisation the last Levenberg-Marquardt solve ended with at
    `z` (`_solve`) and that solve's horizon; used when it covers every sample, else (or
    without it) the Jacobian is computed afresh."""
    blocks = _natural_blocks(problem, z, lin, horizon) if lin is not None else None
    if blocks is None:
        blocks = jacobian_blocks_at(problem, x, z, sigma, step)
    if not _blocked(problem):
        r, S, U, slots, used = blocks
        cov = _dense_covariance(problem, r.reshape(-1), _dense_jacobian(problem, S, U, slots))
    else:
        cov = covariance.blocked(problem.names, problem.log_scale, *blocks)
    model = rounding.model_of(problem, sigma)
    if model is not None:  # quantised channels: their rounding's own covariance (`rounding.py`)
        cov = rounding.rounding_covariance(model, problem, blocks, cov)
    return cov, blocks


def _natural_blocks(problem: Problem, z, lin, horizon):
    """The blocks `(r, S, U, slots, used)` (`jacobian_blocks_at`) from a Levenberg-Marquardt
    solve's linearisation `lin` at `z` (w.r.t. the unconstrained `z`; the shared columns
    divided by `d x / d z` give them w.r.t. the natural coordinates), or None where it
    cannot stand for the full Jacobian: its horizon left samples out, or a parameter sits so
    near a bound that `d x / d z` loses precision (`SIGMOID_Z_MAX`) or underflows. Raises
    if a log's simulation failed there (its residuals are the failure value of
    `identify.residuals.residuals`)."""
    mask = np.asarray(problem.valid[:, :, None] & problem.present[:, None, :])
    if horizon is not None and not np.array_equal(np.asarray(used_mask(problem, float(horizon))), mask):
        return None  # the horizon's samples are not all of them
    zp = np.asarray(z.phys)
    two_sided = np.isfinite(np.asarray(problem.lower)) & np.isfinite(np.asarray(problem.upper))
    if np.any(two_sided & (np.abs(zp) > SIGMOID_Z_MAX)):
        return None
    scale = dx_dz(problem, zp)
    if not np.all(np.isfinite(scale) & (np.abs(scale) > 1e-250)):
        return None
    r, S, U = (np.asarray(a) for a in lin)
    L, n = r.shape
    used = mask.reshape(L, n)
    failed = [used[l].any() and np.all(r[l][used[l]] == FAILED_RESIDUAL) for l in range(L)]
    if any(failed):
        raise _failed_at_optimum(problem, x_from_z(problem, z.phys), failed)
    return r, S / scale, U, _nuisance_slots(problem), used


_FAILED_AT_OPTIMUM = "fit: the simulation at the fitted parameters failed; check bounds and solver settings"


def _failed_at_optimum(problem: Problem, x, failed) -> SimulationFailed:
    """`SimulationFailed` for the logs flagged in `failed` at natural coordinates `x`."""
    theta = np.asarray(theta_from_x(problem, jnp.asarray(x)))
    return SimulationFailed(
        _FAILED_AT_OPTIMUM,
        horizon_s=None,
        values=dict(zip(problem.names, theta.tolist())),
        logs={
            name: "the simulation at the fitted parameters failed" for name, f in zip(problem.log_names, failed) if f
        },
    )


def jacobian_blocks_at(problem: Problem, x, z, sigma, step):
    """The weighted residuals and their block-arrow Jacobian at `(x, z)` in natural
    coordinates, as numpy arrays `(r, S, U, slots, used)` (`identify.covariance.blocked`:
    `r` `(L, n)`, `S` `(L, n, P)` shared columns, `U` `(L, n, k)` per-log nuisance columns,
    `slots` their positions among the nuisances, `used` which residuals count)."""
    jac = _jacobian_blocks(problem, x, z.y0, z.offset, sigma, step)
    if not bool(jnp.all(jac.ok)):
        raise _failed_at_optimum(problem, x, ~np.asarray(jac.ok))
    L, n, _ = jac.shared.shape
    used = np.asarray(problem.valid[:, :, None] & problem.present[:, None, :]).reshape(L, n)
    return (
        np.asarray(jac.r),
        np.asarray(jac.shared),
        np.concatenate([np.asarray(jac.y0), np.asarray(jac.offset)], axis=2),
        _nuisance_slots(problem),
        used,
    )


def _nuisance_slots(problem: Problem) -> np.ndarray:
    """`(L, k)` position of each log's nuisance slot among the nuisance columns (initial-state
    entries, then offsets), -1 on padding (`identify.covariance.blocked`)."""
    layout = Layout.of(problem)
    slots = []
    start = 0
    for kind, width in ((0, len(problem.y0_free)), (1, len(problem.offset_free))):
        pos, used = layout.arrays(kind)
        slots.append(np.where(used, start + pos, -1))
        start += width
    return np.concatenate(slots, axis=1)


def _dense_jacobian(problem: Problem, S, U, slots) -> np.ndarray:
    """The dense Jacobian `(L n, P + k_y0 + k_offset)` from the blocks (`_nuisance_slots`)."""
    L, n, P = S.shape
    J = np.zeros((L, n, P + len(problem.y0_free) + len(problem.offset_free)))
    J[:, :, :P] = S
    for l, j in zip(*np.nonzero(slots >= 0)):
        J[l, :, P + slots[l, j]] = U[l, :, j]
    return J.reshape(L * n, -1)
