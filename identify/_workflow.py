"""From an experiment file to a fit: the glue between `identify.experiment` and
`identify.fit`, and the residual report."""

from __future__ import annotations

import numpy as np

from ._data.experiment import Experiment, LogSpec
from ._diagnose import residual_tests as diagnostics
from ._diagnose.diagnosis import Diagnosis
from ._diagnose.search import diagnose_logs
from ._diagnose.split import split_logs
from ._fit.fit import fit
from ._fit.fit_independent import fit_independent
from ._fit.result import FitResult, fitted_outputs
from ._model.parameters import Parameter
from ._model.problem import LogData, Problem, make_problem


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


def diagnose(experiment, *, progress=None, **options) -> Diagnosis:
    """Diagnose an `Experiment` (see the module docstring); `options` go to `diagnose_logs`.
    The baseline fit starts from the experiment's `[[starts]]` too (`fit_options`'
    `extra_starts`, unless the caller gives them)."""
    from ._data.experiment import Experiment
    from ._workflow import log_data, parameters

    if not isinstance(experiment, Experiment):
        raise TypeError(
            f"diagnose: expected an Experiment (identify.load_experiment(path)), got {type(experiment).__name__} "
            f"{experiment!r}"
        )
    options["fit_options"] = {"extra_starts": experiment.starts, **(options.get("fit_options") or {})}

    n = experiment.chain.n_links
    fit_logs = [log_data(s, n) for s in experiment.fit_logs]
    val_logs = [log_data(s, n) for s in experiment.validation_logs]
    time_split = not val_logs and len(fit_logs) == 1
    fit_logs, held, desc = split_logs(fit_logs, val_logs)
    noise = {c: v for c, v in experiment.noise.items() if v is not None}
    return diagnose_logs(
        experiment.chain,
        # (a time split holds out a segment of the one log: a per-log parameter is its value)
        parameters(experiment, per_log=not time_split),
        fit_logs,
        held,
        noise,
        measurement=experiment.measurement,
        split=desc,
        progress=progress,
        **options,
    )


def validate(exp, result, progress=None):
    """The fitted model on every validation log (`identify.evaluate_held_out`: physical
    parameters fixed, each log's own initial-state entries and offsets re-estimated).
    Returns `(outputs, report, nuisances)` in the layout of `identify.fitted_outputs`,
    `identify.residual_report` and `FitResult.initial_states/offsets`."""
    from ._fit.result import fitted_outputs
    from ._workflow import evaluate_held_out, residual_report

    held = evaluate_held_out(result, exp, progress=progress)
    nuisances = {
        name: {
            "initial_states": {k: v[0] for k, v in held.initial_states.get(name, {}).items()},
            "offsets": {k: v[0] for k, v in held.offsets.get(name, {}).items()},
            # (each held-out log's own value of a per-log parameter, `Parameter.per_log`)
            "parameters": {p: by_log[name] for p, by_log in held.per_log.items()},
        }
        for name in held.problem.log_names
    }
    return fitted_outputs(held), residual_report(held), nuisances


#: `identify fit` adds cluster-robust intervals (`identify.clustered_uncertainty`) from this
#: many fit logs on (fewer clusters give an interval too uncertain to be useful).
CLUSTER_MIN_LOGS = 5
