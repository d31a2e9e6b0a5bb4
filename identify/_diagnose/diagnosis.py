"""`Diagnosis`: what `diagnose_logs` returns, with its summary and JSON form; its assembly at the
search's end (the extended model's intervals, the causes), and two stacked searches reported as one.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

import flexdyn as fd

from .._data import channels as ch, measurement as meas, noise_floor as nf
from .._data.units import display_unit
from .._fit import covariance, hac
from .._fit.result import FitResult
from .._model.parameters import Z95, names_at_bounds, x_from_z
from .._model.problem import Problem, parameter_unit
from .._model.residuals import (
    initial_states_of,
    sensor_offsets,
)
from . import catalogue as cat, evidence as ev
from .held_out import HeldOutSet, _floor_per_channel, _held_out_summary, held_out_headroom, limits_at_end
from .joint_model import Superset, _bounds, _jacobian, _pad_used, _predict
from .notes import note_text
from .scores import Cause, _limit_text, _rms_per_channel, not_fitted_of, round_verdicts
from .state import CurrentModel, SearchOptions, SearchState
from .verdict import Excitation, Verdict, verdict_of

#: what `Diagnosis.detection_limits` are, as the summary and the report say it
DETECTION_LIMITS_MEANING = (
    "the smallest effect of each candidate not named that these logs would have let the search name, "
    "linearised at the final model (`identify.diagnose.detection_limits`; on simulated pendulum logs, dry "
    "friction at its limit was named in 7 of 12 trials, at 1.5x in 12 of 12, at 0.67x in none)"
)


@dataclasses.dataclass
class Diagnosis:
    """What `diagnose` found (see `summary()` and `to_dict()`)."""

    split: str
    baseline: FitResult
    evidence: dict
    rounds: list  # per round: list of Score (sorted by dBIC)
    causes: list  # Cause, in the order accepted
    held_out: dict  # {'baseline': {ch: rms}, 'extended': {ch: rms}, 'gain': {ch: ratio}, 'gain_total': ...}
    delta_bic_total: float
    fraction_explained: float
    # None when the baseline's held-out residual is not above the noise level (e.g. noise
    # "estimate"d from the baseline's own residual): there is no excess to explain
    fraction_of_excess_explained: float | None
    extended_chain: fd.Chain
    extended_measurement: meas.Measurement
    extended_parameters: dict
    outputs: dict  # per held-out and fit log: t, measured, baseline, extended
    modal_frequencies_hz: list
    wall_time: float
    # every parameter of the extended model (baseline and extensions): name -> {value,
    # std_error, ci95}, from the exact Jacobian of its final fit
    extended_intervals: dict = dataclasses.field(default_factory=dict)
    # weighted costs (sums of squared residuals over the noise) of the baseline and the
    # extended model on the fit and held-out data; N (`n_fit`, `n_held_out`) and the
    # number of added parameters `k`: what the totals are computed from
    costs: dict = dataclasses.field(default_factory=dict)
    # what the baseline model assumes that the logs may break (`evidence.stiffening_checks`:
    # a flexible link spinning or hanging enough to need geometric stiffening)
    model_checks: list = dataclasses.field(default_factory=list)
    # what the search decided not to try, and why: `{'round': n, 'text': ...}` (candidates
    # not refitted in round n, counted over the whole search)
    notes: list = dataclasses.field(default_factory=list)
    # the catalogue entries not tried at all, and why: name -> reason (an entry that does
    # not apply to the rig or the logs, one the caller excluded, one already in the model);
    # and label (`sensor_highpass:theta1`) -> reason for a sensor entry, or a part of one,
    # that the channel's declared sensor kind cannot have (`catalogue.kind_left_out`)
    not_tried: dict = dataclasses.field(default_factory=dict)
    # the smallest effect of each continuous candidate not named that these logs would have
    # let the search name (BIC test and held-out gain), linearised at the final model
    # (`detection_limits`): label -> {parameter: {"value", "criterion", "unit", "neutral"}},
    # "value" the offset from the neutral value (inf: not seen to first order)
    detection_limits: dict = dataclasses.field(default_factory=dict)
    # the held-out gain a cause had to reach (`diagnose_logs`' `min_gain`)
    min_gain: float = 1.1
    # the per-log parameters (`Parameter.per_log`) of the extended model: name -> {log:
    # value (SI)}, the fit logs' fitted with it (also in `extended_parameters` as
    # `name[log]`, with intervals), the held-out logs' refitted there like their initial
    # states (what the held-out scores were computed at)
    per_log: dict = dataclasses.field(default_factory=dict)
    # which logs of `per_log` are held out
    held_out_logs: tuple = ()
    # where an interrupted search stopped (`diagnose_logs`: Ctrl-C during its rounds); None
    # when it finished. The causes are then those accepted before it.
    interrupted: str | None = None
    # named, none or inconclusive, with the competing candidates and what would decide
    # (`verdict.verdict_of`)
    verdict: Verdict | None = None

    def marginal_text(self, c) -> str:
        """What a cause's marginal held-out gain (`Cause.marginal`) means."""
        return (
            f"its held-out gain {c.held_out_gain:.4f}x is within two standard errors ({c.held_out_gain_se:.2g} "
            f"each) of the {self.min_gain:g}x bar it passed: as likely a chance pass as an effect; confirm it on "
            "more held-out data (or a noisy input column may be what it fits)"
        )

    @property
    def named(self) -> list[str]:
        return [c.name for c in self.causes]

    @property
    def not_fitted(self) -> dict:
        """The catalogue candidates the search could not test: those whose fit never left
        its start in the last round that tried them (`Score.not_fitted`), label ->
        `"round n: why"`. Neither evidence against them nor a detection limit."""
        return not_fitted_of(self.rounds)

    def not_fitted_lines(self) -> list[str]:
        """A line per candidate of `not_fitted`."""
        return [f"{lab}: not fitted ({why}): no detection limit" for lab, why in self.not_fitted.items()]

    @property
    def implausible(self) -> list[str]:
        """The labels of the candidates that passed both tests in some round but were not
        named because their fitted values are implausible (`Score.implausible`), in order."""
        out = []
        for scores in self.rounds:
            out += [s.label for s in scores if s.implausible and s.label not in out]
        return out

    @property
    def unexplained_hint(self) -> str:
        """What the line of a channel `left_unexplained` adds about the candidates not
        fitted (the search did not rule them out), or ''."""
        if not self.not_fitted:
            return ""
        labels = ", ".join(self.not_fitted)
        return f"; not ruled out: {labels}, which the search could not fit (the detection limits say why)"

    @property
    def left_unexplained(self) -> list[str]:
        """The channels whose held-out residual under the extended model is above
        `identify.noise_floor.POOR_FIT` times the held-out data's model-free noise floor."""
        floor = self.held_out.get("noise_floor", {})
        return [c for c, rms in self.held_out["extended"].items() if c in floor and rms > nf.POOR_FIT * floor[c]]

    @property
    def excess_explained_text(self) -> str:
        """`fraction_of_excess_explained` as text ("n/a ..." when there is no excess)."""
        if self.fraction_of_excess_explained is None:
            return "n/a, the baseline's held-out residual is not above the noise level"
        return f"{self.fraction_of_excess_explained:.3f}"

    @property
    def baseline_converged(self) -> bool:
        """Whether the baseline fit's solver converged (a parameter on its bound does not
        count against it here: in a diagnosis that is often the missing effect's symptom,
        and `notes` says so). `identify diagnose` exits 3 when it did not."""
        return self.baseline.stages[-1].outcome == "successful"

    @property
    def extended_at_bounds(self) -> list[str]:
        """The baseline's parameters whose value in the extended model lies on one of
        their bounds (judged as `FitResult.at_bounds` is): a named cause may have taken
        over what such a parameter stood for in the baseline."""
        if not self.causes:
            return []
        problem = self.baseline.problem
        xs = []
        for name, log, value in zip(problem.names, problem.log_scale, self.baseline.values):
            v = float(self.extended_parameters.get(name, value))
            xs.append(math.log(v) if log and v > 0 else (-math.inf if log else v))
        return names_at_bounds(problem, np.asarray(xs))

    def at_bound_lines(self) -> list[str]:
        """A sentence per parameter of `extended_at_bounds`."""
        return [
            f"{n} = {float(self.extended_parameters[n]):.5g} ended on a bound in the extended model: what it stood for "
            "in the baseline may now be carried by the named cause(s) (its interval is then meaningless), or its "
            "bound is too narrow (widen it if that is physical)"
            for n in self.extended_at_bounds
        ]

    def detection_limit_lines(self) -> list[str]:
        """One line per candidate not named: the smallest effect that would have been
        named, per parameter, and the criterion that sets it."""
        out = []
        for lab, per in self.detection_limits.items():
            parts = [
                f"{n} {_limit_text(p)} ({p['criterion']})"
                if math.isfinite(p["value"])
                else f"{n}: not seen apart from the model's own parameters (to first order)"
                for n, p in per.items()
            ]
            out.append(f"{lab}: {'; '.join(parts)}")
        return out

    def summary(self) -> str:
        lines = [f"held-out data: {self.split}", ""]
        if self.interrupted:
            lines[:0] = [f"INTERRUPTED: {self.interrupted}: what follows is what was accepted before it", ""]
        if self.verdict is not None:
            lines += self.verdict.lines() + [""]
        if self.causes:
            lines.append("accepted causes:")
            for c in self.causes:
                lines.append(
                    f"  {c.name} at {c.where} ({c.description}): dBIC {c.delta_bic:.1f}, "
                    f"held-out gain {c.held_out_gain:.2f}x"
                    + (f" (SE {c.held_out_gain_se:.2g})" if np.isfinite(c.held_out_gain_se) else "")
                    + (f" (together with {', '.join(c.together_with)}: the pair's scores)" if c.together_with else "")
                )
                for n, p in c.parameters.items():
                    lines.append(
                        f"    {n} = {p['value']:.{covariance.digits(p['value'], p['std_error'])}g}"
                        + (f" {p['unit']}" if p["unit"] and p["unit"] != "1" else "")  # (a gain's "1" read as a typo)
                        + f" (SE {p['std_error']:.2g}, 95 % CI {covariance.interval_text(*p['ci95'])}"
                        + (f"; {p['method']})" if p.get("method", "white") != "white" else ")")
                    )
                for w in c.warnings:
                    lines.append(f"    IMPLAUSIBLE: {w}")
                if c.marginal(self.min_gain):
                    lines.append(f"    MARGINAL: {self.marginal_text(c)}")
        elif self.verdict is not None and self.verdict.kind == "inconclusive":
            lines.append("no cause named: inconclusive (the verdict above)")
        else:
            lines.append("no catalogue entry explains the residual significantly (see the evidence and the scores)")
        if self.implausible:
            lines.append(
                f"not named, passing only with implausible values: {', '.join(self.implausible)} (see the scores and "
                "the notes): probably standing in for an effect the catalogue lacks"
            )
        for line in self.at_bound_lines():
            lines.append(f"on a bound: {line}")
        for check in self.model_checks:
            if check["flagged"]:
                lines.append(f"model check: {check['message']}")
        lines.append("")
        floor = self.held_out.get("noise_floor", {})
        lines.append(
            "held-out RMS per channel (baseline -> extended, gain; the data's model-free noise floor, "
            "identify.noise_floor):"
        )
        for c in self.held_out["baseline"]:
            k, unit = display_unit(c)
            lines.append(
                f"  {c} ({unit}): {k * self.held_out['baseline'][c]:.4g} -> {k * self.held_out['extended'][c]:.4g} "
                f"({self.held_out['gain'][c]:.2f}x)" + (f"; floor {k * floor[c]:.4g}" if c in floor else "")
            )
        for c in self.left_unexplained:
            ratio = self.held_out["extended"][c] / floor[c]
            lines.append(
                f"  {c}: the {'extended' if self.causes else 'baseline'} model's held-out residual is still "
                f"{ratio:.3g} times the noise floor: an effect is left unexplained (or the noise is not white, "
                "or the logged input is noisy: noise on a torque column drives the model, not the rig)"
                + self.unexplained_hint
            )
        for name, by_log in self.per_log.items():
            unit = _unit(self.baseline.problem, name)
            unit = f" ({unit})" if unit and unit != "1" else ""
            fitted = ", ".join(f"{log} {v:.5g}" for log, v in by_log.items() if log not in self.held_out_logs)
            held = ", ".join(f"{log} {v:.5g}" for log, v in by_log.items() if log in self.held_out_logs)
            lines.append(
                f"per log: {name}{unit}: {fitted} (fitted)" + (f"; {held} (held out, refitted there)" if held else "")
            )
        lines.append(
            f"total dBIC {self.delta_bic_total:.1f}; fraction of the held-out residual explained "
            f"{self.fraction_explained:.3f} (of its excess over the noise: {self.excess_explained_text})"
        )
        lines.extend(f"note: {note_text(n)}" for n in self.notes)
        if self.not_tried:
            lines.append("not tried:")
            lines.extend(f"  {n}: {why}" for n, why in self.not_tried.items())
        if self.detection_limits or self.not_fitted:
            lines.append(f"detection limits ({DETECTION_LIMITS_MEANING}):")
            lines.extend(f"  {text}" for text in self.detection_limit_lines() + self.not_fitted_lines())
        for r, scores in enumerate(self.rounds, start=1):
            lines.append("")
            lines.append(f"round {r}: candidates (best first)")
            w = max([34] + [len(s.label) for s in scores])  # a pair's label is long
            lines.append(f"  {'candidate':<{w}} {'dBIC':>10} {'p-value':>9} {'held-out gain':>14}  accepted")
            verdict = round_verdicts(scores)
            for s in scores:
                if s.screened:
                    lines.append(f"  {s.label:<{w}} {s.delta_bic:>10.1f}   (predicted; not fitted: {s.screen_reason})")
                    continue
                if s.not_fitted:
                    lines.append(f"  {s.label:<{w}} {'--':>10}   {verdict[s.label]}")
                    continue
                lines.append(
                    f"  {s.label:<{w}} {s.delta_bic:>10.1f} {s.p_value:>9.2g} {s.held_out_gain:>13.3f}x  "
                    f"{verdict[s.label]}"
                )
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {
            "split": self.split,
            "interrupted": self.interrupted,
            "verdict": None if self.verdict is None else self.verdict.to_dict(),
            "baseline": self.baseline.to_dict(),
            "evidence": self.evidence,
            "rounds": [[dataclasses.asdict(s) for s in scores] for scores in self.rounds],
            "causes": [dataclasses.asdict(c) for c in self.causes],
            "named": self.named,
            "held_out": self.held_out,
            "delta_bic_total": self.delta_bic_total,
            "fraction_explained": self.fraction_explained,
            "fraction_of_excess_explained": self.fraction_of_excess_explained,
            "extended_parameters": self.extended_parameters,
            "extended_intervals": self.extended_intervals,
            "baseline_converged": self.baseline_converged,
            "extended_at_bounds": self.extended_at_bounds,
            "costs": self.costs,
            "model_checks": self.model_checks,
            "notes": self.notes,
            "not_tried": self.not_tried,
            "detection_limits": self.detection_limits,
            "not_fitted": self.not_fitted,
            "per_log": self.per_log,
            "held_out_logs": list(self.held_out_logs),
            "modal_frequencies_hz": self.modal_frequencies_hz,
            "wall_time_s": self.wall_time,
        }


def _with_totals(diag: Diagnosis, wall_time: float) -> Diagnosis:
    """`diag` with the totals computed from its `costs`: dBIC of the extended model against
    the baseline (`N ln(RSS_ext / RSS_0) + k ln N`), the fraction of the held-out residual
    explained, and of its excess over the noise (expected cost `N_held_out`)."""
    c = diag.costs
    n, k = c["n_fit"], c["k"]
    fit0, fit1 = c["fit"]["baseline"], c["fit"]["extended"]
    ho0, ho1 = c["held_out"]["baseline"], c["held_out"]["extended"]
    dbic = n * math.log(max(fit1, 1e-300) / fit0) + k * math.log(n) if diag.causes else 0.0
    excess = ho0 - c["n_held_out"]
    return dataclasses.replace(
        diag,
        delta_bic_total=float(dbic),
        fraction_explained=float(1.0 - ho1 / ho0) if ho0 > 0 else 0.0,
        fraction_of_excess_explained=float((ho0 - ho1) / excess) if excess > 0 else None,
        wall_time=wall_time,
    )


def _stacked(outer: Diagnosis, inner: Diagnosis) -> Diagnosis:
    """A search that ended on a structural change (`outer`) continued by the search from
    that structural model (`inner`, whose baseline is it, every accepted effect's
    parameters free). Rounds and causes are concatenated; the causes `outer` accepted
    report their parameters from the final extended model; the extended model, its costs
    and held-out RMS are `inner`'s, compared with `outer`'s baseline."""
    causes = [
        dataclasses.replace(
            c,
            parameters={
                n: {**inner.extended_intervals[n], "unit": p["unit"]} if n in inner.extended_intervals else p
                for n, p in c.parameters.items()
            },
        )
        for c in outer.causes
    ]
    outputs = {}
    for name, e in outer.outputs.items():
        ie = inner.outputs[name]
        outputs[name] = {**e, "extended": ie.get("extended", ie["baseline"])}
    costs = {
        **outer.costs,
        "fit": {"baseline": outer.costs["fit"]["baseline"], "extended": inner.costs["fit"]["extended"]},
        "held_out": {"baseline": outer.costs["held_out"]["baseline"], "extended": inner.costs["held_out"]["extended"]},
        "k": outer.costs["k"] + inner.costs["k"],
    }
    return dataclasses.replace(
        outer,
        rounds=outer.rounds + inner.rounds,
        causes=causes + inner.causes,
        # the inner search's rounds continue the outer's count
        # (the inner search's baseline notes are about the model after the outer rounds; one
        # the outer search already made is not repeated)
        notes=outer.notes
        + [
            {**n, "round": n["round"] + len(outer.rounds)}
            for n in inner.notes
            if not (n["round"] == 0 and any(o["text"] == n["text"] for o in outer.notes))
        ],
        # not tried by either search (the inner one may try what the outer could not)
        not_tried={n: why for n, why in outer.not_tried.items() if n in inner.not_tried},
        held_out=_held_out_summary(
            outer.held_out["baseline"],
            inner.held_out["extended"],
            costs["held_out"]["baseline"],
            costs["held_out"]["extended"],
            outer.held_out["noise_floor"],
        ),
        extended_chain=inner.extended_chain,
        extended_measurement=inner.extended_measurement,
        extended_parameters=inner.extended_parameters,
        extended_intervals=inner.extended_intervals,
        per_log=inner.per_log,
        outputs=outputs,
        costs=costs,
        detection_limits=inner.detection_limits,
    )


def _unit(problem: Problem, name: str) -> str:
    return parameter_unit(problem, name)


def _unit_chain(name: str) -> str:
    return {"stiffness": "N m/rad", "rotor_inertia": "kg m^2"}.get(name.rsplit(".", 1)[-1], "")


def _traces(superset: Superset, held: HeldOutSet, baseline: CurrentModel, current: CurrentModel, step) -> dict:
    """Measured, baseline and extended outputs (SI) on the fit and held-out logs, for plots."""
    out = {}
    variants = [("baseline", baseline)]
    if current.layout:
        variants.append(("extended", current))
    for role, problem in (("fit", superset.problem), ("held-out", held.problem)):
        for name, model in variants:
            theta = superset.theta_of(model.v, model.idx, model.logf)
            if role == "fit":
                y0s, off = initial_states_of(problem, model.v.y0), sensor_offsets(problem, model.v.offset)
            else:
                _, w = held.refit(theta[None], step)
                y0s, off = initial_states_of(problem, w.y0[0]), sensor_offsets(problem, w.offset[0])
                theta = w.theta[0]  # (the held-out problem's: its logs' own per-log values in)
            pred, _ = _predict(problem, theta, y0s, None, step)
            pred = np.asarray(pred + off[:, None, :])
            valid, present = np.asarray(problem.valid), np.asarray(problem.present)
            for l, log in enumerate(problem.log_names):
                k = valid[l]
                entry = out.setdefault(log, {"role": role, "t": np.asarray(problem.t[l])[k], "measured": {}})
                for j, c in enumerate(problem.channels):
                    if present[l, j]:
                        entry["measured"][c] = np.asarray(problem.measured[l, k, j])
                        entry.setdefault(name, {})[c] = pred[l, k, j]
    return out


def _extended_intervals(base: FitResult, superset: Superset, current: CurrentModel, step) -> tuple[dict, dict]:
    """`Diagnosis.extended_intervals`: every parameter of the extended model (baseline and
    extensions) with its standard error and 95 % interval, from the baseline fit or, with
    extensions accepted, the exact Jacobian of the joint model at `current` (log-scale ones
    through their logs); and the extensions' alone, with their units.

    With extensions, the interval is the white formula's `s^2 (J^T J)^-1` while the
    residual is white, and the HAC sandwich's (`identify._fit.hac`) when its lag-1
    autocorrelation is measurable (`method` says which): a quantised encoder on a hub that
    stiction holds still errs by one value over the whole still stretch, and the white
    intervals of a simulated servo rig's dry friction were then several times too narrow."""
    problem = base.problem
    ext_values = {}
    ext_intervals = {
        n: {
            "value": float(base.values[i]),
            "std_error": float(base.std_errors[i]),
            "ci95": [float(base.ci_low[i]), float(base.ci_high[i])],
        }
        for i, n in enumerate(base.names)
    }
    if not current.layout:
        return ext_intervals, ext_values
    v, joint = current.v, superset.joint
    xb = x_from_z(_bounds(joint), v.zb)
    r, J = _jacobian(
        joint,
        xb,
        v.xe,
        v.y0,
        v.offset,
        jnp.asarray(current.idx),
        jnp.asarray(current.logf),
        superset.sigma_j,
        step,
    )
    r, J, used = np.asarray(r), np.asarray(J), np.asarray(superset.used)
    # (an undetermined parameter gets an infinite error, as in the fit: `identify.covariance`)
    se_nat = covariance.dense((), (), r[used], J[used]).std_errors
    # a residual correlated along the logs (a count held while the hub is still, model
    # error) makes the white formula's intervals too narrow: the HAC sandwich instead
    L, n = np.asarray(superset.problem.t).shape
    robust = hac.hac(r, J, used, (L, n, len(superset.problem.channels)))
    method = (
        f"HAC (residual lag-1 autocorrelation {robust.lag1:.3g}; bandwidths {list(robust.bandwidths)} samples)"
        if robust.autocorrelated
        else "white"
    )
    if robust.autocorrelated:
        se_nat = robust.std_errors
    natural = [(n, float(xb[i]), float(se_nat[i]), problem.log_scale[i]) for i, n in enumerate(problem.names)]
    natural += [(n, float(v.xe[s]), float(se_nat[joint.nb + s]), lg) for s, (n, _, lg) in enumerate(current.layout)]
    for n, x, se, lg in natural:
        val = math.exp(x) if lg else x
        lo, hi = log_interval(x, se) if lg else (x - Z95 * se, x + Z95 * se)
        ext_intervals[n] = {"value": val, "std_error": val * se if lg else se, "ci95": [lo, hi], "method": method}
    for n, _, _ in current.layout:
        ext_values[n] = {**ext_intervals[n], "unit": _unit(superset.problem, n)}
    return ext_intervals, ext_values


def log_interval(x: float, se: float) -> tuple[float, float]:
    """The 95 % interval `exp(x -+ Z95 se)` of a parameter fitted through its logarithm
    `x` with standard error `se`: an upper end beyond the floats is `inf`, not an
    `OverflowError` (a parameter the data barely determine, e.g. an actuator lag near 0
    on held commands, has an `se` of thousands; its interval is then (0, inf), honestly)."""
    lo, hi = x - Z95 * se, x + Z95 * se
    return (math.exp(lo) if lo > -745.0 else 0.0), (math.exp(hi) if hi < 709.0 else math.inf)


def _causes(state: SearchState, ext_values: dict, plausibility: cat.Plausibility) -> list[Cause]:
    """A `Cause` per accepted entry, its parameters from `ext_values` (a continuous one) or
    its structural model's own fit (replaced by the stacked search's, `_stacked`), with the
    warnings of fitted values the component does not plausibly reach (`plausibility`): a
    cause accepted with plausible values can reach such values in the final joint refit."""
    causes = []
    for accepted in state.accepted:
        wc, sc = accepted.candidate, accepted.score
        if wc.structural:
            nan = {"std_error": float("nan"), "ci95": [float("nan")] * 2}
            params = {
                n: {"value": val, **sc.intervals.get(n, nan), "unit": _unit_chain(n)} for n, val in sc.params.items()
            }
        else:
            params = {n: ext_values[n] for n in wc.params}
        causes.append(
            Cause(
                wc.name,
                wc.where,
                cat.DESCRIPTION[wc.name],
                params,
                sc.delta_bic,
                sc.held_out_gain,
                held_out_gain_se=sc.held_out_gain_se,
                together_with=list(accepted.together_with),
                warnings=plausibility.judge(wc, {n: p["value"] for n, p in params.items()}),
            )
        )
    return causes


def _extended_model(base: FitResult, superset: Superset, current: CurrentModel, ext_values: dict) -> tuple:
    """The extended model's parameters (SI; a per-log one as `name[log]`), chain and measurement."""
    problem = base.problem
    extended_params = dict(base.value)
    if current.layout:
        theta_ext = np.asarray(superset.theta_of(current.v, current.idx, current.logf))
        extended_params = {n: float(theta_ext[i]) for i, n in enumerate(problem.names)}
        extended_params.update({n: d["value"] for n, d in ext_values.items()})
    # (a per-log parameter keeps the rig's value in the extended chain, as `FitResult.chain`)
    own_names = set(problem.names) - set(problem.shared_names)
    chain_vals, meas_vals = meas.split_values({n: v for n, v in extended_params.items() if n not in own_names})
    ext_chain = fd.with_parameters(superset.chain, chain_vals)
    ext_meas = meas.with_parameters(superset.measurement, meas_vals)
    return extended_params, ext_chain, ext_meas


def _per_log(problem: Problem, held_problem: Problem, extended_params: dict, theta_held) -> dict:
    """`Diagnosis.per_log`: each per-log parameter's value per log, the fit logs' from the
    extended model, the held-out logs' refitted there (`theta_held`: their parameter vector)."""
    per_log = {}
    theta_held = np.asarray(theta_held)
    for name, _ in problem.per_log:
        per_log[name] = {log: extended_params[f"{name}[{log}]"] for log in problem.log_names}
        (index_ho,) = [ix for n, ix in held_problem.per_log if n == name]
        per_log[name].update({log: float(theta_held[i]) for log, i in zip(held_problem.log_names, index_ho)})
    return per_log


def _baseline_evidence(superset: Superset, held: HeldOutSet, base: FitResult, traces: dict, modal) -> dict:
    """`Diagnosis.evidence`: what the baseline gets wrong, on the fit and the held-out logs."""
    outs = {
        name: {
            "t": e["t"],
            "measured": e["measured"],
            "simulated": e["baseline"],
            "residual": {c: e["baseline"][c] - e["measured"][c] for c in e["measured"]},
        }
        for name, e in traces.items()
    }
    torques = {}
    for problem in (superset.problem, held.problem):
        for l, name in enumerate(problem.log_names):
            tv = np.asarray(problem.torque_v[l])[: len(traces[name]["t"]), 0]
            if np.any(tv != 0):
                torques[name] = tv
    return ev.evidence(outs, base.sigma, modal, torques)


def assemble(
    *,
    split: str,
    options: SearchOptions,
    base: FitResult,
    superset: Superset,
    held: HeldOutSet,
    baseline: CurrentModel,
    state: SearchState,
    cands,
    modal: list,
    not_tried: dict,
) -> Diagnosis:
    """The `Diagnosis` of a search that ended at `state` (totals: `_with_totals`): the extended
    model and its intervals, the causes, the held-out RMS against the `baseline` model, the
    traces and the baseline's evidence, the per-log values and the detection limits (unless the
    search goes on from a structural model, `state.stack_on`, which reports them)."""
    current, step, problem = state.current, state.step, base.problem
    ext_intervals, ext_values = _extended_intervals(base, superset, current, step)
    causes = _causes(state, ext_values, options.plausibility)
    rms_base = _rms_per_channel(held.problem, _pad_used(baseline.ho, held.used), superset.sigma)
    rms_ext = _rms_per_channel(held.problem, _pad_used(current.ho, held.used), superset.sigma)
    ho_cost0, ho_cost1 = float(baseline.ho @ baseline.ho), float(current.ho @ current.ho)
    costs = {
        "fit": {"baseline": baseline.cost, "extended": float(current.cost)},
        "held_out": {"baseline": ho_cost0, "extended": ho_cost1},
        "n_fit": superset.N,
        "n_held_out": int(held.used.sum()),
        "k": int(sum(s.k for s in state.causes_scores)),
    }
    extended_params, ext_chain, ext_meas = _extended_model(base, superset, current, ext_values)
    traces = _traces(superset, held, baseline, current, step)
    # the held-out logs' unknowns at the final model (each log's own per-log values, the
    # detection limits' linearisation point): one held-out fit for both
    unknowns = None
    if problem.per_log or state.stack_on is None:
        _, unknowns = held.refit(superset.theta_of(current.v, current.idx, current.logf)[None], step)
    per_log = _per_log(problem, held.problem, extended_params, unknowns.theta[0]) if problem.per_log else {}
    evidence = _baseline_evidence(superset, held, base, traces, modal)
    model_checks = ev.stiffening_checks_of(base.chain, traces)
    limits = {}
    if state.stack_on is None:
        options.say("detection limits of the candidates not named ...")
        # (not for a candidate whose fit never left its start: the search did not test it)
        skip = state.done | set(not_fitted_of(state.rounds))
        candidates = [c for c in cands if not c.structural and c.label not in skip]
        limits = limits_at_end(
            superset, held, current, unknowns, candidates, step, options.bic_threshold, options.min_gain
        )
    inputs = tuple(ch.input_name(base.chain, j) for j in range(len(base.chain.joints)))
    verdict = verdict_of(
        causes,
        state.rounds,
        bic_threshold=options.bic_threshold,
        min_gain=options.min_gain,
        headroom=held_out_headroom(held.problem, baseline.ho),
        fit=Excitation.of(problem, inputs),
        held_out=Excitation.of(held.problem, inputs),
    )
    return Diagnosis(
        verdict=verdict,
        min_gain=options.min_gain,
        split=split,
        baseline=base,
        evidence=evidence,
        rounds=state.rounds,
        causes=causes,
        held_out=_held_out_summary(rms_base, rms_ext, ho_cost0, ho_cost1, _floor_per_channel(held.problem)),
        delta_bic_total=0.0,
        fraction_explained=0.0,
        fraction_of_excess_explained=None,
        extended_chain=ext_chain,
        extended_measurement=ext_meas,
        extended_parameters=extended_params,
        outputs=traces,
        modal_frequencies_hz=modal,
        wall_time=0.0,
        extended_intervals=ext_intervals,
        costs=costs,
        model_checks=model_checks,
        notes=state.notes,
        not_tried=not_tried,
        detection_limits=limits,
        per_log=per_log,
        held_out_logs=tuple(held.problem.log_names),
    )
