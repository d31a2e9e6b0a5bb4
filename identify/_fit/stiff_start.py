"""Whether `fit`'s solver can integrate a model at given parameters within its step budget,
estimated from the model's linearisation before any simulation (`StepEstimate`).

A fit that walks into a stiff model (a mode kHz above the logs' band: an elastic joint made
nearly rigid) does not fail at once: every simulation takes tens of thousands of steps, each
Levenberg-Marquardt iteration minutes, until one solve reaches `Problem.max_steps` (seen on a
geared servo's logs: 10-16 minutes per run before `joint_elasticity` failed). The number of
steps a stiff model needs follows from its highest natural frequency, which a linearisation
gives in milliseconds.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

import flexdyn as fd

from .._model.parameters import theta_from_x, x_from_z
from .._model.problem import Problem
from .._model.residuals import chain_at, initial_states_of
from .steps import SimulationFailed

#: The adaptive Tsit5 solver's mean step, in units of `flexdyn.stable_step` (Tsit5, `safety=1`)
#: at the log's initial state, at most. Tsit5's region hugs the imaginary axis (one step
#: multiplies an undamped mode by 1.0001 at `h omega = 1`, 1.03 at 2), so the adaptive steps
#: exceed the strict limit `stable_step` finds there. Measured on a two-inertia joint (rotor
#: 100x the link) with the fit's solve (`identify.residuals.predict`, rtol 1e-8): joint mode
#: 0.5, 2 and 7 kHz, damped lightly and heavily, under a sine, a square wave and a chirp of
#: torque, over 0.5 and 2 s: the solve took 0.39-1.6 times `span / stable_step` steps (0.43-0.83
#: at 2 kHz and above, where the stiff mode sets the step). So `span / (ADAPTIVE_OVER_STABLE *
#: stable_step)` errs low: a model it calls too stiff is.
ADAPTIVE_OVER_STABLE = 3.0


@dataclasses.dataclass(frozen=True)
class StepEstimate:
    """The steps a fit's constant-step stage needs for its slowest log (SI).

    - `frequency_hz`: the highest natural frequency of the model's linearisation at the
      log's initial state, `max |lambda(A)| / (2 pi)` (`flexdyn.linearize`; for an undamped
      mode its frequency: a rotor of inertia `J1` on a spring `k` against a link `J2`,
      `sqrt(k (1/J1 + 1/J2)) / (2 pi)`);
    - `stable_step_s`: Tsit5's stability limit there (`flexdyn.stable_step`, safety 1), s;
    - `steps`: the stage's constant-step solve over the log's `span_s`: it integrates at
      `grid_safety` times the adaptive solver's mean step (`fit`'s `grid_safety`), and that
      is at most `ADAPTIVE_OVER_STABLE` stable steps, so
      `span_s / (grid_safety * ADAPTIVE_OVER_STABLE * stable_step_s)`;
    - `budget`: the solver's step limit, `Problem.max_steps` (per log and solve);
    - `log`: the log's name; `span_s`: the time its stage's solve covers, s.
    """

    frequency_hz: float
    stable_step_s: float
    steps: float
    budget: int
    log: str
    span_s: float

    @property
    def too_stiff(self) -> bool:
        """Whether the estimate exceeds the budget: the stage's solves would end on the
        solver's step limit (the estimate errs low: `ADAPTIVE_OVER_STABLE`)."""
        return self.steps > self.budget

    def reason(self) -> str:
        """What a report says of a model too stiff for the fit: the frequency, the steps and
        the budget."""
        return (
            f"too stiff for the solver: its highest natural frequency, at log '{self.log}''s initial state, is "
            f"{self.frequency_hz:.3g} Hz, so integrating the log's {self.span_s:.3g} s takes at least "
            f"{self.steps:.3g} steps (stable step {self.stable_step_s:.3g} s), over the solver's limit of "
            f"{self.budget} steps per solve"
        )


def estimate_steps(problem: Problem, theta, y0s=None, horizon: float | None = None, grid_safety: float = 0.5):
    """The `StepEstimate` of the log that needs the most steps at parameters `theta` (SI, in
    `problem.names` order) from initial states `y0s` `(L, 2n)` (default: the known ones,
    `Problem.y0_known`), over `horizon` (s from each log's onset, as `fit`'s stages; None:
    the whole logs); None when no log has a finite linearisation. Host-side (a linearisation
    and an eigenvalue problem per log)."""
    if not 0 < grid_safety <= 1:
        raise ValueError(f"estimate_steps: grid_safety expected a factor in (0, 1], got {grid_safety!r}")
    theta = jnp.asarray(theta, dtype=float)
    y0s = np.asarray(problem.y0_known if y0s is None else y0s, dtype=float)
    t, valid, onset = np.asarray(problem.t), np.asarray(problem.valid), np.asarray(problem.onset)
    log_set = np.asarray(problem.log_set)
    worst = None
    for l, name in enumerate(problem.log_names):
        span = _span(t[l][valid[l]], float(onset[l]), horizon)
        if span <= 0:
            continue
        chain = chain_at(problem, theta, jnp.asarray(log_set[l]), l)
        y0 = jnp.asarray(y0s[l])
        A = np.asarray(fd.linearize(chain, y0).A)
        if not np.all(np.isfinite(A)):  # (no estimate: the solve itself will say what fails)
            continue
        lam = np.linalg.eigvals(A)
        step = fd.stable_step(chain, y0, solver="tsit5", safety=1.0)
        steps = span / (grid_safety * ADAPTIVE_OVER_STABLE * step) if math.isfinite(step) else 0.0
        est = StepEstimate(
            float(np.max(np.abs(lam), initial=0.0)) / (2 * math.pi), step, steps, problem.max_steps, name, span
        )
        if worst is None or est.steps > worst.steps:
            worst = est
    return worst


def _span(t: np.ndarray, onset: float, horizon: float | None) -> float:
    """The time a stage's solve of one log covers (`identify.residuals`' `_simulate_log`):
    from its onset to `onset + horizon` when that ends before the log, else the whole log."""
    if t.size < 2:
        return 0.0
    if horizon is not None and onset + horizon < t[-1]:
        return float(horizon)
    return float(t[-1] - t[0])


class TooStiff(SimulationFailed):
    """`fit(stop_when_stiff=True)`'s refusal of a model too stiff for its solver before any
    stage finished (`StepEstimate.too_stiff`): raised at once, without a simulation.
    `estimate`: the `StepEstimate`; `where`: at which values (`"at its starting values"`)."""

    def __init__(self, estimate: StepEstimate, *, where: str, horizon_s: float | None, values: dict):
        super().__init__(
            f"fit: {where} the model is {estimate.reason()}; not simulated",
            horizon_s=horizon_s,
            values=values,
            logs={estimate.log: estimate.reason()},
        )
        self.estimate = estimate
        self.where = where


def stiff_at(problem: Problem, z, horizon: float | None, grid_safety: float) -> StepEstimate | None:
    """The `StepEstimate` at `fit`'s variables `z` (parameters and free initial states) over
    `horizon` when it is too stiff for the solver, else None (always for a problem with a
    fixed step, `Problem.dt`: its solves take a set number of steps)."""
    if problem.dt is not None:
        return None
    theta = theta_from_x(problem, x_from_z(problem, z.phys))
    est = estimate_steps(problem, theta, initial_states_of(problem, z.y0), horizon, grid_safety)
    return est if est is not None and est.too_stiff else None


def values_at(problem: Problem, z) -> dict:
    """Parameter name -> value (SI) at `fit`'s variables `z`."""
    theta = np.asarray(theta_from_x(problem, x_from_z(problem, z.phys)))
    return {name: float(v) for name, v in zip(problem.names, theta)}
