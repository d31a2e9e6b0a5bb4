"""`fit`: Levenberg-Marquardt through the simulation over a growing horizon, with multi-start and
restarts from a bound.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

import flexdyn as fd
from flexdyn._checks import runtime_check_message

from .._data import noise_floor as nf
from .._model.parameters import Parameter, names_at_bounds, x_from_theta, x_from_z
from .._model.problem import Problem, check_same_parameters, guesses_of
from .._model.variables import Variables
from .jacobian import _covariance_at
from .levenberg_marquardt import _check_budgets, _check_damping, _solve
from .multiple_shooting import check_segment, multiple_shooting
from .quality import (
    NOISE_AGREEMENT,
    NOISE_ROUNDS,
    _noise_text,
    _noise_to_estimate,
    _reestimate_sigma,
    _residual_ms,
    _same_misfit,
    noise_floors,
)
from .result import FitResult, _finish
from .stage import Stage
from .starts import _extra_starts, _frequency_initialise, initial_variables, multi_start
from .steps import (
    GRID_ERROR,
    GRID_RECHECK,
    SimulationFailed,
    _default_horizons,
    _Grid,
    _say_onsets,
    _stage_step,
    _step_error,
)
from .stiff_start import TooStiff, stiff_at, values_at


def fit(
    problem: Problem,
    parameters: Sequence[Parameter] | None = None,
    *,
    horizons: Sequence[float] | None = None,
    n_stages: int = 4,
    estimate_noise: Sequence[str] | bool | None = None,
    max_steps: int = 200,
    rtol: float = 1e-3,
    atol: float = 1e-10,
    grid_safety: float = 0.5,
    grid_error: float | None = GRID_ERROR,
    n_starts: int = 8,
    start_spread: float = 2.0,
    early_max_steps: int = 60,
    max_restarts: int = 2,
    restart_poor_fit: bool = True,
    frequency_init: bool = True,
    first_damping: float = 1e-3,
    extra_starts: Sequence[dict] = (),
    stop_when_stiff: bool = False,
    shooting: str = "single",
    segment: float | None = None,
    progress=None,
) -> FitResult:
    """Fit the free parameters (and per-log nuisances) of `problem`.

    **Arguments:**
    - `problem`, `parameters`: from `make_problem`; `parameters` (the same ones, in the
      same order) may be left out: the problem keeps their guesses (`Problem.parameters`).
    - `horizons`: horizon (s, from each log's onset: where its input or motion starts,
      `log_onset`; the log's start for a log that moves from its first sample) of each
      stage; default `n_stages` horizons doubling up to the full length (`n_stages=1`:
      plain single shooting). A stage that ends before a log does simulates that log
      from its onset, from its initial state; the last stage simulates every log whole.
    - `estimate_noise`: re-estimate the noise level of these channels (True: all; None,
      the default: those `make_problem` was given no noise for) from the residuals after
      the first pass and refit with the new weights, again until the residuals' RMS agrees
      with the weights within `NOISE_AGREEMENT` (at most `NOISE_ROUNDS` passes): with
      make_problem's default weights the intervals would be several times too wide.
    - `max_steps`, `rtol`, `atol`: Levenberg-Marquardt settings per stage (termination on
      the RMS change of the residuals and parameters, see `_solve`).
    - `grid_safety`: each stage integrates with a constant step, `grid_safety` times the
      mean step of the adaptive solver at the stage's starting parameters: an adaptive
      solver's accept/reject decisions make the loss a noisy function of the parameters,
      which stalls Levenberg-Marquardt; a grid frozen during a stage keeps it smooth.
    - `grid_error`: the stage's step is then coarsened (by up to `GRID_COARSEN`) while the
      outputs it simulates stay within `grid_error` noise levels of the adaptive solution
      at the stage's start; after the last stage the step is checked again at the optimum
      and, over `GRID_RECHECK` times that, the stage is solved again at the tight step.
      None: the tight step.
    - `n_starts`, `start_spread`: the first (shortest) stage is solved from `n_starts`
      points (the guess and a deterministic design within a factor `start_spread` of it,
      see `_starts`), and the best continues (`multi_start`): a single start from far-off
      guesses can land in a wrong basin.
    - `extra_starts`: more points for the multi-start stage, each a dict of parameter
      values (SI, by name; the others at their guesses), after the `n_starts` of the
      design: points a caller knows matter (a vendor's value, an earlier rig's fit, the
      limit in which a model extension reproduces the model it extends). Each runs the
      first stage like the design's points, and the best of all continues.
    - `max_restarts`: if the fit ends with a parameter on a bound, or (`restart_poor_fit`)
      with a channel's residual RMS above `identify.noise_floor.POOR_FIT` (2) times its
      noise floor estimated from the data alone (both signs of a wrong basin), the growing
      horizon is run again from up to this many next-best distinct optima of the
      multi-start stage (`_distinct`: starts that ended at the same short-horizon cost
      count once; none with `n_starts=1`). The result is the attempt off the bounds with
      the lowest `identify.noise_floor.score`; a restart that ends with the same score (within
      `SAME_SCORE`, 10 %) as an earlier one, both on a bound or both off, stops the
      restarts: the same misfit from two starts is the model's (a missing effect:
      `identify diagnose`) or the data's (a sign, a unit), not the start's.
    - `restart_poor_fit`: restart on a poor fit, as above (`diagnose` turns it off: its
      baseline misses an effect on purpose). Every result reports its goodness of fit
      (`FitResult.fit_quality`, `poor_fit`) either way.
    - `early_max_steps`: iteration budget of the stages before the last (they only need
      to land in the right basin).
    - `frequency_init`: before fitting, replace the guess of every free `link<i>.EI` whose
      link's tip deflection or root curvature is recorded by the factor (1/16 to 16) of it
      whose simulated channel's amplitude spectrum, under the logs' own inputs, is most
      similar to the measured one (`identify.frequency_init`; 25 simulations of the logs
      per EI): it puts the first stage in the right basin when EI is far off.
    - `first_damping`: `tau` of the Levenberg-Marquardt solve that starts from the guess when
      there is one start (`n_starts=1`, or no free physical parameter): its first damping
      is `tau * max diag(J^T J)` at the guess (`identify.trust_region`; 0 keeps
      optimistix's damping 1, an undamped Gauss-Newton step at our residuals' scale).
      The multi-start stage and the stages that continue from an optimum keep
      optimistix's start (there, `tau` made the fit slower for the same convergence).
    - `stop_when_stiff`: before each stage's adaptive solve, estimate from the model's
      linearisation at the stage's starting values the steps its solves need
      (`estimate_steps` in `identify/_fit/stiff_start.py`); when that exceeds the solver's step limit
      (`Problem.max_steps`), or the adaptive solve fails after all, the growing horizon
      stops there and the result is the last finished stage's, marked
      (`FitResult.stopped`, its cost over that stage's horizon), instead of spending minutes
      on solves that end on the step limit and raise. Before any stage has finished it
      raises `TooStiff` (a `SimulationFailed`, its `estimate` the `StepEstimate`) at once. For a fit that
      may walk into a stiff model (`identify diagnose`'s structural candidates).
    - `shooting`: `"single"` (the default: the growing horizon above) or `"multiple"`: for
      long, drifting or lightly damped logs that cannot be simulated open loop over their
      whole length from the guess. Each log is cut into segments of at most `segment` s
      (default: the growing horizon's first, `horizons[0]`), each with its own estimated
      start state, continuity enforced by a growing penalty
      (`identify/_fit/multiple_shooting.py`); from its optimum the ordinary fit over whole
      logs (one stage) gives the result, so the optimum, noise estimate and intervals are
      single shooting's. It replaces the multi-start and the growing horizon (`n_starts`,
      `start_spread`, `extra_starts`, `horizons`, `max_restarts` are not used). Open-loop
      problems only.
    - `progress`: callable taking a message string (e.g. `print`), or None.
    """
    _check_damping(first_damping)
    _check_budgets(max_steps=max_steps, early_max_steps=early_max_steps)
    horizons, segment = _check_shooting(problem, shooting, segment, horizons, n_stages)
    parameters = problem.parameters if parameters is None else parameters
    check_same_parameters(problem, parameters, "fit")
    extra = _extra_starts(problem, parameters, extra_starts)
    fd.ensure_mapping_headroom()  # a fit compiles ~10-50 programs (flexdyn.program_cache)
    start = time.perf_counter()
    say = progress or (lambda msg: None)
    x0 = x_from_theta(problem, guesses_of(problem, parameters))
    if frequency_init:
        x0 = _frequency_initialise(problem, x0, say, grid_safety)
    z = initial_variables(problem, x0)
    _say_onsets(problem, horizons, say)
    estimate_noise = _noise_to_estimate(problem, estimate_noise)
    schedule = _Schedule(
        rounds=NOISE_ROUNDS if estimate_noise else 1,
        estimate_noise=estimate_noise,
        grid=_Grid(grid_safety, grid_error),
        max_steps=max_steps,
        early_max_steps=early_max_steps,
        cap=max(max_steps, early_max_steps),
        rtol=rtol,
        atol=atol,
        stop_when_stiff=stop_when_stiff,
    )
    if stop_when_stiff:  # (the last stage must simulate the whole logs: checked over them)
        estimate = stiff_at(problem, z, None, grid_safety)
        if estimate is not None:
            raise TooStiff(estimate, where="at its starting values", horizon_s=None, values=values_at(problem, z))
    several = shooting == "single" and (n_starts > 1 or len(extra))
    if shooting == "multiple":  # into the basin segment by segment, then one stage over whole logs
        z, stages = _multiple_shooting(problem, z, segment, horizons[-1], schedule, say)
        candidates, horizons = [z], horizons[-1:]
    elif several and problem.names:
        starts = _Starts(x0, extra, n_starts, start_spread, keep=max_restarts + 1)
        candidates, stages = _multi_start(problem, z, starts, horizons[0], schedule, say)
    else:
        candidates, stages = [z], []
    attempts, failed, stopped = _attempts(
        problem,
        candidates,
        horizons,
        schedule,
        tau_first=0.0 if (n_starts > 1 or shooting == "multiple") and problem.names else first_damping,
        restart_poor_fit=restart_poor_fit,
        no_other_start=not several,
        max_restarts=max_restarts,
        say=say,
    )
    kept = _best_attempt(attempts, say)
    stages.extend(kept.stages)
    say("  computing standard errors (exact Jacobian at the optimum) ...")
    z, sigma, step, lin = kept.z, kept.sigma, kept.step, kept.lin
    x = x_from_z(problem, z.phys)
    cov, blocks = _covariance_at(problem, x, z, sigma, step, *lin)
    result = _finish(problem, parameters, z, x, sigma, step, cov, stages, time.perf_counter() - start, kept.ms, blocks)
    return dataclasses.replace(
        result,
        sigma_estimated=tuple(estimate_noise),
        failed_restarts=[failed] * bool(failed),
        stopped=stopped,
        converged=result.converged and not stopped,
    )


def _check_shooting(problem, shooting: str, segment, horizons, n_stages: int):
    """The stages' horizons (s) and, under multiple shooting, the checked segment (s)."""
    if shooting not in ("single", "multiple"):
        raise ValueError(f"fit: shooting expected 'single' or 'multiple', got {shooting!r}")
    if shooting == "single" and segment is not None:
        raise ValueError("fit: segment is multiple shooting's segment length: pass shooting='multiple' with it")
    horizons = list(horizons) if horizons is not None else _default_horizons(problem, n_stages)
    if shooting == "multiple":
        segment = check_segment(problem, horizons[0] if segment is None else segment)
    return horizons, segment


class _Starts(NamedTuple):
    """The multi-start stage's points: the design's `n` within a factor `spread` of the
    guess `x0`, the caller's `extra` ones; the best `keep` distinct optima continue."""

    x0: object
    extra: object
    n: int
    spread: float
    keep: int


def _multi_start(problem, z, starts: _Starts, horizon: float, schedule, say):
    """The first (shortest) stage from every start: the candidates to continue from, best
    first, and the stage's record (as a list of stages)."""
    candidates, stage = multi_start(
        problem,
        z,
        starts.x0,
        starts.extra,
        horizon,
        schedule.grid,
        problem.sigma,
        n_starts=starts.n,
        spread=starts.spread,
        max_steps=schedule.early_max_steps,
        cap=schedule.cap,
        rtol=schedule.rtol,
        atol=schedule.atol,
        keep=starts.keep,
        say=say,
    )
    return candidates, [stage]


def _multiple_shooting(problem, z, segment: float, horizon: float, schedule, say):
    """`fit`'s multiple-shooting stages (`multiple_shooting`) from `z`, integrated at the
    constant step of a stage over whole logs at `z`; returns its optimum and stages."""
    step = _stage_step(problem, z, horizon, schedule.grid, problem.sigma)
    outcome = multiple_shooting(
        problem, z, segment, step, max_steps=schedule.cap, rtol=schedule.rtol, atol=schedule.atol, say=say
    )
    return outcome.z, list(outcome.stages)


class _Schedule(NamedTuple):
    """The growing horizon's settings, the same for every attempt (`fit`'s arguments)."""

    rounds: int  # passes of the noise re-estimation (`NOISE_ROUNDS`, or 1)
    estimate_noise: tuple  # the channels whose noise is re-estimated
    grid: _Grid
    max_steps: int  # the last stage's iteration budget
    early_max_steps: int  # the budget of the stages before it
    # one compiled Levenberg-Marquardt program serves every stage and start: the budget is
    # traced (`_BudgetedLM`), the loop bound `cap` static
    cap: int
    rtol: float
    atol: float
    stop_when_stiff: bool = False  # `fit`'s option


class _Attempt(NamedTuple):
    """One growing horizon (`_grow`) from one start, and how well it explains the data."""

    bounded: bool  # a parameter ended on a bound
    score: float  # `identify.noise_floor.score` of its residuals
    z: Variables
    sigma: object  # the noise levels it ended with
    step: object
    lin: tuple  # the linearisation and horizon (`_grow`)
    stages: list  # its stages' records
    ms: object  # `_residual_ms`


def _attempts(
    problem: Problem,
    candidates: list,
    horizons: list,
    schedule: _Schedule,
    *,
    tau_first: float,
    restart_poor_fit: bool,
    no_other_start: bool,
    max_restarts: int,
    say: Callable,
) -> tuple[list[_Attempt], str | None, str]:
    """Grow the horizon from the best start (`candidates[0]`); while that ends on a bound of
    a parameter or (`restart_poor_fit`) with a residual far above the model-free noise
    floor (a wrong basin), from the next-best ones, until an attempt ends the same
    misfit as an earlier one (`_same_misfit`), or until a restart's simulation fails (a
    restart may walk into a stiff region; the attempts that finished are kept). Returns the
    attempts made, in order, the failed restart's message (or None), and, when the first
    attempt stopped in a stiff region (`fit`'s `stop_when_stiff`), where and why (else "";
    no restart follows: its cost covers a shorter horizon than a finished attempt's)."""
    floors = noise_floors(problem)
    attempts, why = [], ""
    for attempt, z in enumerate(candidates):
        if attempt:
            say(f"  {why}: growing the horizon again from the first stage's optimum #{attempt + 1}")
        try:
            z, sigma, step, lin, stages, stopped = _grow(problem, z, problem.sigma, horizons, schedule, say, tau_first)
            if stopped and attempts:  # (a restart that stopped did not finish: as one that failed)
                raise RuntimeError(stopped)
        except RuntimeError as e:  # (SimulationFailed; a solver's run-time check)
            if not attempts:
                raise
            failed = f"the restart from the first stage's optimum #{attempt + 1} failed ({_one_line(e)})"
            say(f"  {failed}: keeping the attempt(s) before it")
            return attempts, failed, ""
        x = x_from_z(problem, z.phys)
        bounded = bool(names_at_bounds(problem, np.asarray(x)))
        ms = _residual_ms(problem, z, sigma, step, lin)
        quality = nf.goodness(problem.channels, ms, *floors)
        poor = [c for c, q in quality.items() if q["poor"]]
        score = nf.score(ms, *floors)
        same = _same_misfit(bounded, score, [(a.bounded, a.score) for a in attempts])
        attempts.append(_Attempt(bounded, score, z, sigma, step, lin, stages, ms))
        if stopped:
            return attempts, None, stopped
        if not bounded and not (restart_poor_fit and poor):
            break
        if same:  # the same misfit again: the model (or the data), not the start, is the cause
            say(
                "  the restart ended with the same misfit"
                + (" on a bound again" if bounded else "")
                + ": keeping the best so far"
            )
            break
        why = (
            "a parameter ended on its bound"
            if bounded
            else "the residual of "
            + ", ".join(f"{c} is {quality[c]['ratio']:.3g}" for c in poor)
            + " times the noise floor"
        )
        if attempt + 1 == len(candidates):  # say so: whether the restarts ran is not visible otherwise
            say(
                f"  {'this attempt: ' if attempt else ''}{why}; not restarted: "
                + (
                    "no other start (n_starts=1 and no extra starts)"
                    if len(candidates) == 1 and no_other_start
                    else f"the {len(candidates)} distinct optima of the multi-start stage kept for restarts "
                    f"(max_restarts={max_restarts}) have all been grown"
                )
                + ": the misfit is more likely the model's or the data's than the start's"
            )
    return attempts, None, ""


def _one_line(e: Exception) -> str:
    """An error's message in one line, without the JAX and Equinox stacks around a run-time check."""
    text = runtime_check_message(e) or str(e)
    return " ".join(text.split())[:400]


def _best_attempt(attempts: list[_Attempt], say: Callable) -> _Attempt:
    """The attempt off the bounds that explains the data best (`identify.noise_floor.score`:
    unlike the cost, it does not depend on the noise weights each attempt re-estimated)."""
    kept = min(range(len(attempts)), key=lambda k: (attempts[k].bounded, attempts[k].score))
    if len(attempts) > 1:  # (which attempt the result is: the reasons said above were each attempt's)
        say(
            f"  keeping attempt {kept + 1} of {len(attempts)}"
            + (" (on a bound)" if attempts[kept].bounded else ", off the bounds")
            + ", the one that explains the data best (residual RMS against the noise floor)"
        )
    return attempts[kept]


def _stage_record(horizon, steps, cost, result) -> Stage:
    """A stage's entry of `FitResult.stages`."""
    return Stage(float(horizon), int(steps), float(cost), result)


def _grow(problem, z, sigma, horizons, schedule: _Schedule, say, tau_first):
    """The growing-horizon stages (and the noise re-estimation rounds) from `z` with noise
    levels `sigma`; returns the last stage's `z`, noise levels, step, linearisation
    (`_solve`) and horizon, the stages' records, and (`schedule.stop_when_stiff`) where and
    why the stages stopped in a stiff region ("" when they all ran: `_stiff_stop`)."""
    stages = []
    step = lin = finished = None
    for rnd in range(schedule.rounds):
        # The horizon grows in the first round only; later rounds (new noise weights) start
        # at the optimum, where the full horizon is safe.
        for k, h in enumerate(horizons if rnd == 0 else horizons[-1:]):
            last = rnd > 0 or k == len(horizons) - 1
            stage_step = _stiff_stop(problem, z, sigma, h, schedule, finished, say)
            if isinstance(stage_step, str):
                return z, sigma, step, (lin, finished), stages, stage_step
            step = stage_step
            budget = jnp.asarray(schedule.max_steps if last else schedule.early_max_steps)  # traced
            tau = jnp.asarray(tau_first if (rnd == 0 and k == 0) else 0.0, dtype=float)
            z, result, steps, cost, lin = _solve(
                problem, z, sigma, jnp.asarray(h), step, budget, tau, schedule.cap, schedule.rtol, schedule.atol
            )
            finished = h
            stages.append(_stage_record(h, steps, cost, result))
            say(
                f"  horizon {h:8.3f} s: {int(steps):3d} iterations, cost {float(cost):.6g} ({stages[-1].outcome}"
                + (
                    f": an early stage's budget, early_max_steps={schedule.early_max_steps}; the next stage goes "
                    "on from here)"
                    if not last and stages[-1].outcome == "max_steps_reached"
                    else ")"
                )
            )
        if rnd + 1 < schedule.rounds:
            new = _reestimate_sigma(problem, z, sigma, schedule.estimate_noise, step)
            change = float(np.max(np.abs(np.log(np.asarray(new) / np.asarray(sigma)))))
            if rnd > 0 and change < math.log1p(NOISE_AGREEMENT):
                say(f"  noise re-estimated again: within {100 * NOISE_AGREEMENT:g} % of the weights used: done")
                break
            sigma = new
            say("  noise re-estimated: " + _noise_text(problem.channels, sigma, schedule.estimate_noise))
    if schedule.grid.error and step is not None:
        try:
            _refuse_if_stiff(problem, z, h, schedule, "at the optimum")
            z, step, lin = _recheck_step(problem, z, sigma, h, step, lin, schedule, stages, say)
        except SimulationFailed as e:
            if not schedule.stop_when_stiff:
                raise
            stopped = f"stopped before the check of its integration step at the optimum, keeping that step: {_why(e)}"
            say(f"  {stopped}")
            return z, sigma, step, (lin, h), stages, stopped
    return z, sigma, step, (lin, h), stages, ""


def _refuse_if_stiff(problem, z, horizon, schedule: _Schedule, where: str) -> None:
    """With `schedule.stop_when_stiff`, raise `TooStiff` when the model at `z` is too stiff
    for the solver over `horizon` (`stiff_start.stiff_at`); `where`: at which values."""
    if not schedule.stop_when_stiff:
        return
    estimate = stiff_at(problem, z, horizon, schedule.grid.safety)
    if estimate is not None:
        raise TooStiff(estimate, where=where, horizon_s=float(horizon), values=values_at(problem, z))


def _why(e: SimulationFailed) -> str:
    """What stopped a fit (`_stiff_stop`), in a clause."""
    return f"{e.where} the model is {e.estimate.reason()}" if isinstance(e, TooStiff) else _one_line(e)


def _stiff_stop(problem, z, sigma, horizon, schedule: _Schedule, finished, say):
    """The constant step of the stage at `horizon` from `z` (`_stage_step`, noise levels
    `sigma`), or, with `schedule.stop_when_stiff`, why the stages stop there (a string): the
    model at `z` is too stiff for the solver (`stiff_start.stiff_at`, before any
    simulation), or its adaptive solve failed. Before any stage finished (`finished`: the
    last finished stage's horizon, or None) those raise (`TooStiff`, `SimulationFailed`):
    there is nothing to keep."""
    if not schedule.stop_when_stiff:
        return _stage_step(problem, z, horizon, schedule.grid, sigma)
    where = "at the values it reached" if finished is not None else "at the first stage's start"
    try:
        _refuse_if_stiff(problem, z, horizon, schedule, where)
        return _stage_step(problem, z, horizon, schedule.grid, sigma)
    except SimulationFailed as e:
        if finished is None:
            raise
        stopped = f"stopped before the {float(horizon):.4g} s stage, keeping the {float(finished):.4g} s one: {_why(e)}"
        say(f"  {stopped}")
        return stopped


def _recheck_step(problem, z, sigma, horizon, step, lin, schedule: _Schedule, stages: list, say):
    """The last stage's constant `step` checked at its optimum `z`: over `GRID_RECHECK`
    `grid_error`s off the adaptive solution there (the optimum moved the modes up, or made
    the step unstable), the last stage is solved again at the tight step and its record
    appended to `stages`. Returns `z`, the step and the linearisation."""
    grid = schedule.grid
    tight, error = _step_error(problem, z, horizon, grid, jnp.asarray(sigma), step)
    if not float(step) > float(tight) * (1 + 1e-9) or error <= GRID_RECHECK * grid.error:
        return z, step, lin
    say(
        f"  integration step {float(step) * 1e3:.3g} ms is {error:.3g} noise levels off at the optimum: "
        f"solving again at {float(tight) * 1e3:.3g} ms"
    )
    budget = jnp.asarray(schedule.max_steps)
    z, result, steps, cost, lin = _solve(
        problem,
        z,
        sigma,
        jnp.asarray(horizon),
        tight,
        budget,
        jnp.asarray(0.0, dtype=float),
        schedule.cap,
        schedule.rtol,
        schedule.atol,
    )
    stages.append(_stage_record(horizon, steps, cost, result))
    say(f"  horizon {horizon:8.3f} s: {int(steps):3d} iterations, cost {float(cost):.6g} ({stages[-1].outcome})")
    return z, tight, lin
