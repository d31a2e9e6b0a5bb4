"""`fit`: Levenberg-Marquardt through the simulation over a growing horizon, with multi-start and
restarts from a bound.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

import flexdyn as fd

from .._data import noise_floor as nf
from .._model.parameters import Parameter, names_at_bounds, x_from_theta, x_from_z, z_from_x
from .._model.problem import Problem, check_same_parameters, guesses_of
from .jacobian import _covariance_at
from .levenberg_marquardt import _check_budgets, _check_damping, _result_name, _solve
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
from .starts import _distinct, _extra_starts, _frequency_initialise, _starts
from .steps import GRID_ERROR, GRID_RECHECK, _default_horizons, _Grid, _say_onsets, _stage_step, _step_error


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
      from its onset, from its initial state (the rest before it skipped:
      `identify.residuals._simulate_log`); the last stage simulates every log whole.
    - `estimate_noise`: re-estimate the noise level of these channels (True: all; None,
      the default: those `make_problem` was given no noise for) from the residuals after
      the first pass and refit with the new weights, again until the residuals' RMS agrees
      with the weights within `NOISE_AGREEMENT` (at most `NOISE_ROUNDS` passes). Review:
      from make_problem's default weights (1 % of each channel's RMS) one refit left the
      angle's weight at 0.259 deg while its residual was 0.050 deg (the noise), and the
      intervals 3.5x too wide. (Until 2026-12-05 the default re-estimated declared levels
      too, which make_problem's docstring said it would not: review.)
    - `max_steps`, `rtol`, `atol`: Levenberg-Marquardt settings per stage (termination on
      the RMS change of the residuals and parameters, see `_solve`).
    - `grid_safety`: each stage integrates with a constant step, `grid_safety` times the
      mean step of the adaptive solver at the stage's starting parameters. An adaptive
      solver inside the fit makes the loss a noisy function of the parameters (its
      accept/reject decisions flip under tiny parameter changes: measured 1e-7 relative
      at rtol 1e-10), which stalls Levenberg-Marquardt; a grid that is frozen during
      a stage makes the loss smooth.
    - `grid_error`: the stage's step is then coarsened (by up to `GRID_COARSEN`) while the
      outputs it simulates stay within `grid_error` noise levels of the adaptive solution
      at the stage's start; after the last stage the step is checked again at the optimum
      and, over `GRID_RECHECK` times that, the stage is solved again at the tight step.
      None: the tight step (as before 2026-12-05). Measured on a 2-mode flexible link
      (two 2 s logs at 500 Hz, 3 parameters): the warm fit 14.0 -> 6.3 s, the same values
      to 8 digits (`benchmarks/README.md`: the fit benchmark side by side).
    - `n_starts`, `start_spread`: the first (shortest) stage is solved from `n_starts`
      points (the guess and a deterministic design within a factor `start_spread` of it,
      see `_starts`), and the best continues. Measured on the
      4-parameter flexible-arm benchmark: from guesses -50 %/+100 % off, single-start
      growing horizon converged in 20 of 24 trials, all failures starting at 2x EI.
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
      count once; none with `n_starts=1`). The result is the attempt off the bounds with the lowest
      `identify.noise_floor.score`; a restart that ends with the same score (within
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
      similar to the measured one (`identify.frequency_init`): a frequency-domain
      initialisation, blind to phase, that puts the first stage in the right basin when EI
      is far off. 25 simulations of the logs per EI (17 on a grid, 8 refining; measured
      with the 18 before the refinement grew: ~1 s for the 1.2 s test log, ~6 s for a 3 s
      one, ~11 s for the spinning-link example's two 4 s logs, on 2 cores).
    - `first_damping`: `tau` of the Levenberg-Marquardt solve that starts from the guess when
      there is one start (`n_starts=1`, or no free physical parameter): its first damping
      is `tau * max diag(J^T J)` at the guess (`identify.trust_region`; 0 keeps
      optimistix's damping 1, an undamped Gauss-Newton step at our residuals' scale).
      Measured (`benchmarks/bench_fit_convergence.py`, 16 guesses -50 %/+100 % off): a
      growing horizon from one start converged in 16 of 16 fits instead of 12, single
      shooting from the benchmark's guess took 10 steps instead of 22. The multi-start
      stage and the stages that continue from an optimum keep optimistix's start (there,
      `tau` made the default fit slower for the same convergence).
    - `progress`: callable taking a message string (e.g. `print`), or None.
    """
    _check_damping(first_damping)
    _check_budgets(max_steps=max_steps, early_max_steps=early_max_steps)
    parameters = problem.parameters if parameters is None else parameters
    check_same_parameters(problem, parameters, "fit")
    extra = _extra_starts(problem, parameters, extra_starts)
    fd.ensure_mapping_headroom()  # a fit compiles ~10-50 programs (flexdyn.program_cache)
    start = time.perf_counter()
    say = progress or (lambda msg: None)
    x0 = x_from_theta(problem, guesses_of(problem, parameters))
    if frequency_init:
        x0 = _frequency_initialise(problem, x0, say, grid_safety)
    z = {
        "phys": jnp.asarray(z_from_x(problem, x0)),
        "y0": jnp.asarray([problem.y0_known[l, s] for l, s in problem.y0_free], dtype=float),
        "offset": jnp.zeros(len(problem.offset_free)),
    }
    sigma = problem.sigma
    horizons = list(horizons) if horizons is not None else _default_horizons(problem, n_stages)
    _say_onsets(problem, horizons, say)
    stages = []
    estimate_noise = _noise_to_estimate(problem, estimate_noise)
    rounds = NOISE_ROUNDS if estimate_noise else 1
    candidates = [z]
    # one compiled Levenberg-Marquardt program for every stage and start: the iteration
    # budget is traced (`_BudgetedLM`), the loop bound `cap` static
    cap = max(max_steps, early_max_steps)
    if (n_starts > 1 or len(extra)) and problem.names:
        # Multi-start on the shortest horizon: a few cheap short fits from a design around
        # the guess, one after another with the stages' compiled program (a vmapped call
        # would be a second program, ~18 s more compilation on 2 cores, and on the CPU it
        # is not faster); the best ones seed the growing horizon.
        h = horizons[0]
        step = _stage_step(problem, z, h, _Grid(grid_safety, grid_error), sigma)
        xs = list(_starts(problem, x0, n_starts, start_spread)) + extra
        runs = [
            _solve(
                problem,
                {"phys": jnp.asarray(z_from_x(problem, x)), "y0": z["y0"], "offset": z["offset"]},
                sigma,
                jnp.asarray(h),
                step,
                jnp.asarray(early_max_steps),  # an array: traced, not a static argument
                jnp.asarray(0.0, dtype=float),  # optimistix's start: see `first_damping`
                cap,
                rtol,
                atol,
            )
            for x in xs
        ]
        costs = np.asarray([float(r[3]) for r in runs])
        order = np.argsort(np.where(np.isfinite(costs), costs, np.inf))
        candidates = _distinct([runs[int(i)][0] for i in order], costs[order])[: max_restarts + 1]
        best = int(order[0])
        stages.append(
            {
                "horizon_s": float(h),
                "iterations": max(int(r[2]) for r in runs),
                "cost": float(costs[best]),
                "result": _result_name(runs[best][1]),
                "starts": len(xs),
                "start_costs": [float(c) for c in costs],
            }
        )
        n_design = len(xs) - len(extra)
        which = f"start {best + 1}" if best < n_design else f"extra start {best - n_design + 1}"
        say(
            f"  horizon {h:8.3f} s: {len(xs)} starts, best cost {float(costs[best]):.6g} from {which} "
            f"(costs in order, the guess first: {', '.join(f'{float(c):.4g}' for c in costs)})"
        )
    # Grow the horizon from the best start; if that ends on a bound of a parameter or with
    # a residual far above the model-free noise floor (a wrong basin: `restart_poor_fit`),
    # try the next-best starts, and keep the one off the bounds that explains the data
    # best (`identify.noise_floor.score`: unlike the cost, it does not depend on the noise
    # weights each attempt re-estimated).
    floors = noise_floors(problem)
    outcomes, why = [], ""
    for attempt, z in enumerate(candidates):
        if attempt:
            say(f"  {why}: growing the horizon again from the first stage's optimum #{attempt + 1}")
        z, sigma_a, step, lin, tried = _grow(
            problem,
            z,
            sigma,
            horizons,
            rounds,
            estimate_noise,
            _Grid(grid_safety, grid_error),
            max_steps,
            early_max_steps,
            cap,
            rtol,
            atol,
            say,
            0.0 if n_starts > 1 and problem.names else first_damping,
        )
        x = x_from_z(problem, z["phys"])
        bounded = bool(names_at_bounds(problem, np.asarray(x)))
        ms = _residual_ms(problem, z, sigma_a, step, lin)
        quality = nf.goodness(problem.channels, ms, *floors)
        poor = [c for c, q in quality.items() if q["poor"]]
        score = nf.score(ms, *floors)
        same = _same_misfit(bounded, score, [(o[0], o[1]) for o in outcomes])
        outcomes.append((bounded, score, z, sigma_a, step, lin, tried, ms))
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
        if attempt + 1 == len(candidates):
            # (review: 8 starts at the same cost, a poor fit, and no trace of whether the
            # documented restart had run)
            say(
                f"  {'this attempt: ' if attempt else ''}{why}; not restarted: "
                + (
                    "no other start (n_starts=1 and no extra starts)"
                    if len(candidates) == 1 and not (n_starts > 1 or len(extra))
                    else f"the {len(candidates)} distinct optima of the multi-start stage kept for restarts "
                    f"(max_restarts={max_restarts}) have all been grown"
                )
                + ": the misfit is more likely the model's or the data's than the start's"
            )
    kept = min(range(len(outcomes)), key=lambda k: (outcomes[k][0], outcomes[k][1]))
    if len(outcomes) > 1:
        # (review: "a parameter ended on its bound" was read as said of the result, which
        # was the first attempt, off the bounds)
        say(
            f"  keeping attempt {kept + 1} of {len(outcomes)}"
            + (" (on a bound)" if outcomes[kept][0] else ", off the bounds")
            + ", the one that explains the data best (residual RMS against the noise floor)"
        )
    _, _, z, sigma, step, lin, tried, ms = outcomes[kept]
    stages.extend(tried)
    say("  computing standard errors (exact Jacobian at the optimum) ...")
    x = x_from_z(problem, z["phys"])
    cov, blocks = _covariance_at(problem, x, z, sigma, step, *lin)
    result = _finish(problem, parameters, z, x, sigma, step, cov, stages, time.perf_counter() - start, ms, blocks)
    return dataclasses.replace(result, sigma_estimated=tuple(estimate_noise))


def _grow(
    problem,
    z,
    sigma,
    horizons,
    rounds,
    estimate_noise,
    grid,
    max_steps,
    early_max_steps,
    cap,
    rtol,
    atol,
    say,
    tau_first,
):
    """The growing-horizon stages (and a noise re-estimation round) from `z`; returns the
    last stage's `z`, noise levels, step, linearisation (`_solve`) and horizon, and the
    stages' records."""
    stages = []
    step = lin = None
    for rnd in range(rounds):
        # The horizon grows in the first round only; later rounds (new noise weights) start
        # at the optimum, where the full horizon is safe.
        for k, h in enumerate(horizons if rnd == 0 else horizons[-1:]):
            last = rnd > 0 or k == len(horizons) - 1
            step = _stage_step(problem, z, h, grid, sigma)
            budget = jnp.asarray(max_steps if last else early_max_steps)  # traced: no recompilation
            tau = jnp.asarray(tau_first if (rnd == 0 and k == 0) else 0.0, dtype=float)
            z, result, steps, cost, lin = _solve(problem, z, sigma, jnp.asarray(h), step, budget, tau, cap, rtol, atol)
            stages.append(
                {"horizon_s": float(h), "iterations": int(steps), "cost": float(cost), "result": _result_name(result)}
            )
            say(
                f"  horizon {h:8.3f} s: {int(steps):3d} iterations, cost {float(cost):.6g} ({stages[-1]['result']}"
                + (
                    f": an early stage's budget, early_max_steps={early_max_steps}; the next stage goes on from here)"
                    if not last and stages[-1]["result"] == "max_steps_reached"
                    else ")"
                )
            )
        if rnd + 1 < rounds:
            new = _reestimate_sigma(problem, z, sigma, estimate_noise, step)
            change = float(np.max(np.abs(np.log(np.asarray(new) / np.asarray(sigma)))))
            if rnd > 0 and change < math.log1p(NOISE_AGREEMENT):
                say(f"  noise re-estimated again: within {100 * NOISE_AGREEMENT:g} % of the weights used: done")
                break
            sigma = new
            say("  noise re-estimated: " + _noise_text(problem.channels, sigma, estimate_noise))
    if grid.error and step is not None:
        tight, error = _step_error(problem, z, h, grid, jnp.asarray(sigma), step)
        if float(step) > float(tight) * (1 + 1e-9):
            if not error <= GRID_RECHECK * grid.error:
                # the optimum moved the modes up (or made the step unstable): the last stage
                # again, at the tight step
                say(
                    f"  integration step {float(step) * 1e3:.3g} ms is {error:.3g} noise levels off at the optimum: "
                    f"solving again at {float(tight) * 1e3:.3g} ms"
                )
                step = tight
                budget = jnp.asarray(max_steps)
                z, result, steps, cost, lin = _solve(
                    problem, z, sigma, jnp.asarray(h), step, budget, jnp.asarray(0.0, dtype=float), cap, rtol, atol
                )
                stages.append(
                    {
                        "horizon_s": float(h),
                        "iterations": int(steps),
                        "cost": float(cost),
                        "result": _result_name(result),
                    }
                )
                say(
                    f"  horizon {h:8.3f} s: {int(steps):3d} iterations, cost {float(cost):.6g} ({stages[-1]['result']})"
                )
    return z, sigma, step, (lin, h), stages
