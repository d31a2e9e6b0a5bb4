"""`Score` and `Cause`, the BIC and F-test verdicts of a round, and the held-out gain's standard error."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .._model.problem import Problem
from . import catalogue as cat
from .held_out import _no_headroom


@dataclasses.dataclass
class Score:
    """One candidate's fit and scores (SI)."""

    name: str
    where: str
    params: dict  # name -> value
    cost: float
    delta_bic: float
    p_value: float
    held_out_rms: dict  # channel -> RMS (SI)
    held_out_gain: float
    accepted: bool
    k: int
    # not fitted: its cost and dBIC are those one Gauss-Newton step predicts (`_screen`), and
    # `screen_reason` says why that ranked it out
    screened: bool = False
    screen_reason: str = ""
    # structural candidates (a model of their own): name -> {std_error, ci95} of the new
    # parameters, from that model's fit (continuous ones get theirs from the joint model)
    intervals: dict = dataclasses.field(default_factory=dict)
    # two entries fitted together (the pair search): their labels; else empty
    members: tuple = ()
    # the standard error of `held_out_gain` from the held-out samples (`gain_standard_error`)
    held_out_gain_se: float = float("nan")
    # a candidate that passes both tests with fitted values it does not plausibly reach
    # (`catalogue.Plausibility.judge`): the sentences saying which; it is not accepted.
    # Empty for every other candidate (a value that fails the tests anyway is not judged).
    implausible: list = dataclasses.field(default_factory=list)
    # a candidate whose fit never left its starting values, from its own starts and wider
    # ones (`continuous._never_left`): why, and its dBIC, p-value and held-out gain are NaN
    # (no evidence for or against the effect); never accepted. Empty for a fitted one.
    not_fitted: str = ""

    @property
    def label(self) -> str:
        return cat.pair_label(self.members) if self.members else f"{self.name}:{self.where}"


@dataclasses.dataclass
class Cause:
    """An accepted model extension with its fitted parameters and 95 % intervals."""

    name: str
    where: str
    description: str
    parameters: dict  # name -> {value, std_error, ci95, unit, method}: `method` "white" or "HAC ..." (`_fit/hac.py`)
    delta_bic: float
    held_out_gain: float
    # the other causes accepted together with this one (a pair found by the pair search;
    # `delta_bic` and `held_out_gain` are then the pair's)
    together_with: list = dataclasses.field(default_factory=list)
    # fitted values outside what the component plausibly does (`catalogue.implausible`)
    warnings: list = dataclasses.field(default_factory=list)
    held_out_gain_se: float = float("nan")  # `Score.held_out_gain_se`

    def marginal(self, min_gain: float) -> bool:
        """Whether the held-out gain is within two standard errors of the bar it passed."""
        return bool(np.isfinite(self.held_out_gain_se) and self.held_out_gain - min_gain < 2 * self.held_out_gain_se)


def _limit_text(p: dict) -> str:
    """A detection limit as text: `0.0012 N m`, or `1 +- 0.0047` about a non-zero neutral value."""
    unit = f" {p['unit']}" if p["unit"] and p["unit"] != "1" else ""
    if p.get("neutral", 0.0) == 0.0:
        return f"{p['value']:.2g}{unit}"
    return f"{p['neutral']:g} +- {p['value']:.2g}{unit}"


def _rms_per_channel(problem: Problem, r: np.ndarray, sigma: np.ndarray) -> dict:
    """Per-channel RMS (SI) of weighted residuals `r` (flattened (L, T, C))."""
    L, T, C = problem.measured.shape
    r = np.asarray(r).reshape(L, T, C) * sigma[None, None, :]
    mask = np.asarray(problem.valid[:, :, None] & problem.present[:, None, :])
    return {c: float(np.sqrt(np.mean(r[:, :, k][mask[:, :, k]] ** 2))) for k, c in enumerate(problem.channels)}


def _with_headroom(labels: set, problem: Problem, r_used, min_gain: float, rnd: int, notes: list, say) -> set:
    """`labels`, the structural candidates to fit in round `rnd` (from 1; in round 1 all
    of them, from the baseline), or none when the current model's held-out residual
    `r_used` leaves no room for `min_gain` (`_no_headroom`; the decision goes to
    `notes`)."""
    if not labels:
        return labels
    full, why = _no_headroom(problem, r_used, min_gain)
    if not full:
        return labels
    if rnd == 1:
        text = f"{', '.join(sorted(labels))} not fitted: the baseline is at the noise; {why}"
    else:
        text = f"{', '.join(sorted(labels))} not refitted: the model of the previous round is at the noise; {why}"
    say(f"  round {rnd}: {text}")
    notes.append({"round": rnd, "text": text})
    return set()


def _promising(drops: dict, cost: float, n: int, bic_threshold: float) -> set:
    """The structural candidates whose cost drop `drops[label] = (drop, k)`, taken off a
    model of the previous round, would pass the BIC test against a model of cost `cost`:
    `N ln(cost / (cost - drop)) > bic_threshold + k ln N`."""
    return {
        label for label, (drop, k) in drops.items() if drop > cost * -math.expm1(-(bic_threshold + k * math.log(n)) / n)
    }


def gain_standard_error(r_base, r_ext) -> float:
    """The standard error of a held-out gain `sqrt(mean(r_base^2) / mean(r_ext^2))` from
    its paired samples (the same held-out samples under the two models; NaN if they do not
    pair up). Delta method: `log gain^2 = log mean(a) - log mean(b)` (`a = r_base^2`,
    `b = r_ext^2`) has variance `var(a / mean(a) - b / mean(b)) / n_eff`, with `n_eff = n
    (1 - rho) / (1 + rho)` for a lag-1 autocorrelation `rho >= 0` of that difference (a
    residual correlated in time holds fewer independent samples). A gain that passes its bar
    by less than its own scatter is marked marginal (`Cause.marginal`)."""
    a, b = np.square(np.asarray(r_base, float)), np.square(np.asarray(r_ext, float))
    if a.shape != b.shape or a.size < 10 or not (a.mean() > 0 and b.mean() > 0):
        return float("nan")
    d = a / a.mean() - b / b.mean()
    dc = d - d.mean()
    var = float(np.mean(dc**2))
    if var == 0.0:
        return 0.0
    rho = min(max(float(np.mean(dc[1:] * dc[:-1])) / var, 0.0), 0.99)
    n_eff = d.size * (1.0 - rho) / (1.0 + rho)
    gain = math.sqrt(a.mean() / b.mean())
    return 0.5 * gain * math.sqrt(var / n_eff)


def round_verdicts(scores) -> dict:
    """Label -> `"named"` for a round's first accepted candidate (the one the search
    names), `"passes, not named (the named one is better)"` for the others that pass both
    tests, `"passes, not named: implausible: ..."` for one that passes them with implausible
    values (`Score.implausible`), `"not fitted: ..."` for one whose fit never left its
    start (`Score.not_fitted`), `""` else: what the console, the summary and the report show."""
    named = next((s.label for s in scores if s.accepted), None)
    return {s.label: _verdict(s, named) for s in scores}


def _verdict(s: Score, named: str | None) -> str:
    if s.accepted:
        return "named" if s.label == named else "passes, not named (the named one is better)"
    if s.not_fitted:
        return f"not fitted: {s.not_fitted}"
    if s.implausible:  # (the report says once what such a value usually means)
        return f"passes, not named: implausible: {'; '.join(x for x in s.implausible if x != cat.STANDING_IN)}"
    return ""


def not_fitted_of(rounds) -> dict:
    """The single catalogue candidates whose last score in `rounds` (lists of `Score`, in
    order) is not fitted (`Score.not_fitted`): label -> `"round n: why"`. The search has
    not tested them: no detection limit, no evidence against."""
    last = {}
    for r, scores in enumerate(rounds, start=1):
        for s in scores:
            if not s.members:
                last[s.label] = (r, s)
    return {lab: f"round {r}: {s.not_fitted}" for lab, (r, s) in last.items() if s.not_fitted}
