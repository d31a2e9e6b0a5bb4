"""`FitResult`: what a fit returns, its summary and JSON form; `fitted_outputs`."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

import flexdyn as fd

from .._data import channels as ch, measurement as meas, noise_floor as nf
from .._data.channels import state_names
from .._data.measurement import Measurement
from .._data.units import display_unit
from .._model.parameters import Z95, names_at_bounds, theta_from_x, x_from_z
from .._model.problem import Problem, guesses_of, parameter_unit
from .._model.residuals import (
    initial_states_of,
    predict_jit,
    sensor_offsets,
)
from .._model.variables import Variables
from . import covariance
from .covariance import Covariance
from .quality import (
    GROSS_MISFIT,
    WEIGHT_MISMATCH,
    _floor_above_residual_notes,
    _initial_far,
    _reversed_channels,
    noise_floors,
)


@dataclasses.dataclass
class FitResult:
    """Everything a fit produced (SI units; see `summary()` and `to_dict()`)."""

    names: list[str]
    values: np.ndarray
    guesses: np.ndarray
    std_errors: np.ndarray
    ci_low: np.ndarray
    ci_high: np.ndarray
    correlation: np.ndarray
    initial_states: dict  # log name -> {entry: (value, SE)}
    offsets: dict  # log name -> {channel: (value, SE)}
    sigma: dict  # channel -> noise standard deviation used for the weights
    residual_variance: float
    cost: float
    n_residuals: int
    stages: list  # [Stage]
    converged: bool
    at_bounds: list  # parameters that ended on a bound (the fit is then not converged)
    identifiability: list  # warnings, [{'combination': str, 'ratio': float}]
    singular_values: np.ndarray
    wall_time: float
    problem: Problem = dataclasses.field(repr=False)
    z: Variables = dataclasses.field(repr=False)
    step: object = dataclasses.field(repr=False, default=None)
    # channel -> {'residual_rms', 'noise_floor', 'ratio', 'poor'} (`identify.noise_floor`):
    # does the fitted model explain the data down to a noise floor estimated without it?
    fit_quality: dict = dataclasses.field(default_factory=dict)
    # the weighted residuals and their Jacobian blocks at the optimum, natural coordinates
    # (`jacobian_blocks_at`: `(r, S, U, slots, used)`), what the covariance came from; reused
    # by `identify.clustered_uncertainty` (None: it computes them afresh)
    jacobian_blocks: tuple | None = dataclasses.field(repr=False, default=None)
    # logs fitted together in one vmapped batch (`fit_independent`): `wall_time` is then the
    # batch's time divided among them
    batch_size: int = 1
    # channels whose simulation moves against the measurement (`_reversed_channels`):
    # channel -> correlation of the two (below REVERSED_CORRELATION); checked on a poor fit
    reversed_channels: dict = dataclasses.field(default_factory=dict)
    # fitted initial-state entries far from their log's first sample (`_initial_far`):
    # log -> {entry: (fitted + offset, first sample, noise)}, SI
    initial_far: dict = dataclasses.field(default_factory=dict)
    # the channels whose `sigma` the fit re-estimated from its residuals (`estimate_noise`);
    # the others' were given (`make_problem`'s `noise`, or its default)
    sigma_estimated: tuple = ()
    # restarts (`fit`'s `max_restarts`) whose simulation failed, each with its error: the
    # result is the best attempt that finished
    failed_restarts: list = dataclasses.field(default_factory=list)
    # `fit(stop_when_stiff=True)`: where and why the growing horizon stopped in a model too
    # stiff for the solver ("" when every stage ran). The result is then the last finished
    # stage's, its cost over that stage's horizon only (not comparable with a whole fit's),
    # and not converged.
    stopped: str = ""
    # closed-loop logs (`identify/_fit/direct.py`): which fit this is, the direct method's
    # (the logged command replayed) or the loop's, and why ("" for an open-loop problem);
    # the loop fit a direct result started from, and a direct fit that was not kept
    direct_note: str = ""
    # how the parameters' standard errors were computed: "white" (`s^2 (J^T J)^+`) or
    # "rounding" (quantised channels: their rounding propagated, `identify/_fit/rounding.py`)
    interval_method: str = "white"
    loop_fit: FitResult | None = dataclasses.field(repr=False, default=None)
    direct_rejected: FitResult | None = dataclasses.field(repr=False, default=None)

    @property
    def value(self) -> dict:
        """Parameter name -> fitted value (SI)."""
        return dict(zip(self.names, self.values.tolist()))

    @property
    def shared_value(self) -> dict:
        """Name -> fitted value (SI) of the parameters shared by all logs (all but the
        per-log ones, `Parameter.per_log`)."""
        return {n: v for n, v in self.value.items() if n in self.problem.shared_names}

    @property
    def per_log(self) -> dict:
        """Per-log parameters (`Parameter.per_log`): name -> {log: fitted value (SI)}."""
        return {
            name: {log: float(self.values[i]) for log, i in zip(self.problem.log_names, index)}
            for name, index in self.problem.per_log
        }

    @property
    def chain(self) -> fd.Chain:
        """The problem's chain with the fitted values of its shared parameters (a per-log
        parameter keeps the rig's value: `log_chain(log)` has a log's own)."""
        return fd.with_parameters(self.problem.chain, meas.split_values(self.shared_value)[0])

    @property
    def measurement(self) -> Measurement:
        """The problem's measurement model with the fitted values of its shared
        parameters (per-log ones: `log_measurement(log)`)."""
        return meas.with_parameters(self.problem.measurement, meas.split_values(self.shared_value)[1])

    def _log_values(self, log: str) -> dict:
        names = self.problem.log_names
        if log not in names:
            raise ValueError(f"FitResult: no log named {log!r}; the fit's logs are {list(names)}")
        l = names.index(log)
        values = dict(self.shared_value)
        values.update({n: float(v) for n, v in zip(self.problem.log_set_names, np.asarray(self.problem.log_set)[l])})
        values.update({name: by_log[log] for name, by_log in self.per_log.items()})
        return values

    def log_chain(self, log: str) -> fd.Chain:
        """The chain that simulated log `log`: the fitted shared values, the log's known
        values (`LogData.set`) and its own fitted per-log values."""
        return fd.with_parameters(self.problem.chain, meas.split_values(self._log_values(log))[0])

    def log_measurement(self, log: str) -> Measurement:
        """The measurement model of log `log` (as `log_chain`)."""
        return meas.with_parameters(self.problem.measurement, meas.split_values(self._log_values(log))[1])

    @property
    def closed_loop_caveat(self) -> str:
        """For a fit simulated closed loop (`Problem.loop`), why its intervals may be too
        narrow (empty otherwise, and for a direct-method fit, `identify/_fit/direct.py`,
        whose problem is open loop). They treat the residual as sensor noise about the
        model's loop, but the rig's controller fed back its own readings, noise and rounding
        included: a count that flips at another instant in the model than on the rig
        changes the command and all the motion after it. Measured on the servo example over
        seeded sensor count phases (`tests/identify/test_servo_flexible_link_coverage.py`);
        not on the frictionless servo pendulum of `tests/identify/test_closed_loop.py`."""
        if self.problem is None or self.problem.loop is None:
            return ""
        return (
            "closed-loop fit: the intervals treat the residual as sensor noise about the model's loop, not the "
            "rig's controller feeding back its own noise and rounding, which can move the trajectory; where it "
            "does they are too narrow: on the servo example (geared friction that holds the hub, quantised "
            "readings) 56 % of 95 % intervals held the truth over seeded sensor count phases, the damping and "
            "dry friction up to 7 standard errors off (on a frictionless servo pendulum with a noisy reading "
            "they held). The direct method (the logged command replayed from this optimum; identify.fit_experiment's "
            "default) does not have this problem"
        )

    @property
    def poor_fit(self) -> list[str]:
        """The channels whose residual RMS exceeds `identify.noise_floor.POOR_FIT` times
        their model-free noise floor: a wrong basin or a missing effect."""
        return [c for c, q in self.fit_quality.items() if q["poor"]]

    def _weight_hint(self, c: str, q: dict) -> str:
        """For a poorly fitted channel of a fit with several channels whose weight (the
        noise level it assumed) is over `WEIGHT_MISMATCH` times off its noise floor: the
        weights as a cause, not only the model (make_problem's default weights, 1 % of each
        channel's RMS, can leave every log several times its floor where the declared noise
        puts it at the floor). A weight the fit re-estimated itself is named as such: on a
        model missing an effect, a re-estimated noise can grow far above its floor over the
        rounds while a declared channel keeps its weight, and the fit trades the first
        channel away; re-estimating again does not help."""
        used, floor = self.sigma.get(c), q["noise_floor"]
        if len(self.sigma) < 2 or not used or not floor > 0:
            return ""
        ratio = used / floor
        if 1 / WEIGHT_MISMATCH <= ratio <= WEIGHT_MISMATCH:
            return ""
        scale, unit = display_unit(c)
        if c in self.sigma_estimated and ratio > WEIGHT_MISMATCH:
            return (
                f"; its weight was re-estimated from the residuals as a noise of {scale * used:.3g} {unit}, "
                f"{ratio:.3g} times its floor: a model that misses an effect inflates a re-estimated noise with its "
                "misfit, and the fit then trades that channel away against those of declared noise, biasing what it "
                "informs "
                f"(declare its noise, about {scale * floor:.3g} {unit} from its floor, to keep its weight; "
                "`identify diagnose` looks for the missing effect)"
            )
        return (
            f"; its weight assumed a noise of {scale * used:.3g} {unit}, {ratio:.3g} times its floor: with several "
            "channels, weights this far off let the others pull the fit (declare each channel's noise, or let fit "
            "re-estimate it)"
        )

    def summary(self) -> str:
        """The parameter table (value, standard error, 95 % interval assuming white residuals,
        guess, change, unit), cost and convergence, goodness of fit against the noise floor,
        and warnings. Intervals of combinations, and intervals robust to correlated
        residuals, come from `identify.clustered_uncertainty(result).interval(fn)`."""
        lines = []
        if self.problem is not None:  # which logs: a per-log result of `fit_independent` names its own
            names = self.problem.log_names
            shown = ", ".join(names) if len(names) <= 6 else ", ".join(names[:5]) + f", ... ({len(names) - 5} more)"
            lines.append(f"fit to {len(names)} log{'s' if len(names) != 1 else ''}: {shown}")
        lines.append(
            f"{'parameter':<28} {'value':>12} {'std err':>10} {'95% CI':>25} {'guess':>12} {'change':>8}  unit",
        )
        for i, n in enumerate(self.names):
            change = (self.values[i] - self.guesses[i]) / abs(self.guesses[i]) if self.guesses[i] else float("nan")
            ci = covariance.interval_text(self.ci_low[i], self.ci_high[i], self.std_errors[i])
            d = max(5, covariance.digits(self.values[i], self.std_errors[i]))
            unit = "" if self.problem is None else parameter_unit(self.problem, n)
            lines.append(
                f"{n:<28} {self.values[i]:>12.{d}g} {self.std_errors[i]:>10.3g} {ci:>25} "
                f"{self.guesses[i]:>12.4g} {100 * change:>7.1f}%  {unit}"
            )
        if self.problem is not None:
            lines.extend(back_emf_lines(self.chain))
        if self.problem is not None and self.problem.log_set_names:  # (`LogData.set`)
            values = np.asarray(self.problem.log_set)
            for k, n in enumerate(self.problem.log_set_names):
                per_log = ", ".join(f"{v:g} ({log})" for v, log in zip(values[:, k], self.problem.log_names))
                lines.append(f"known per log: {n} = {per_log} {parameter_unit(self.problem, n)}")
        its = sum(s.iterations for s in self.stages)
        lines.append(
            f"cost {self.cost:.6g} over {self.n_residuals} residuals, residual variance {self.residual_variance:.4g}, "
            f"{its} LM iterations in {len(self.stages)} solver stages (`stages`), {self.wall_time:.1f} s"
            + (f" (its share of {self.batch_size} logs fitted in one batch)" if self.batch_size > 1 else "")
            + ", "
            f"{'converged' if self.converged else 'NOT converged'}"
        )
        if self.fit_quality:
            lines.append(
                "residual RMS / model-free noise floor: "
                + ", ".join(f"{c} {q['ratio']:.3g}" for c, q in self.fit_quality.items())
            )
            lines.extend(_floor_above_residual_notes(self.fit_quality))
        for name in self.at_bounds:
            i = self.names.index(name)
            at_lower = False  # (on the lower of its two bounds, in the natural coordinate)
            if self.problem is not None and self.problem.log_scale[i]:
                x, lo, hi = math.log(self.values[i]), float(self.problem.lower[i]), float(self.problem.upper[i])
                at_lower = abs(x - lo) < abs(x - hi)
            hint = (
                f"; {name} is positive and fitted in log space, so it cannot reach 0: if its true value may be 0 "
                "(no payload, no damping), fix it at 0 instead of fitting it"
                if at_lower
                else ""
            )
            lines.append(
                f"warning: {name} ended on its bound: widen the bounds or improve the guess{hint}. The intervals "
                "above assume an interior optimum and do not hold on a bound (nor, for the parameters correlated "
                "with it, off it)"
            )
        for c in self.poor_fit:
            q = self.fit_quality[c]
            scale, unit = display_unit(c)
            lines.append(
                f"warning: the residual of {c} (RMS {scale * q['residual_rms']:.3g} {unit}) is {q['ratio']:.3g} times "
                f"its noise floor ({scale * q['noise_floor']:.3g} {unit}, estimated from the data alone, pooled "
                "over the logs: `identify fit`'s residual table and identify.residual_report give each log's): the fit "
                "ended in a wrong basin or the model misses an effect (try other guesses, or `identify diagnose`), "
                "unless the sensor's noise is low-pass filtered (a first-order filter at a twentieth of the "
                "sampling rate makes the floor 0.42 of the noise: identify.noise_floor)"
                + (
                    "; this far off, check the set-up first: the rig's gravity against the logs' angle zero, and "
                    "the columns' units (docs/experiment-format.md)"
                    if q["ratio"] > GROSS_MISFIT
                    else ""
                )
                + self._weight_hint(c, q)
            )
        for log, entries in self.initial_far.items():
            for e, (start, first, noise) in entries.items():
                scale, unit = display_unit(e)
                lines.append(
                    f"warning: log {log!r}: the fitted initial {e} ({scale * start:.4g} {unit}, with its offset) is "
                    f"{scale * abs(start - first):.3g} {unit} from the log's first sample "
                    f"({scale * first:.4g} {unit}), "
                    f"{abs(start - first) / noise:.0f}x the channel's noise: the fit moved the start to absorb a "
                    "misfit (a missing effect, or a log that does not start as declared)"
                )
        for c, corr in self.reversed_channels.items():
            lines.append(
                f"warning: {c} first moves against the simulation's push (cosine {corr:.2f} of the two traces over "
                "each log's first push of the torque): is its sign "
                "reversed (or the torque's)? flexdyn's angles, deflections and torques are counter-clockwise "
                "positive (README: conventions); a reversed column is read with sign = -1 in its calibration in "
                f"the log's entry (calibration = {{ {c} = {{ sign = -1 }} }}, or the torque's; any unit: "
                "docs/experiment-format.md)"
            )
        if self.poor_fit:
            lines.append(
                "note: the intervals above assume white residuals; with model error in the residual they are "
                "too narrow (identify.clustered_uncertainty assumes only independent logs)"
            )
        for text in self.failed_restarts:
            lines.append(f"note: {text}; the result is the best attempt that finished")
        if self.stopped:
            lines.append(f"note: the fit {self.stopped}; the result is that stage's, over its horizon only")
        if self.interval_method == "rounding":
            lines.append(
                "note: intervals from the quantised channels' rounding propagated through the fit (its phase "
                "unknown, the same in every log unless the channel's offset is fitted per log), not the white formula"
            )
        if self.direct_note:
            lines.append(f"note: {self.direct_note}")
        if self.closed_loop_caveat:
            lines.append(f"warning: {self.closed_loop_caveat}")
        for w in self.identifiability:
            lines.append(
                f"warning: the data cannot separate {w['combination']} (singular value ratio {w['ratio']:.2g})"
            )
        undetermined = [n for n, se in zip(self.names, self.std_errors) if not np.isfinite(se)]
        if undetermined:
            lines.append(
                f"warning: {', '.join(undetermined)} not determined by these data (no interval): the fit is the "
                "same anywhere along the combination(s) the data cannot separate; fix one parameter of each, or "
                "add data that separate them"
            )
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """Everything `summary()` shows, JSON-ready (SI units; `identify fit` writes it to
        `result.json`)."""
        return {
            "parameters": [
                {
                    "name": n,
                    "value": float(self.values[i]),
                    "std_error": float(self.std_errors[i]),
                    "ci95": [float(self.ci_low[i]), float(self.ci_high[i])],
                    "guess": float(self.guesses[i]),
                    "unit": parameter_unit(self.problem, n),
                }
                for i, n in enumerate(self.names)
            ],
            "known_per_log": {
                log: {n: float(v) for n, v in zip(self.problem.log_set_names, row)}
                for log, row in zip(self.problem.log_names, np.asarray(self.problem.log_set).tolist())
            }
            if self.problem is not None and self.problem.log_set_names
            else {},
            # per-log parameters (`Parameter.per_log`): name -> {log: entry `name[log]` above}
            "fitted_per_log": {
                name: {log: f"{name}[{log}]" for log in self.problem.log_names} for name, _ in self.problem.per_log
            }
            if self.problem is not None
            else {},
            "correlation": self.correlation.tolist(),
            "correlation_names": list(self.names),  # the rows' and columns' order
            # per log: {entry: {value, std_error, unit}}, named fields rather than bare pairs
            "initial_states": {
                k: {e: _valued(v, se, ch.state_unit(e)) for e, (v, se) in d.items()}
                for k, d in self.initial_states.items()
            },
            "offsets": {
                k: {c: _valued(v, se, ch.channel_unit(c)) for c, (v, se) in d.items()} for k, d in self.offsets.items()
            },
            "noise_sigma": self.sigma,
            "noise_sigma_estimated": list(self.sigma_estimated),
            "failed_restarts": list(self.failed_restarts),
            "stopped": self.stopped,
            "closed_loop_caveat": self.closed_loop_caveat,
            "direct_note": self.direct_note,
            "interval_method": self.interval_method,
            # the closed-loop fit a direct-method result started from (None otherwise)
            "loop_fit": None
            if self.loop_fit is None
            else {"value": self.loop_fit.value, "cost": self.loop_fit.cost, "fit_quality": self.loop_fit.fit_quality},
            # the SI unit of every per-channel value here (noise_sigma, fit_quality's
            # residual_rms and noise_floor; `identify fit` adds residual RMS in the same units)
            "channel_units": {c: ch.channel_unit(c) for c in self.sigma},
            "residual_variance": self.residual_variance,
            "cost": self.cost,
            "n_residuals": self.n_residuals,
            "stages": [s.to_dict() for s in self.stages],
            # where each log's horizons count from (`log_onset`), s after its first sample
            "onset_s": {
                name: float(o - t0)
                for name, o, t0 in zip(
                    self.problem.log_names, np.asarray(self.problem.onset), np.asarray(self.problem.t[:, 0])
                )
            },
            "converged": self.converged,
            "at_bounds": self.at_bounds,
            "reversed_channels": self.reversed_channels,
            "initial_far": {
                log: {e: {"fitted_with_offset": a, "first_sample": b, "noise": n} for e, (a, b, n) in d.items()}
                for log, d in self.initial_far.items()
            },
            "identifiability_warnings": self.identifiability,
            "fit_quality": self.fit_quality,
            "singular_values": self.singular_values.tolist(),
            "wall_time_s": self.wall_time,
            "batch_size": self.batch_size,
        }


def _valued(value: float, std_error: float, unit: str) -> dict:
    """A fitted nuisance as `FitResult.to_dict` writes it."""
    return {"value": float(value), "std_error": float(std_error), "unit": unit}


def _finish(
    problem: Problem, parameters, z, x, sigma, step, cov: Covariance, stages, wall_time, residual_ms, blocks=None
) -> FitResult:
    """Host-side statistics of a converged fit: intervals, nuisances, convergence (the
    covariance and identifiability from `identify.covariance`), the goodness of fit
    against the model-free noise floor (`identify.noise_floor`; `residual_ms`:
    `_residual_ms` at `z`; `blocks`: the Jacobian blocks the covariance came from)."""
    se_nat = cov.std_errors
    p = len(problem.names)
    xs = np.asarray(x)
    values = np.array([np.exp(v) if s else v for v, s in zip(xs, problem.log_scale)])
    se = np.array([values[i] * se_nat[i] if problem.log_scale[i] else se_nat[i] for i in range(p)])
    with np.errstate(over="ignore"):  # an unidentifiable parameter has an unbounded interval
        lo = np.array(
            [np.exp(xs[i] - Z95 * se_nat[i]) if problem.log_scale[i] else xs[i] - Z95 * se_nat[i] for i in range(p)]
        )
        hi = np.array(
            [np.exp(xs[i] + Z95 * se_nat[i]) if problem.log_scale[i] else xs[i] + Z95 * se_nat[i] for i in range(p)]
        )
        se = np.where(np.isfinite(se), se, np.inf)
    states = state_names(problem.chain)
    init, offs = {}, {}
    for k, (l, s) in enumerate(problem.y0_free):
        init.setdefault(problem.log_names[l], {})[states[s]] = (float(z.y0[k]), float(se_nat[p + k]))
    q = p + len(problem.y0_free)
    for k, (l, c) in enumerate(problem.offset_free):
        offs.setdefault(problem.log_names[l], {})[problem.channels[c]] = (float(z.offset[k]), float(se_nat[q + k]))
    at_bounds = names_at_bounds(problem, xs)
    quality = nf.goodness(problem.channels, residual_ms, *noise_floors(problem))
    poor = [c for c, q in quality.items() if q["poor"]]
    reversed_channels = _reversed_channels(problem, z, sigma, step, poor) if poor else {}
    initial_far = _initial_far(problem, init, offs, sigma)
    # A parameter on its bound is not an interior optimum: the standard errors mean nothing
    # there and the bound, not the data, decided the value.
    converged = stages[-1].outcome == "successful" and not at_bounds
    return FitResult(
        names=list(problem.names),
        values=values,
        guesses=np.array(guesses_of(problem, parameters), float),
        std_errors=se,
        ci_low=lo,
        ci_high=hi,
        correlation=cov.correlation,
        initial_states=init,
        offsets=offs,
        sigma={c: float(s) for c, s in zip(problem.channels, sigma)},
        residual_variance=cov.residual_variance,
        cost=cov.rss,
        n_residuals=cov.n_residuals,
        stages=stages,
        converged=converged,
        at_bounds=at_bounds,
        identifiability=cov.identifiability,
        singular_values=cov.singular_values,
        wall_time=wall_time,
        fit_quality=quality,
        reversed_channels=reversed_channels,
        initial_far=initial_far,
        problem=problem,
        z=z,
        step=step,
        jacobian_blocks=blocks,
        interval_method=cov.method,
    )


def fitted_outputs(result: FitResult) -> dict:
    """Per log: `{'t', 'measured': {ch: ...}, 'simulated': {ch: ...}, 'residual': {ch: ...}}`
    (SI; simulated includes the fitted sensor offsets), for plots and residual tests."""
    problem, z = result.problem, result.z
    theta = theta_from_x(problem, x_from_z(problem, z.phys))
    pred, _ = predict_jit(problem, theta, initial_states_of(problem, z.y0), None, result.step)
    off = sensor_offsets(problem, z.offset)
    pred = np.asarray(pred + off[:, None, :])
    meas, valid, present = np.asarray(problem.measured), np.asarray(problem.valid), np.asarray(problem.present)
    out = {}
    for l, name in enumerate(problem.log_names):
        k = valid[l]
        entry = {"t": np.asarray(problem.t[l])[k], "measured": {}, "simulated": {}, "residual": {}}
        for j, c in enumerate(problem.channels):
            if present[l, j]:
                entry["measured"][c] = meas[l, k, j]
                entry["simulated"][c] = pred[l, k, j]
                entry["residual"][c] = pred[l, k, j] - meas[l, k, j]
        out[name] = entry
    return out


def back_emf_lines(chain: fd.Chain) -> list[str]:
    """One line per joint driven by a voltage through a motor: its back-EMF damping
    `N^2 K_t^2 / R` at the fitted values (`flexdyn.motor.back_emf_damping`; below the
    electrical corner frequency `R / (2 pi L)` for an inductive motor).
    The model has it through the motor, so the fitted `joint<i>.damping` is the damping
    beyond it; a model of the same rig without the motor would need a joint damping of at
    least this (issue 61: a fit that left the motor out went below it)."""
    lines = []
    for i, (joint, motor) in enumerate(zip(chain.joints, chain.motors), start=1):
        if motor is not None and motor.drive == "voltage":
            floor = float(fd.motor.back_emf_damping(motor, joint.gear_ratio))
            lines.append(
                f"joint{i}: back-EMF damping N^2 K_t^2 / R = {floor:.4g} N m s/rad through motor{i} (in the model; "
                f"joint{i}.damping is the damping beyond it, and a model without the motor needs at least this)"
            )
    return lines
