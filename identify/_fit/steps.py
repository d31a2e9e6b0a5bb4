"""Each fitting stage's constant integration step, chosen against an adaptive reference, and
the simulation-failure vocabulary (`SimulationFailed`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._model.parameters import theta_from_x, x_from_z
from .._model.problem import Problem
from .._model.residuals import (
    initial_states_of,
    predict,
    used_mask,
)


@eqx.filter_jit
def _grid_step(problem: Problem, z, horizon, safety: float):
    """A constant integration step for the next stage: `safety` times the mean step the
    adaptive solver (the problem's rtol/atol) takes at the current parameters; whether
    every log's solve succeeded; the simulated outputs `(L, T, C)` (what
    `_frequency_initialise` compares with the logs)."""
    theta = theta_from_x(problem, x_from_z(problem, z["phys"]))
    outputs, ok, n = predict(problem, theta, initial_states_of(problem, z["y0"]), horizon, stats=True)
    # The span from the onset: an early stage's solve starts there, and the last stage's
    # takes a handful of steps for the rest before it (at rest the error estimate is 0 and
    # the steps grow tenfold each), so the mean step over the whole log would be the
    # rest's, not the motion's.
    span = jnp.minimum(problem.t[:, -1], problem.onset + horizon) - problem.onset
    return safety * jnp.min(span / jnp.maximum(n, 1)), jnp.all(ok), outputs


def _default_horizons(problem: Problem, n_stages: int) -> list[float]:
    """`n_stages` horizons (s from each log's onset, `log_onset`) doubling up to the
    longest log's length after its onset."""
    duration = float(np.max(np.asarray(problem.t[:, -1] - problem.onset)))
    if n_stages <= 1:
        return [duration]
    first = duration / 2 ** (n_stages - 1)
    return [first * 2**k for k in range(n_stages - 1)] + [duration]


def _say_onsets(problem: Problem, horizons, say):
    """Report the logs whose horizons count from a later onset than their first sample."""
    late = np.asarray(problem.onset - problem.t[:, 0])
    if len(horizons) > 1 and np.any(late > 0):
        say(
            "  horizons count from each log's onset (its input or motion starts): "
            + ", ".join(f"{name} at {d:.3g} s" for name, d in zip(problem.log_names, late) if d > 0)
        )


#: `fit`'s `grid_error`: a stage's constant step is the coarsest of `GRID_COARSEN` times
#: the tight one (`grid_safety` times the adaptive solver's mean step at the problem's
#: tolerances, 1e-10 by default) whose simulated outputs stay within this many noise
#: levels of the adaptive solution at the stage's starting parameters, on every used
#: sample of every channel. Measured (a 2-mode flexible link, 2 ms samples, noise 0.05 deg
#: and 2e-3 1/m, 2026-12-05): the tight step 0.18 ms is 2e-10 noise levels off; 0.67 ms
#: 4e-7, 1 ms 3e-6, 2 ms 1.5e-4. A systematic error of 1e-3 noise levels on every one of
#: `N` samples moves a parameter by at most ~1e-3 sqrt(N) standard errors (0.05 at N = 2000).
GRID_ERROR = 1e-3


#: the coarsening factors tried over the tight step, coarsest first (each aligned with the
#: torque samples, `aligned_step`)
GRID_COARSEN = (8.0, 4.0, 2.0)


#: after the last stage the chosen step is checked again at the optimum (where the
#: parameters may have moved the modes up); over this many `GRID_ERROR`s, the last stage is
#: solved again at the tight step
GRID_RECHECK = 10.0


class _Grid(NamedTuple):
    """How a stage's constant step is chosen (`fit`'s `grid_safety`, `grid_error`)."""

    safety: float
    error: float | None = None


def _span_horizon(problem: Problem, span: float):
    """The stage horizon (from each log's onset) that simulates `span` s of every log, or
    whole logs (a horizon beyond every log's end) when `span` reaches past them all; an
    array, so that it is traced like the stages' horizons (one program)."""
    whole = float(jnp.max(problem.t[:, -1] - problem.onset))
    return jnp.asarray(span if span < whole else whole + 1.0, dtype=float)


class SimulationFailed(RuntimeError):
    """A fit stage could not simulate its logs at the current parameters (the adaptive
    solver reached its step limit, or the state stopped being finite). Attributes:
    `horizon_s` (the stage's horizon, s from each log's onset), `values` (parameter name
    -> value, SI, where the simulation failed), `logs` (log name -> what failed)."""

    def __init__(self, message: str, *, horizon_s: float, values: dict, logs: dict):
        super().__init__(message)
        self.horizon_s = horizon_s
        self.values = values
        self.logs = logs


@eqx.filter_jit
def _solve_flags(problem: Problem, theta, y0s, horizon):
    """Each log's success flag and whether its solve reached the step limit."""
    _, ok, limit = predict(problem, theta, y0s, horizon, stats="limit")
    return ok, limit


def _simulation_failure(problem: Problem, z, horizon) -> SimulationFailed:
    """Why the logs' simulation at `z` over `horizon` failed, per log (one more solve,
    only after a failure; review: "the simulation at the current parameters failed" said
    neither which log, nor why, nor at which values)."""
    theta = np.asarray(theta_from_x(problem, x_from_z(problem, z["phys"])))
    ok, limit = _solve_flags(problem, jnp.asarray(theta), initial_states_of(problem, z["y0"]), jnp.asarray(horizon))
    logs = {}
    for name, ok_l, limit_l in zip(problem.log_names, np.asarray(ok), np.asarray(limit)):
        if not ok_l:
            logs[name] = (
                f"the adaptive solver reached its limit of {problem.max_steps} steps (a stiff model: a mode far "
                "above the logs' band)"
                if limit_l
                else "the state stopped being finite, or a parameter is out of its range"
            )
    if not logs:  # (the stage's own program disagreed with this one: say so, do not guess)
        logs = {name: "the stage's simulation failed; a repeated one succeeded" for name in problem.log_names}
    values = {name: float(v) for name, v in zip(problem.names, theta)}
    shown = ", ".join(f"{name} = {v:.4g}" for name, v in values.items())
    which = "; ".join(f"log '{name}': {why}" for name, why in logs.items())
    return SimulationFailed(
        f"fit: the simulation over the {float(horizon):.4g} s horizon failed at the current parameters ({which}); "
        f"parameters where it failed: {shown}; check guesses and bounds",
        horizon_s=float(horizon),
        values=values,
        logs=logs,
    )


def _stage_step(problem: Problem, z, horizon, grid, sigma=None):
    """The constant step of a stage (None: use the problem's own fixed dt); raises
    `SimulationFailed` when a log's simulation fails. `grid`: a `_Grid` (or the bare
    safety factor). With `grid.error` and the noise levels `sigma`, the coarsest step of
    `GRID_COARSEN` that keeps the outputs within `grid.error` noise levels of the adaptive
    solution (`_grid_errors`); the tight step if none does."""
    grid = grid if isinstance(grid, _Grid) else _Grid(grid)
    if problem.dt is not None:
        return None
    step, ok, reference = _grid_step(problem, z, jnp.asarray(horizon), grid.safety)
    if not bool(ok):
        raise _simulation_failure(problem, z, horizon)
    tight = aligned_step(problem, step)
    if not grid.error or sigma is None:
        return tight
    tried = _coarser_steps(problem, step, tight)
    if not tried:
        return tight
    errors = np.asarray(
        _grid_errors(
            problem,
            z,
            jnp.asarray(horizon),
            _padded_steps(tried, tried[0]),
            reference,
            sigma,
            jnp.asarray(grid.error, dtype=float),
        )
    )
    for h, e in zip(tried, errors):
        if e <= grid.error:
            return jnp.asarray(h, dtype=jnp.asarray(tight).dtype)
    return tight


def _coarser_steps(problem: Problem, step, tight) -> list[float]:
    """The distinct steps of `GRID_COARSEN` times the adaptive `step`, aligned, coarser than
    `tight`, coarsest first."""
    out = sorted({float(aligned_step(problem, float(step) * f)) for f in GRID_COARSEN}, reverse=True)
    return [h for h in out if h > float(tight) * (1 + 1e-9)]


def _padded_steps(steps, pad):
    """`steps` padded to `len(GRID_COARSEN)` (one compiled `_grid_errors`) with `pad`, a
    step as coarse as the coarsest tried (cheap to simulate; its results are not read)."""
    return jnp.asarray(list(steps) + [float(pad)] * (len(GRID_COARSEN) - len(steps)), dtype=float)


@eqx.filter_jit
def _grid_errors(problem: Problem, z, horizon, steps, reference, sigma, bar):
    """For each constant step of `steps`, in order: the largest deviation, in noise levels
    `sigma`, of the outputs simulated at that step from `reference` (`_grid_step`'s
    adaptive outputs) over the used samples up to `horizon`; inf where a simulation failed,
    and for every step after the first within `bar` (not simulated: the caller takes the
    first that passes; `bar` = inf simulates the first step only). The steps are simulated
    one after another (a `scan`: under `vmap` every one would take as many steps as the
    finest; under `fit_independent`'s vmap the skip is a select, both sides computed)."""
    theta = theta_from_x(problem, x_from_z(problem, z["phys"]))
    y0s = initial_states_of(problem, z["y0"])
    mask = used_mask(problem, horizon)

    def one(h):
        outputs, ok = predict(problem, theta, y0s, horizon, h)
        dev = jnp.where(mask, jnp.abs(outputs - reference) / sigma, 0.0)
        return jnp.where(jnp.all(ok) & jnp.all(jnp.isfinite(dev)), jnp.max(dev), jnp.inf)

    def body(done, h):
        e = jax.lax.cond(done, lambda: jnp.asarray(jnp.inf, dtype=reference.dtype), lambda: one(h))
        return done | (e <= bar), e

    return jax.lax.scan(body, jnp.asarray(False), steps)[1]


def _step_error(problem: Problem, z, horizon, grid, sigma, step) -> tuple:
    """The tight step at `z` (as `_stage_step` without coarsening) and how far (noise
    levels) the outputs at the constant `step` are from the adaptive solution there
    (`_grid_errors` of that one step): one adaptive solve for both."""
    adaptive, ok, reference = _grid_step(problem, z, jnp.asarray(horizon), grid.safety)
    if not bool(ok):
        raise _simulation_failure(problem, z, horizon)
    tight = aligned_step(problem, adaptive)
    if not float(step) > float(tight) * (1 + 1e-9):
        return tight, 0.0  # (not coarser than the tight step: nothing to check)
    return tight, float(
        _grid_errors(
            problem,
            z,
            jnp.asarray(horizon),
            _padded_steps([float(step)], step),
            reference,
            sigma,
            jnp.asarray(jnp.inf, dtype=float),
        )[0]
    )


def aligned_step(problem: Problem, step):
    """`step` shortened to divide the torque's sample interval, when the logs are driven,
    sampled uniformly at one common interval `dt_s`: `dt_s / ceil(dt_s / step)` (at most
    2x more steps; `dt_s` itself when `step >= dt_s`). Otherwise `step` unchanged.

    The applied torque is linear between samples, so its derivative jumps at every sample.
    A constant step that straddles the sample times integrates across those kinks: the
    local error there is second order, not fifth, and the sum over the log biases the fit.
    Measured (identify diagnose, the tilted paper-004 arm, seed 1, 5 ms samples): at a
    3.0 ms step the fitted in-plane gravity was 3 standard errors from the truth, at a
    4x finer step inside its 95 % interval. With steps aligned to the samples every kink
    falls on a step boundary, where Tsit5 restarts its stages."""
    if step is None:
        return None
    tv = np.asarray(problem.torque_v)
    if not np.any(tv != 0):
        return step
    t, valid = np.asarray(problem.t), np.asarray(problem.valid)
    intervals = np.concatenate([np.diff(t[l][valid[l]]) for l in range(t.shape[0])])
    if intervals.size == 0:
        return step
    dt_s = float(np.median(intervals))
    if not (dt_s > 0 and np.allclose(intervals, dt_s, rtol=1e-6, atol=0.0)):
        return step
    h = float(step)
    if h >= dt_s:
        # At most the sample interval. The mean adaptive step of a log that rests before
        # its input starts is set by the rest, where the adaptive steps grow tenfold each:
        # measured (a 2-mode flexible link, 4.0 s at rest then a 0.4 s doublet, 4 ms
        # samples, free initial modal coordinates) 0.33 s, 27x the stiffest mode's
        # stability limit (`fd.stable_step`, 12.2 ms), and the Jacobian at the optimum
        # came out non-finite. The torque's samples resolve the input no finer anyway.
        return jnp.asarray(dt_s, dtype=jnp.asarray(step).dtype)
    return jnp.asarray(dt_s / math.ceil(dt_s / h - 1e-9), dtype=jnp.asarray(step).dtype)
