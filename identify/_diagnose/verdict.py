"""The diagnosis's verdict: *named*, *none* or *inconclusive*.

- **named**: a cause passed both tests: significant on the fit logs (dBIC below
  `-bic_threshold`) and confirmed on the held-out logs (held-out gain at least `min_gain`).
- **inconclusive**: nothing named, but some fitted candidate is significant on the fit logs
  and the held-out logs could not confirm or refute it: even a perfect model could not be
  shown to gain `min_gain` on them (`can_show_gain`: their residual is not clearly more
  than `min_gain` times its own noise floor), or the candidate's held-out gain is within
  two of its standard errors of `min_gain`; or it passed both tests with implausible
  values (an effect the catalogue lacks, most likely). The competing candidates are listed
  with their scores, and what data would decide between them.
- **none**: no fitted candidate is significant on the fit logs, or each one that is fails
  on held-out logs that had room to show its gain.

Reporting *none* where the fit logs show a significant systematic residual that the held-out
logs cannot test would tell a user that the model is complete when the data say otherwise
(a rigid joint that is really elastic, missed because the gentler log was held out).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .._data import units
from .._model.problem import Problem
from .held_out import FLOOR_MARGIN_SE, Headroom

NAMED, NONE, INCONCLUSIVE = "named", "none", "inconclusive"


@dataclasses.dataclass(frozen=True)
class Verdict:
    """`Diagnosis.verdict`: `kind` (`NAMED`, `NONE`, `INCONCLUSIVE`), `reason` (a sentence),
    for an inconclusive one the `competing` candidates (dicts: `label`, `delta_bic`,
    `held_out_gain`, `held_out_gain_se`, `why`: what kept it from being named; best dBIC
    first) and `to_decide`: what data would confirm or separate them."""

    kind: str
    reason: str
    competing: tuple = ()
    to_decide: tuple = ()

    def lines(self) -> list[str]:
        out = [f"verdict: {self.kind.upper()}: {self.reason}"]
        for c in self.competing:
            se = c["held_out_gain_se"]
            out.append(
                f"  {c['label']}: dBIC {c['delta_bic']:.1f} on the fit logs, held-out gain {c['held_out_gain']:.3f}x"
                + (f" (SE {se:.2g})" if np.isfinite(se) else "")
                + f": {c['why']}"
            )
        out += [f"  to decide: {t}" for t in self.to_decide]
        return out

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True)
class Excitation:
    """How hard a set of logs drives the rig: the largest |input| (each joint's input, in its
    own unit: N m, V or A) and each channel's peak-to-peak range (SI)."""

    input_peak: dict
    range: dict

    @staticmethod
    def of(problem: Problem, inputs: tuple[str, ...]) -> Excitation:
        valid = np.asarray(problem.valid, bool)
        u = np.asarray(problem.torque_v)
        peak = {name: float(np.max(np.abs(u[:, :, j][valid]), initial=0.0)) for j, name in enumerate(inputs)}
        measured, present = np.asarray(problem.measured), np.asarray(problem.present, bool)
        rng = {}
        for k, c in enumerate(problem.channels):
            logs = [l for l in range(measured.shape[0]) if present[l, k] and valid[l].any()]
            if logs:
                rng[c] = float(max(np.ptp(measured[l, valid[l], k]) for l in logs))
        return Excitation(peak, rng)


def verdict_of(
    causes: list,
    rounds: list,
    *,
    bic_threshold: float,
    min_gain: float,
    headroom: Headroom,
    fit: Excitation,
    held_out: Excitation,
) -> Verdict:
    """The verdict of a search (see the module docstring): `causes` named, the `rounds`'
    scores (`Score`), the baseline's held-out `headroom`, and how hard the fit and the
    held-out logs drive the rig (for what data would decide)."""
    if causes:
        return Verdict(NAMED, "each cause below is significant on the fit logs and confirmed on the held-out logs")
    at_noise = not can_show_gain(headroom, min_gain)
    competing, refuted = [], []
    for s in _significant(rounds, bic_threshold):
        why = _why_not_named(s, min_gain, at_noise, headroom)
        (refuted if why is None else competing).append((s, why))
    if competing:
        rows = tuple(
            {
                "label": s.label,
                "delta_bic": float(s.delta_bic),
                "held_out_gain": float(s.held_out_gain),
                "held_out_gain_se": float(s.held_out_gain_se),
                "why": why,
            }
            for s, why in competing
        )
        reason = (
            f"{len(rows)} candidate(s) fit the fit logs significantly better (dBIC below -{bic_threshold:g}), and the "
            "held-out logs could not confirm or refute them: the model is probably incomplete, but the data cannot "
            "say how"
        )
        return Verdict(INCONCLUSIVE, reason, rows, _to_decide(at_noise, headroom, fit, held_out, min_gain))
    if refuted:
        best = min(refuted, key=lambda p: p[0].delta_bic)[0]
        return Verdict(
            NONE,
            f"{len(refuted)} candidate(s) fit the fit logs significantly better, but each failed on held-out logs "
            f"with room to show it (best {best.label}: dBIC {best.delta_bic:.1f}, held-out gain "
            f"{best.held_out_gain:.3f}x, below {min_gain:g}x): what they fit does not carry over to other logs",
        )
    return Verdict(NONE, f"no candidate fits the fit logs significantly better (dBIC below -{bic_threshold:g})")


def can_show_gain(headroom: Headroom, min_gain: float) -> bool:
    """Whether held-out logs with this `headroom` could show a held-out gain of `min_gain`:
    a model that reaches their noise floor gains `ratio`, so the ratio must exceed
    `min_gain` by `FLOOR_MARGIN_SE` standard errors of the floor; or the residual is not
    white (a misfit the floor takes for noise, near the Nyquist frequency: the ratio then
    understates it). The reverse of the margin of `Headroom.at_the_noise`, which stops
    refits only when no gain is possible: here a refutation needs a gain that was."""
    white = all(abs(a) * math.sqrt(headroom.n) < FLOOR_MARGIN_SE + 1.0 for a in headroom.autocorrelation)
    return not white or headroom.ratio * (1.0 - FLOOR_MARGIN_SE * headroom.floor_se) >= min_gain


def _significant(rounds: list, bic_threshold: float) -> list:
    """Each label's latest fitted score that is significant on the fit logs, best dBIC first
    (not one ranked by its screening step only, nor one whose fit never left its start)."""
    latest = {}
    for scores in rounds:
        for s in scores:
            if not s.screened and not s.not_fitted:
                latest[s.label] = s
    return sorted((s for s in latest.values() if s.delta_bic < -bic_threshold), key=lambda s: s.delta_bic)


def _why_not_named(s, min_gain: float, at_noise: bool, headroom: Headroom) -> str | None:
    """Why a candidate significant on the fit logs was neither named nor refuted; None when
    the held-out logs refuted it (its gain clearly below the bar on data with room for it)."""
    if s.implausible:
        return "passes both tests only with implausible values (" + "; ".join(s.implausible) + ")"
    if at_noise:
        return (
            f"the held-out logs are near their noise floor (residual {headroom.ratio:.3f}x it, SE "
            f"{100 * headroom.floor_se:.1f} %): no model could be shown to gain {min_gain:g}x there"
        )
    se = s.held_out_gain_se
    if np.isfinite(se) and s.held_out_gain + 2 * se >= min_gain:
        return f"its held-out gain is within two standard errors of the {min_gain:g}x bar"
    return None


def _to_decide(at_noise: bool, headroom: Headroom, fit: Excitation, held_out: Excitation, min_gain: float) -> tuple:
    """What data would confirm or separate the competing candidates."""
    out = []
    weaker = [
        f"{c} ranges over {_amount(c, held_out.range[c])} in the held-out logs, {_amount(c, r)} in the fit logs"
        for c, r in fit.range.items()
        if c in held_out.range and held_out.range[c] < 0.5 * r
    ]
    inputs = [
        f"{name} peaks at {held_out.input_peak[name]:.3g} in the held-out logs, {p:.3g} in the fit logs"
        for name, p in fit.input_peak.items()
        if p > 0 and held_out.input_peak.get(name, 0.0) < 0.5 * p
    ]
    if at_noise or weaker or inputs:
        out.append(
            "held-out data that excite the rig as the fit logs do: "
            + ("; ".join(inputs + weaker) if inputs or weaker else "the held-out logs show no model error above noise")
            + ". Hold out a log driven at least as hard (or swap the logs' roles) and diagnose again"
        )
    out.append(
        f"longer or more held-out logs: a held-out gain is confirmed when it exceeds {min_gain:g}x by more than "
        "two of its standard errors"
    )
    return tuple(out)


def _amount(channel: str, value: float) -> str:
    factor, unit = units.display_unit(channel)
    return f"{value * factor:.3g} {unit}"
