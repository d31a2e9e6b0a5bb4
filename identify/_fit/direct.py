"""Closed-loop logs fitted by the direct method: the logged command replayed, from the loop's fit.

A closed-loop problem (`make_problem(controller=...)`) simulates the rig's loop: the model's
controller reads the model's sensors and commands the model's drive, so errors do not integrate
over a long log as in an open-loop replay, and the fit converges from far guesses. Its
estimates are not efficient and its intervals are not honest where the rig's controller fed
back its own noise and rounding: a reading that flips a count at another instant on the rig
than in the model changes the command and all the motion after it. That difference acts like
process noise, which the output-error intervals do not carry. On the servo example over
seeded sensor count phases, 56 % of the 95 % intervals held the truth, with the damping and
the dry friction up to 7 standard errors off.

The direct method of closed-loop identification (Ljung, *System Identification*, 2nd ed.
1999, sec. 13.4; Forssell & Ljung 1999, Automatica 35:1215) fits the plant to the measured
input and output as if the log were open loop. The rig's logged command is the input the
drive received, noise and rounding of the readings it came from included, so the
trajectory it drives carries no count flips of the model's own. The measured output is then
that trajectory plus sensor noise. With the loop's one-sample delay (the controller holds a
command computed from earlier readings) the input at each instant is independent of the
sensor noise at that instant. The estimate is then consistent, and its intervals (the fit's
HAC sandwich, `identify/_fit/hac.py`) are right, when the noise model is: here white,
possibly rounded, sensor noise.

Its weakness is the one the loop fit avoids: from far guesses an open-loop replay drifts.
So the direct fit starts at the loop fit's optimum (`direct_fit`), one start and one stage
over the whole logs. It is kept only if it converges and fits every channel it shares with
the loop fit no worse, relative to each channel's noise floor, than `DRIFT_TOLERANCE` times
the loop fit. Otherwise the loop fit is the result, with the reason (`FitResult.direct_note`)
and its caveat on the intervals (`FitResult.closed_loop_caveat`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._model.parameters import Parameter
from .._model.problem import Problem
from .fit import fit
from .result import FitResult

#: the direct fit is kept where each shared channel's residual RMS over its noise floor is
#: at most this many times the loop fit's: a replay that drifts fits worse
DRIFT_TOLERANCE = 1.5


def start_parameters(loop_fit: FitResult) -> list[Parameter]:
    """The loop fit's free parameters, their guesses at its values (a per-log parameter at
    the median of its logs' values), bounds and per-log flags unchanged."""
    out = []
    for p in loop_fit.problem.parameters:
        if p.per_log:
            guess = float(np.median(list(loop_fit.per_log[p.name].values())))
        else:
            guess = float(loop_fit.value[p.name])
        out.append(Parameter(p.name, float(np.clip(guess, p.lower, p.upper)), p.lower, p.upper, per_log=p.per_log))
    return out


def drift_reason(loop_fit: FitResult, direct: FitResult) -> str:
    """Why the direct fit is not kept ("" when it is): not converged, or a channel fitted
    more than `DRIFT_TOLERANCE` times worse against its noise floor than by the loop fit."""
    if not direct.converged:
        why = f"on bounds {direct.at_bounds}" if direct.at_bounds else "it did not converge"
        return f"the direct fit (logged command replayed) was not kept: {why}"
    worse = []
    for c, q in direct.fit_quality.items():
        before = loop_fit.fit_quality.get(c)
        if before is None:
            continue
        ratio, ratio_loop = q["ratio"], before["ratio"]
        if ratio > DRIFT_TOLERANCE * ratio_loop:
            worse.append(f"{c} {ratio:.3g}x its noise floor against {ratio_loop:.3g}x closed loop")
    if worse:
        return (
            "the direct fit (logged command replayed) was not kept: it drifts, " + "; ".join(worse) + " (a "
            "replay of a long log integrates every model error; fit closed loop only, or with shooting='multiple')"
        )
    return ""


def direct_fit(loop_fit: FitResult, replay: Problem, **options) -> FitResult:
    """The direct-method fit of closed-loop logs (module docstring), or `loop_fit` where it
    is not kept.

    `loop_fit`: `fit` of the closed-loop problem; `replay`: the same logs, parameters,
    measurement and declared noise without the controller, the logged command their input
    (`identify.problem_from_experiment(..., replay=True)`); `options`: passed to `fit`
    (one start, one stage, no frequency initialisation and no extra starts unless given).
    The result keeps the loop fit as `FitResult.loop_fit` and says which one it is in
    `FitResult.direct_note`. A direct fit that fails (a replay whose simulation fails, say)
    leaves the loop fit as the result, the error in the note."""
    if replay.loop is not None:
        raise ValueError("direct_fit: `replay` must be open loop (a problem without a controller)")
    if not loop_fit.converged:
        return dataclasses.replace(
            loop_fit, direct_note="no direct fit (logged command replayed): the closed-loop fit did not converge"
        )
    options = {"n_starts": 1, "n_stages": 1, "frequency_init": False, "extra_starts": (), **options}
    try:
        direct = fit(replay, start_parameters(loop_fit), **options)
    except Exception as e:  # noqa: BLE001 (any failure: the finished loop fit is kept, with the reason)
        why = f"{type(e).__name__}: {e}".splitlines()[0]
        return dataclasses.replace(loop_fit, direct_note=f"the direct fit (logged command replayed) failed: {why}")
    reason = drift_reason(loop_fit, direct)
    if reason:
        return dataclasses.replace(loop_fit, direct_note=reason, direct_rejected=direct)
    note = (
        "values and intervals by the direct method: the logged command replayed open loop, started at the "
        f"closed-loop fit's optimum (cost {loop_fit.cost:.6g}; `loop_fit`)"
    )
    return dataclasses.replace(direct, loop_fit=loop_fit, direct_note=note)
