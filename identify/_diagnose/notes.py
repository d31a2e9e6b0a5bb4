"""The notes a diagnosis carries: what was not tried and why, convergence, poorly determined values."""

from __future__ import annotations

import numpy as np

from . import catalogue as cat
from .held_out import _no_headroom, held_out_headroom


def _not_tried(catalogue, offered, cands, exclude, inapplicable: dict, by_kind: dict | None = None) -> dict:
    """`Diagnosis.not_tried`: each entry of `catalogue` with no candidate in `cands`, and
    why (`catalogue.not_applicable`, excluded by the caller, or its parameters already free
    in the baseline), in catalogue order; then, by label, each sensor entry on a channel
    whose sensor kind cannot have it (`by_kind`: `catalogue.kind_left_out`)."""
    by_kind = by_kind or {}
    out = {}
    for name in catalogue:
        ruled_out = {label: why for label, why in by_kind.items() if label.split(":", 1)[0] == name}
        mine = [c for c in offered if c.name == name]
        if any(c.name == name for c in cands):
            pass
        elif not mine:
            if not ruled_out:  # (else every channel's kind rules it out: said below, by channel)
                out[name] = inapplicable.get(name, "not offered on this rig and these logs")
        elif all(c.label in exclude for c in mine):
            out[name] = f"excluded by the caller ({', '.join(c.label for c in mine)})"
        else:
            out[name] = "its parameters are free in the baseline already (it is part of the model)"
        out.update(ruled_out)
    return out


def _after_continuous_at_noise(labels: set, scores, fits, problem, min_gain: float, rnd: int, notes, say) -> set:
    """`labels`, the structural candidates still to fit in round `rnd`, or none when an
    accepted continuous candidate of the round (the best by dBIC) brings the held-out
    residual to the noise (`_no_headroom` of its held-out residual; the decision goes to
    `notes`)."""
    passing = [s for s in scores if s.accepted and not s.members and s.label in fits["labels"]]
    # (a candidate not fitted has no dBIC: `Score.not_fitted`)
    fitted = [s for s in scores if not s.screened and not s.members and np.isfinite(s.delta_bic)]
    # the round's continuous results are said before the structural fits, which take long
    structural = f"fitting the structural candidates ({', '.join(sorted(labels))}; each a model of its own)"
    if not passing:
        lead = min(fitted, key=lambda s: s.delta_bic, default=None)
        say(
            f"  round {rnd}: no continuous candidate passes"
            + (
                f" (best: {lead.label}, dBIC {lead.delta_bic:.1f}, held-out gain {lead.held_out_gain:.3f}x)"
                if lead is not None
                else ""
            )
            + f": {structural}"
        )
        return labels
    best = min(passing, key=lambda s: s.delta_bic)
    full, why = _no_headroom(problem, fits["ho"][fits["labels"].index(best.label)], min_gain)
    if not full:
        ratio = held_out_headroom(problem, fits["ho"][fits["labels"].index(best.label)]).ratio
        say(
            f"  round {rnd}: {best.label} passes (dBIC {best.delta_bic:.1f}, held-out gain {best.held_out_gain:.3f}x) "
            f"but leaves the held-out residual at {ratio:.3g} times its noise floor: {structural}"
        )
        return labels
    text = (
        f"{', '.join(sorted(labels))} not fitted: {best.label} passes and brings the held-out residual to the "
        f"noise (with it, {why.replace('no candidate can reach', 'nothing can add')}); a structural model could "
        "at best tie with it"
    )
    say(f"  round {rnd}: {text}")
    notes.append({"round": rnd, "text": text})
    return set()


#: `_stuck_above_nested`: an excess below this fraction of the current cost is the
#: optimiser's precision, not a local minimum (it matters where the baseline's misfit is large)
STUCK_RELATIVE = 1e-4


def _stuck_above_nested(c, cost: float, cost_current: float, bic_threshold: float, limit: str | None = None) -> str:
    """A note when candidate `c`, whose model holds the current one as a limit, ended its
    fit with a cost (chi-square units, fit data) more than `bic_threshold` (and more than
    `STUCK_RELATIVE` of it) above the current model's: its fit stopped in a local minimum
    (or ran out of steps), and its dBIC is no evidence against the effect. Else ''. The limit: `limit` (a continuous
    candidate: its parameters at their neutral values), else the structural change's
    (`catalogue.NESTED_LIMIT`: an elastic joint stiff enough is the rigid one)."""
    limit = limit if limit is not None else cat.NESTED_LIMIT.get(c.name)
    if limit is None or not cost > cost_current + max(bic_threshold, STUCK_RELATIVE * cost_current):
        return ""
    return (
        f"{c.label}: its fit ended above the model it extends (cost {cost:.1f} against "
        f"{cost_current:.1f}), which it holds as a limit ({limit}): a local minimum, not "
        "evidence against the effect"
    )


#: `_baseline_notes`: a 95 % half-width above this fraction of the value marks a baseline
#: parameter as poorly determined
POORLY_DETERMINED = 0.5


#: `Diagnosis.notes` of a closed-loop search: its fits run in the model's loop
CLOSED_LOOP_NOTE = (
    "closed-loop logs: every fit here runs the model's loop, whose intervals can be too narrow where the rig's "
    "controller fed back its own rounding and noise (on the servo example 56 % of 95 % intervals held); for the "
    "named model's values and intervals, add the cause to the experiment file and run identify fit, which refits "
    "by the direct method (the logged command replayed: 98 % held there)"
)


def _baseline_notes(names, std_errors, values=None) -> list:
    """`Diagnosis.notes` of the baseline fit (round 0): the parameters its fit logs do not
    determine (no interval: `identify.covariance`; their degeneracy is every candidate's,
    whose fit then wanders along it), and those they determine poorly (a 95 % half-width,
    1.96 SE, above `POORLY_DETERMINED` of the value: the logs carry little information
    (short, small motions, much noise), and an effect of similar size may go unnoticed:
    naming no cause then does not say there is none)."""
    notes = []
    undetermined = [n for n, se in zip(names, std_errors) if not np.isfinite(se)]
    if undetermined:
        text = (
            f"the fit logs do not determine the baseline's {', '.join(undetermined)} (they see only a "
            "combination of them; see the fit's identifiability warning): fix one parameter of each combination, "
            "or the candidates' fits inherit the degeneracy"
        )
        notes.append({"round": 0, "text": text})
    if values is not None:
        poor = [
            f"{n} +-{100 * 1.96 * se / abs(v):.0f} %"
            for n, v, se in zip(names, values, std_errors)
            if np.isfinite(se) and 1.96 * se > POORLY_DETERMINED * abs(v)
        ]
        if poor:
            notes.append(
                {
                    "round": 0,
                    "text": f"the fit logs determine the baseline's {', '.join(poor)} only (95 %): unless such a "
                    "value is negligible in the model, they carry little information (short logs, small "
                    "motions or much noise), and a missing effect of comparable size can go undetected; longer "
                    "or richer logs give the search more power",
                }
            )
    return notes


def _fits_but_does_not_predict(scores, bic_threshold: float, min_gain: float, offsets_fitted) -> str:
    """A note when the round's best fit (lowest dBIC, below `-bic_threshold`) predicts the
    held-out logs worse than the model it extends, by as much as acceptance asks it to
    predict them better (held-out gain below `1 / min_gain`): it absorbs something
    particular to the fit logs. A sensor calibration candidate on a channel without per-log
    offsets is the usual case (an encoder offset that differs between logs). Else ''."""
    fitted = [s for s in scores if not s.screened and np.isfinite(s.held_out_gain)]
    if not fitted:
        return ""
    s = min(fitted, key=lambda x: x.delta_bic)
    if not (s.delta_bic < -bic_threshold and s.held_out_gain < 1.0 / min_gain):
        return ""
    text = (
        f"{s.label} fits the fit logs better (dBIC {s.delta_bic:.1f}) but predicts the held-out logs worse "
        f"({s.held_out_gain:.3f}x), so it is not named: what it fits does not carry over to other logs "
        "(something particular to the fit logs, or a small error of the model that it makes up for there)"
    )
    for label in s.members or (s.label,):
        name, _, channel = label.partition(":")
        if name == "sensor_gain_offset" and channel not in offsets_fitted:
            text += (
                f"; an offset of {channel} that differs between logs is one such thing: give each log its own "
                f'(offsets = ["{channel}"] in its [[logs]] entry)'
            )
    return text


def _convergence_notes(result: str, at_bounds) -> list:
    """`Diagnosis.notes` of a baseline fit that did not converge (`result`: its last
    stage's solver result, "successful", "max_steps_reached" or "failed") or ended with
    parameters `at_bounds`. A fit stopped short of its optimum makes every candidate look
    better than it is: part of each candidate's cost drop is the baseline's own fit
    finishing. A parameter on its bound is often the missing effect's symptom (a damping pushed to zero by the
    friction the model lacks), so it is said, not refused."""
    notes = []
    if result != "successful":
        notes.append(
            {
                "round": 0,
                "text": f"the baseline fit did not converge (its solver ended: {result}): every candidate is "
                "scored against a model short of its optimum, so part of its dBIC and held-out gain may be the "
                "baseline's fit finishing; check it with `identify fit` on the same logs, give it more steps "
                "(`diagnose_logs(fit_options={'max_steps': ...})`) or better guesses (`[[starts]]`), and run again",
            }
        )
    if at_bounds:
        notes.append(
            {
                "round": 0,
                "text": f"the baseline's {', '.join(at_bounds)} ended on a bound: the bound, not the data, set "
                "its value; often the symptom of the effect the model lacks (see the named causes and the "
                "extended model's values), otherwise a bound too narrow",
            }
        )
    return notes


def note_text(note: dict) -> str:
    """A `Diagnosis.notes` entry as printed: where it arose (round 0: the baseline) and what it says."""
    where = "baseline" if note["round"] == 0 else f"round {note['round']}"
    return f"{where}: {note['text']}"
