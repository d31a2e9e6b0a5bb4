"""Each fitting stage's constant integration step, chosen against an adaptive reference (for
`fit`'s one problem and, log by log, for `fit_independent`'s batch), and the simulation-failure
vocabulary (`SimulationFailed`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from flexdyn import batch as fbatch

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
    theta = theta_from_x(problem, x_from_z(problem, z.phys))
    outputs, ok, n = predict(problem, theta, initial_states_of(problem, z.y0), horizon, stats=True)
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
#: sample of every channel. A systematic error of 1e-3 noise levels on every one of `N`
#: samples moves a parameter by at most ~1e-3 sqrt(N) standard errors (0.05 at N = 2000).
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
    """A fit could not simulate its logs at the current (or the fitted) parameters: the
    adaptive solver reached its step limit, or the state stopped being finite. Attributes:
    `horizon_s` (the stage's horizon, s from each log's onset; `None`: the whole logs),
    `values` (parameter name -> value, SI, where the simulation failed), `logs` (log name
    -> what failed)."""

    def __init__(self, message: str, *, horizon_s: float | None, values: dict, logs: dict):
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
    """Why the logs' simulation at `z` over `horizon` failed: which log, why, and at which
    parameter values (one more solve, only after a failure)."""
    theta = np.asarray(theta_from_x(problem, x_from_z(problem, z.phys)))
    ok, limit = _solve_flags(problem, jnp.asarray(theta), initial_states_of(problem, z.y0), jnp.asarray(horizon))
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
    chosen = _first_within(tried, errors, grid.error)
    return tight if chosen is None else jnp.asarray(chosen, dtype=jnp.asarray(tight).dtype)


def _first_within(tried, errors, bar) -> float | None:
    """The first (coarsest) of the steps `tried` whose error (noise levels, `_grid_errors`)
    is within `bar`; None if none is."""
    return next((h for h, e in zip(tried, errors) if e <= bar), None)


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
    theta = theta_from_x(problem, x_from_z(problem, z.phys))
    y0s = initial_states_of(problem, z.y0)
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

    The applied torque is linear between samples, so its derivative jumps at every sample:
    a constant step that straddles those kinks has a second-order local error there, which
    biases the fit. Aligned, every kink falls on a step boundary, where Tsit5 restarts."""
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
        # At most the sample interval: the mean adaptive step of a log that rests before
        # its input starts is set by the rest, where the adaptive steps grow tenfold each,
        # and can exceed the stiffest mode's stability limit (`fd.stable_step`) many times.
        # The torque's samples resolve the input no finer anyway.
        return jnp.asarray(dt_s, dtype=jnp.asarray(step).dtype)
    return jnp.asarray(dt_s / math.ceil(dt_s / h - 1e-9), dtype=jnp.asarray(step).dtype)


class BatchGrid(NamedTuple):
    """How `fit_independent` chooses each log's constant step: its batch (`stacked`, padded
    to the devices and sharded, `flexdyn.batch`) and single-log problems (`singles`),
    `_grid_step` and `_grid_errors` vmapped over the batch with each device's share run on
    its own (`batch_grid`), and the fit's `grid_safety` (`safety`) and `grid_error`
    (`error`)."""

    stacked: Problem
    singles: list
    grid_step: Callable
    grid_errors: Callable
    safety: float
    error: float | None


def batch_grid(stacked: Problem, singles: list, mesh: Mesh, safety: float, error: float | None) -> BatchGrid:
    """`fit_independent`'s `BatchGrid` over the devices of `mesh`."""
    # `flexdyn.batch.sharded_vmap`: XLA's partitioning of the plain vmapped program replicated
    # a division in it ("[SPMD] Involuntary full rematerialization ... _grid_step/div").
    return BatchGrid(
        stacked,
        singles,
        fbatch.sharded_vmap(_grid_step, (0, 0, None, None), mesh),
        fbatch.sharded_vmap(_grid_errors, (0, 0, None, 0, 0, 0, None), mesh),
        safety,
        error,
    )


def batch_stage_steps(batch: BatchGrid, z, sigma, horizon, stage: int, coarsen: bool = True):
    """`_stage_step` for every log of `fit_independent`'s batch at `horizon` (s from each
    log's onset) with noise levels `sigma` `(B, C)`: each log's constant step, aligned with
    its torque samples and (`coarsen`) coarsened within `batch.error`; also each log's tight
    step and the adaptive outputs. Padding entries repeat the last log. One batched solve
    per step tried, so a failed simulation raises `RuntimeError` naming the logs and the
    stage (`stage`, from 0), not `SimulationFailed`."""
    singles, n_logs = batch.singles, len(batch.singles)
    adaptive, ok, reference = batch.grid_step(batch.stacked, z, jnp.asarray(horizon), batch.safety)
    if not bool(jnp.all(ok)):
        failed = [singles[k].log_names[0] for k in range(n_logs) if not bool(ok[k])]
        raise RuntimeError(
            f"fit_independent: the simulation of log(s) {failed} at their current parameters failed "
            f"(stage {stage + 1}, horizon {float(horizon):g} s)"
        )
    n = adaptive.shape[0]
    tight = [float(aligned_step(singles[min(k, n_logs - 1)], adaptive[k])) for k in range(n)]
    chosen = list(tight)
    tried = [_coarser_steps(singles[min(k, n_logs - 1)], adaptive[k], tight[k]) for k in range(n)]
    if batch.error and coarsen and any(tried):
        # (a log with nothing to try pads with its coarsest factor, unaligned: not read)
        padded = jnp.stack(
            [_padded_steps(tried[k], tried[k][0] if tried[k] else tight[k] * GRID_COARSEN[0]) for k in range(n)]
        )
        errors = np.asarray(
            batch.grid_errors(
                batch.stacked, z, jnp.asarray(horizon), padded, reference, sigma, jnp.asarray(batch.error, dtype=float)
            )
        )
        for k in range(n):
            step = _first_within(tried[k], errors[k], batch.error)
            chosen[k] = tight[k] if step is None else step
    return jnp.asarray(chosen, dtype=adaptive.dtype), jnp.asarray(tight, dtype=adaptive.dtype), reference


def batch_steps_off(batch: BatchGrid, z, sigma, horizon, step, stage: int) -> tuple[list[int], jax.Array]:
    """`fit`'s check of the last stage's step at the optimum (`_step_error`, `GRID_RECHECK`)
    for every log of the batch: the logs (indices) whose constant `step` is coarser than
    their tight step at `z` and over `GRID_RECHECK` times `batch.error` noise levels off the
    adaptive solution there, and every entry's tight step."""
    _, tight, reference = batch_stage_steps(batch, z, sigma, horizon, stage, coarsen=False)
    padded = jnp.tile(step[:, None], (1, len(GRID_COARSEN)))
    errors = np.asarray(
        batch.grid_errors(
            batch.stacked, z, jnp.asarray(horizon), padded, reference, sigma, jnp.asarray(jnp.inf, dtype=float)
        )
    )[:, 0]
    off = [
        k
        for k in range(len(batch.singles))
        if float(step[k]) > float(tight[k]) * (1 + 1e-9) and not errors[k] <= GRID_RECHECK * batch.error
    ]
    return off, tight
