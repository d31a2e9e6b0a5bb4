"""From an experiment file to a fit: the glue between `identify.experiment` and
`identify.fit`, and the residual report."""

from __future__ import annotations

import numpy as np

from . import diagnostics
from .experiment import Experiment, LogSpec
from .fit import FitResult, LogData, Parameter, Problem, fit, fit_independent, fitted_outputs, make_problem


def log_data(spec: LogSpec, n_joints: int) -> LogData:
    """The `LogData` of one experiment log (times start at the log's first sample)."""
    return LogData.from_log(
        spec.log,
        n_joints,
        initial=dict(spec.initial),
        fit_initial=tuple(spec.fit_initial),
        offsets=tuple(spec.offsets),
        name=spec.name,
        set=dict(spec.set),
    )


def parameters(exp: Experiment, per_log: bool = True) -> list[Parameter]:
    """The experiment's free parameters (`per_log=False`: none of them per log)."""
    return [Parameter(p.name, p.guess, p.lower, p.upper, per_log=p.per_log and per_log) for p in exp.free]


def problem_from_experiment(exp: Experiment, logs=None, *, per_log: bool = True, **solver) -> Problem:
    """A `Problem` over the experiment's fit logs (or `logs`, a list of `LogSpec`);
    `per_log=False`: its per-log parameters shared like the others."""
    specs = exp.fit_logs if logs is None else logs
    data = [log_data(s, exp.chain.n_links) for s in specs]
    noise = {c: v for c, v in exp.noise.items() if v is not None}
    return make_problem(exp.chain, parameters(exp, per_log), data, noise, measurement=exp.measurement, **solver)


def fit_experiment(exp: Experiment, *, progress=None, **options) -> FitResult:
    """Fit the experiment's free parameters to its fit logs. `options` go to `identify.fit`;
    its `extra_starts` default to the experiment's `[[starts]]`."""
    problem = problem_from_experiment(exp)
    estimate = [c for c in problem.channels if exp.noise.get(c) is None]
    options.setdefault("extra_starts", exp.starts)
    return fit(problem, parameters(exp), estimate_noise=estimate or False, progress=progress, **options)


def fit_experiment_independent(exp: Experiment, *, progress=None, **options) -> list[FitResult]:
    """Fit the experiment's free parameters to each fit log on its own
    (`identify.fit_independent`, all logs in one batch): one `FitResult` per log. Channels
    without a declared noise level get each log's own estimate. `options` go to
    `fit_independent`. A `per_log` parameter is fitted like the others (each log its own
    values of all of them)."""
    problem = problem_from_experiment(exp, per_log=False)
    estimate = [c for c in problem.channels if exp.noise.get(c) is None]
    return fit_independent(problem, estimate_noise=estimate or False, progress=progress, **options)


def evaluate_held_out(result: FitResult, exp: Experiment, logs=None, *, progress=None) -> FitResult:
    """The fitted model on held-out logs (default: the experiment's validation logs):
    shared physical parameters fixed at the fitted values, only each log's own unknowns
    estimated: its `fit_initial` entries and offsets, and its own value of each per-log
    parameter (`Parameter.per_log`, from the median of the fit logs' values, within the
    same bounds). Returns a `FitResult` over those logs (free parameters: the per-log
    ones only); its `fitted_outputs` and `residual_report` give the held-out error."""
    specs = exp.validation_logs if logs is None else logs
    if not specs:
        raise ValueError("evaluate_held_out: the experiment has no validation logs")
    chain = result.chain
    data = [log_data(s, chain.n_links) for s in specs]
    own = [
        Parameter(p.name, float(np.median(list(result.per_log[p.name].values()))), p.lower, p.upper, per_log=True)
        for p in result.problem.parameters
        if p.per_log
    ]
    problem = make_problem(chain, own, data, dict(result.sigma), measurement=result.measurement)
    # (nuisances only: one stage; a per-log parameter: the fit's growing horizon and starts,
    # as for the fit logs, from the fit logs' median)
    options = {} if own else {"n_stages": 1}
    return fit(problem, own, estimate_noise=False, progress=progress, **options)


def residual_report(result: FitResult, max_lag: int = 25) -> dict:
    """Per log and channel: residual RMS, whiteness test, and cross-correlation with each
    joint torque the log applies (MATLAB `resid`)."""
    report = {}
    outputs = fitted_outputs(result)
    problem = result.problem
    for l, (name, entry) in enumerate(outputs.items()):
        t = entry["t"]
        uniform = np.allclose(np.diff(t), np.median(np.diff(t)), rtol=1e-3) if len(t) > 2 else True
        per_channel = {}
        torque = np.asarray(problem.torque_v[l])[: len(t)]
        for c, r in entry["residual"].items():
            item = {"rms": float(np.sqrt(np.mean(r**2))), "uniform_sampling": bool(uniform)}
            item["whiteness"] = diagnostics.whiteness(r, max_lag)
            item["input_correlation"] = {
                f"torque{j + 1}": diagnostics.input_correlation(r, torque[:, j], max_lag)
                for j in range(torque.shape[1])
                if np.any(torque[:, j] != 0)
            }
            per_channel[c] = item
        report[name] = per_channel
    return report
