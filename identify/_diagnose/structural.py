"""Structural candidates (a missing mode, joint elasticity): each its own model, fitted and scored,
and the structural part of a search's round."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import jax.numpy as jnp
import numpy as np
from scipy import stats

import flexdyn as fd
from flexdyn._checks import error_reason

from .._data import measurement as meas
from .._fit.fit import fit
from .._fit.result import FitResult
from .._fit.steps import SimulationFailed
from .._fit.stiff_start import TooStiff
from .._model.parameters import Parameter
from .._model.problem import make_problem
from . import catalogue as cat
from .held_out import _held_out_batch, _held_out_start, _no_headroom, _Own, _own_starts, _with_extra_state
from .joint_model import _used
from .notes import _after_continuous_at_noise, _stuck_above_nested
from .scores import Score, _promising, _rms_per_channel, _with_headroom, gain_standard_error
from .state import CandidateFits, CurrentModel, SearchState, StackOn, StructuralModel


@dataclasses.dataclass(frozen=True)
class _StructuralFits:
    """What every structural candidate's fit shares in one diagnosis: the baseline
    (`base`, its free `parameters`), the superset measurement model (`measurement`), the
    fit and held-out logs, the channels and their noise `sigma`, the `N` residuals the
    information criterion counts, and the acceptance thresholds (the plausible values
    among them, `plausibility`)."""

    base: object  # the baseline's `FitResult`
    parameters: list
    measurement: meas.Measurement
    controller: object  # the logs' `identify.Controller` (None: open loop)
    fit_logs: list
    held_out_logs: list
    channels: tuple
    sigma: np.ndarray
    N: int
    rtol: float
    bic_threshold: float
    min_gain: float
    max_frequency_hz: float
    nyquist_hz: float
    say: Callable[[str], None]
    plausibility: cat.Plausibility

    def score(self, c, current: CurrentModel, rms_cur: float):
        return _structural_score(self, c, current, rms_cur)


class _FailedTowardRigid(str):
    """A structural candidate's failure reason (a `str`) whose fit drifted to the model
    the candidate extends; `.evidence`: what that says, for the note."""

    def __new__(cls, reason: str, evidence: str):
        out = super().__new__(cls, reason)
        out.evidence = evidence
        return out


def _rigid_limit(c, error, nyquist_hz: float) -> str | None:
    """For a `joint_elasticity` fit that failed because its simulation needed more steps
    than allowed (`identify.fit.SimulationFailed`): when the joint mode at the values where
    it failed is far above the logs' Nyquist frequency, the evidence that the fit was
    making the joint rigid (None otherwise; `_rigid_limit_at`). A fit refused at its start
    (`TooStiff`) made nothing rigid: None."""
    if c.name != "joint_elasticity" or not isinstance(error, SimulationFailed) or isinstance(error, TooStiff):
        return None
    if not any("limit of" in why for why in error.logs.values()):
        return None
    return _rigid_limit_at(c, error.values, nyquist_hz, "where its simulation ran out of steps")


def _rigid_limit_at(c, values: dict, nyquist_hz: float, where: str) -> str | None:
    """The evidence that a `joint_elasticity` fit was making the joint rigid, from the
    `values` (name -> SI) it reached (`where`: what happened there), or None: when the
    joint mode there is far above the logs' Nyquist frequency. The joint mode is at least
    `sqrt(k / J_rotor) / (2 pi)` (the rotor on its spring against a locked link; a free
    link raises it: `omega^2 = k (1/J_rotor + 1/J_link)`). An elastic-joint fit to logs
    with another effect can drive the joint mode kHz above Nyquist until its adaptive
    solve runs out of steps: that failure is evidence, not "no evidence either way"."""
    k = values.get(f"{c.where}.stiffness")
    rotor = values.get(f"{c.where}.rotor_inertia")
    if k is None or rotor is None or not (k > 0 and rotor > 0):
        return None
    f_joint = math.sqrt(k / rotor) / (2 * math.pi)
    if f_joint < 10 * nyquist_hz:
        return None
    return (
        f"the fit was making the joint rigid: {where}, the joint mode is at least "
        f"{f_joint:.3g} Hz ({c.where}.stiffness {k:.3g} N m/rad, rotor inertia {rotor:.3g} kg m^2), "
        f"{f_joint / nyquist_hz:.0f}x the logs' Nyquist frequency {nyquist_hz:.3g} Hz: evidence against an elastic "
        "joint the logs resolve"
    )


def _not_fitted(c, k: int, reason: str, say) -> Score:
    """The `Score` of structural candidate `c` (`k` new parameters) that the search could not
    fit (`Score.not_fitted`: `reason`): no cost, dBIC, p-value or held-out gain (NaN), never
    accepted, neither evidence against it nor a detection limit."""
    say(f"  structural candidate {c.label}: not fitted: {reason}")
    nan = float("nan")
    return Score(c.name, c.where, {}, nan, nan, nan, {}, nan, False, k, not_fitted=reason)


def _structural_score(setting: _StructuralFits, c, current: CurrentModel, rms_cur: float):
    """Fit a structural candidate as a model of its own (baseline parameters refitted from
    the baseline's values, accepted continuous effects kept at their fitted values), scored
    against the model `current` (held-out RMS `rms_cur`); one that passes both tests with
    implausible values (`catalogue.Plausibility`) is not accepted. Returns `(score, model)` (a
    `state.StructuralModel`); when the fit failed, the reason (a string, for
    `Diagnosis.notes`); when the model is too stiff for the solver at its start, or the fit
    stopped in a stiff region short of the whole logs (`fit`'s `stop_when_stiff`), a
    `Score` that is not fitted (`_not_fitted`; a fit that stopped while making the joint
    rigid is evidence, a failure reason as above: `_rigid_limit_at`)."""
    base, parameters, sup_meas = setting.base, setting.parameters, setting.measurement
    channels, sigma, N, rtol, say = setting.channels, setting.sigma, setting.N, setting.rtol, setting.say
    fit_logs, held_out_logs = setting.fit_logs, setting.held_out_logs
    bic_threshold, min_gain, max_f = setting.bic_threshold, setting.min_gain, setting.max_frequency_hz
    values = {n: val for n, val, _ in current.layout}
    base_chain = base.chain
    struct_chain, new = cat.structural_model(base_chain, c, max_frequency_hz=max_f, nyquist_hz=setting.nyquist_hz)
    m = sup_meas
    if values:
        chain_vals, meas_vals = meas.split_values(values)
        struct_chain, _ = cat.superset(struct_chain, meas.Measurement(), channels, [])
        struct_chain = fd.with_parameters(struct_chain, chain_vals)
        m = meas.with_parameters(sup_meas, meas_vals)
    params = [
        dataclasses.replace(p, guess=float(np.clip(_value_of(base, p.name), p.lower or -np.inf, p.upper or np.inf)))
        for p in parameters
    ]
    params += [Parameter(n, g) for n, g in new.items()]
    noise = dict(zip(channels, sigma))
    say(f"  structural candidate {c.label}: fitting its own model ...")
    try:
        problem = make_problem(
            struct_chain,
            params,
            _with_extra_state(fit_logs, struct_chain),
            noise,
            measurement=m,
            controller=setting.controller,
            rtol=rtol,
            atol=1e-2 * rtol,
        )
        res = fit(
            problem,
            params,
            horizons=None,
            n_stages=2,
            n_starts=8 if new else 1,
            first_damping=0.0,  # without new parameters, a warm start from the baseline's values
            start_spread=3.0,
            estimate_noise=False,
            frequency_init=False,
            restart_poor_fit=False,
            max_steps=60,
            grid_error=None,  # as the baseline's (`diagnose_logs`)
            # (a per-log parameter's guess is one value for all logs: start them at their own too)
            extra_starts=_own_starts(base),
            # a start too stiff for the solver is refused at once, and a fit that walks into
            # a stiff model stops there (minutes each otherwise, before the step limit)
            stop_when_stiff=True,
        )
        if res.stopped:
            rigid = _rigid_limit_at(c, res.value, setting.nyquist_hz, "where its fit stopped")
            if rigid is not None:
                say(f"  structural candidate {c.label}: its fit {res.stopped}")
                return _FailedTowardRigid(f"its fit {res.stopped}", rigid)
            return _not_fitted(c, len(new), f"its fit {res.stopped}", say)
        fitted = fd.with_parameters(struct_chain, res.shared_value)
        # the held-out logs' own values of the per-log parameters are their only free ones
        own = [
            dataclasses.replace(p, guess=_value_of(res, p.name), per_log=True)
            for p in params
            if getattr(p, "per_log", False)
        ]
        ho_problem = make_problem(
            fitted,
            own,
            _with_extra_state(held_out_logs, struct_chain),
            noise,
            measurement=m,
            controller=setting.controller,
            rtol=rtol,
            atol=1e-2 * rtol,
        )
        ho_own = _Own.of(ho_problem)
        v0 = _held_out_start(ho_problem, ho_own, res)
        thetas = jnp.zeros((1, len(ho_problem.names)))  # (every entry is an own value)
        r_ho, _, _ = _held_out_batch(ho_problem, thetas, v0, ho_own, jnp.asarray(sigma), res.step, 25)
    except TooStiff as e:
        return _not_fitted(c, len(new), f"{e.where} its model is {e.estimate.reason()}", say)
    except (RuntimeError, ValueError) as e:
        reason = error_reason(e)
        say(f"  structural candidate {c.label} failed: {reason}")
        rigid = _rigid_limit(c, e, setting.nyquist_hz)
        return reason if rigid is None else _FailedTowardRigid(reason, rigid)
    k = len(new)
    k_eff = max(k, 1)
    dbic = N * math.log(max(res.cost, 1e-300) / current.cost) + k * math.log(N)
    dof = max(N - len(problem.names) - len(problem.y0_free) - len(problem.offset_free), 1)
    F = ((current.cost - res.cost) / k_eff) / (res.cost / dof)
    p_value = float(stats.f.sf(F, k_eff, dof))
    used = _used(ho_problem)
    r_ho = np.asarray(r_ho[0])
    rms_ch = _rms_per_channel(ho_problem, r_ho, np.asarray(sigma))
    rms_c = float(np.sqrt(np.mean(r_ho[used] ** 2)))
    gain = rms_cur / rms_c if rms_c > 0 else np.inf
    vals = {n: float(v) for n, v in res.value.items() if n in new}
    passes = bool(dbic < -bic_threshold and gain >= min_gain)
    implausible = setting.plausibility.judge(c, vals) if passes else []
    # the new parameters' intervals from the structural model's own fit (exact Jacobian)
    intervals = {
        n: {"std_error": float(res.std_errors[i]), "ci95": [float(res.ci_low[i]), float(res.ci_high[i])]}
        for i, n in enumerate(res.names)
        if n in new
    }
    score = Score(
        c.name,
        c.where,
        vals,
        float(res.cost),
        float(dbic),
        p_value,
        rms_ch,
        float(gain),
        passes and not implausible,
        k,
        intervals=intervals,
        held_out_gain_se=gain_standard_error(np.asarray(current.ho), r_ho[used]),
        implausible=implausible,
    )
    fitted_params = [dataclasses.replace(p, guess=_value_of(res, p.name)) for p in params]
    model = StructuralModel(
        chain=fitted,
        measurement=m,
        parameters=fitted_params,
        fit=res,
        held_out_cost=float(np.sum(r_ho[used] ** 2)),
        held_out_problem=ho_problem,
        held_out_residual=r_ho[used],
    )
    return score, model


def _value_of(result: FitResult, name: str) -> float:
    """A free parameter's fitted value; for a per-log one (`Parameter.per_log`), the median
    of the logs' values (a start for a refit)."""
    if name in result.per_log:
        return float(np.median(list(result.per_log[name].values())))
    return float(result.value[name])


def _first_round_structural(setting: _StructuralFits, labels: set, scores: list, state: SearchState, held_problem):
    """The structural candidates to fit in round 1: all of them, unless the baseline's
    held-out residual is at its noise floor (`_with_headroom`) and the fit logs show no
    significant systematic residual either (no continuous candidate of the round, fitted or
    screened, below `-bic_threshold`). Held-out logs at the noise cannot confirm a gain, but
    a significant fit-log residual is still an effect to explain: skipping the structural
    fits then reported an elastic joint as "nothing explains the residual"."""
    significant = [s for s in scores if s.delta_bic < -setting.bic_threshold]
    if not significant or not labels:
        return _with_headroom(labels, held_problem, state.current.ho, setting.min_gain, 1, state.notes, setting.say)
    full, why = _no_headroom(held_problem, state.current.ho, setting.min_gain)
    if full:
        best = min(significant, key=lambda s: s.delta_bic)
        text = (
            f"{', '.join(sorted(labels))} fitted although the baseline is at the noise on the held-out logs ({why}): "
            f"the fit logs show a significant systematic residual ({best.label}: dBIC {best.delta_bic:.1f}); held-out "
            "gains cannot confirm a candidate there"
        )
        setting.say(f"  round 1: {text}")
        state.notes.append({"round": 1, "text": text})
    return labels


def fit_structural_round(
    setting: _StructuralFits, state: SearchState, cands, scores: list, fits: CandidateFits | None, held_problem
) -> None:
    """The structural candidates of round `state.round`, fitted and scored against the
    current model, their scores appended to `scores` (the round's continuous ones; `fits`
    their fits, `held_problem` the held-out problem). In round 1 all of them, unless the
    baseline is at the noise; later only those that improved significantly on the model of
    the previous round (`state.struct_promising`); none once an accepted continuous
    candidate of the round reaches the noise. Each is a model of its own to compile and fit."""
    rnd, done, notes, say = state.round, state.done, state.notes, setting.say
    if rnd == 0:
        state.struct_promising = _first_round_structural(
            setting, {x.label for x in cands if x.structural and x.label not in done}, scores, state, held_problem
        )
    # an accepted continuous candidate at the noise leaves a structural one at best a tie
    pending = {x.label for x in cands if x.structural and x.label not in done} & state.struct_promising
    if pending and fits is not None:
        state.struct_promising = _after_continuous_at_noise(
            pending, scores, {"labels": fits.labels, "ho": fits.ho}, held_problem, setting.min_gain, rnd + 1, notes, say
        )
    rms_cur = float(np.sqrt(np.mean(state.current.ho**2)))
    for c in [x for x in cands if x.structural and x.label not in done and x.label in state.struct_promising]:
        s = setting.score(c, state.current, rms_cur)
        if isinstance(s, Score):  # not fitted (a model too stiff for the solver): no evidence either way
            text = f"{c.label}: not fitted: {s.not_fitted}; it has no detection limit"
            notes.append({"round": rnd + 1, "text": text})
            scores.append(s)
        elif isinstance(s, str):  # its fit failed: said, not dropped in silence
            evidence = getattr(s, "evidence", "no evidence either way")
            text = f"{c.label}: its fit failed ({s}); not scored; {evidence}"
            say(f"  round {rnd + 1}: {text}")
            notes.append({"round": rnd + 1, "text": text})
        else:
            scores.append(s[0])
            state.struct_models[c.label] = s[1]
            stuck = _stuck_above_nested(c, s[0].cost, state.current.cost, setting.bic_threshold)
            if stuck:
                say(f"  round {rnd + 1}: {stuck}")
                notes.append({"round": rnd + 1, "text": stuck})


def record_drops(state: SearchState, scores, cands) -> None:
    """`state.struct_drop`: the cost each structural candidate of the round took off its
    model. The next round refits one only if that drop would pass the BIC test there
    (`_promising`): on the absolute drop, since a large effect masks a small one in a log-ratio."""
    state.struct_drop.update(
        {
            s.label: (state.current.cost - s.cost, s.k)
            for s in scores
            if not s.not_fitted and any(c.label == s.label and c.structural for c in cands)
        }
    )


def stack_on_structural(setting: _StructuralFits, state: SearchState, winner: Score, candidate) -> None:
    """An accepted structural `candidate` changes the model's coordinates, which the joint
    model cannot hold: the search goes on from its model as a new baseline
    (`state.stack_on`), with the structural candidates worth fitting again there."""
    model = state.struct_models[candidate.label]
    again = _promising(state.struct_drop, winner.cost, setting.N, setting.bic_threshold) - {candidate.label}
    if candidate.name in cat.REPEATABLE:
        again |= {candidate.label}
    again = _with_headroom(
        again,
        model.held_out_problem,
        model.held_out_residual,
        setting.min_gain,
        state.round + 2,
        state.notes,
        setting.say,
    )
    state.stack_on = StackOn(model, state.round + 1, again)


def promising_next(setting: _StructuralFits, state: SearchState, held_problem) -> None:
    """`state.struct_promising` for the next round, after a continuous candidate was accepted."""
    promising = _promising(state.struct_drop, state.current.cost, setting.N, setting.bic_threshold)
    state.struct_promising = _with_headroom(
        promising, held_problem, state.current.ho, setting.min_gain, state.round + 2, state.notes, setting.say
    )
