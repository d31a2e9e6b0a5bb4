"""From an experiment file to a fit: the glue between `identify.experiment` and
`identify.fit`, and the residual report."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

import flexdyn as fd
from flexdyn._checks import runtime_check_message

from ._data import channels as ch
from ._data.experiment import Experiment, LogSpec
from ._diagnose import evidence, residual_tests as diagnostics
from ._diagnose.diagnosis import Diagnosis
from ._diagnose.search import diagnose_logs
from ._diagnose.split import split_logs
from ._fit.direct import direct_fit
from ._fit.fit import fit
from ._fit.fit_independent import fit_independent
from ._fit.result import FitResult, fitted_outputs
from ._fit.uncertainty import BetweenLogs, ClusteredUncertainty, between_logs, clustered_uncertainty
from ._model.parameters import Parameter
from ._model.problem import LogData, Problem, make_problem, parameter_unit
from ._report.json import package_versions


def log_data(spec: LogSpec, n_joints: int, *, replay: int | None = None) -> LogData:
    """The `LogData` of one experiment log (times start at the log's first sample);
    `replay`: the joint (1-based) of a closed-loop log's command, replayed as an input:
    the references dropped, the command held over each sample as the controller held it."""
    hold = spec.hold
    if replay is not None:
        holds = [hold] * n_joints if isinstance(hold, str) else list(hold)
        holds[replay - 1] = "zoh"
        hold = holds[0] if len(set(holds)) == 1 else tuple(holds)
    return LogData.from_log(
        spec.log,
        n_joints,
        initial=dict(spec.initial),
        fit_initial=tuple(spec.fit_initial),
        offsets=tuple(spec.offsets),
        name=spec.name,
        set=dict(spec.set),
        hold=hold,
        **({"reference": {}} if replay is not None else {}),
    )


def parameters(exp: Experiment, per_log: bool = True) -> list[Parameter]:
    """The experiment's free parameters (`per_log=False`: none of them per log)."""
    return [Parameter(p.name, p.guess, p.lower, p.upper, per_log=p.per_log and per_log) for p in exp.free]


def problem_from_experiment(
    exp: Experiment, logs=None, *, per_log: bool = True, replay: bool = False, **solver
) -> Problem:
    """A `Problem` over the experiment's fit logs (or `logs`, a list of `LogSpec`);
    `per_log=False`: its per-log parameters shared like the others; `replay`: open loop
    even where the experiment declares a controller (its logged command the input, held
    over each sample, the references dropped: the direct method,
    `identify/_fit/direct.py`)."""
    specs = exp.fit_logs if logs is None else logs
    joint = exp.controller.joint if replay and exp.controller is not None else None
    data = [log_data(s, exp.chain.n_links, replay=joint) for s in specs]
    noise = {c: v for c, v in exp.noise.items() if v is not None}
    return make_problem(
        exp.chain,
        parameters(exp, per_log),
        data,
        noise,
        measurement=exp.measurement,
        controller=None if replay else exp.controller,
        **solver,
    )


def fit_experiment(exp: Experiment, *, progress=None, direct: bool = True, **options) -> FitResult:
    """Fit the experiment's free parameters to its fit logs. `options` go to `identify.fit`;
    its `extra_starts` default to the experiment's `[[starts]]`.

    With a `[controller]`, the logs are fitted closed loop, then (`direct=True`) by the
    direct method from that optimum: the logged command replayed open loop, whose
    intervals hold where the loop fit's are too narrow (`identify/_fit/direct.py`; kept
    only if it does not drift, `FitResult.direct_note` says which)."""
    problem = problem_from_experiment(exp)
    estimate = [c for c in problem.channels if exp.noise.get(c) is None]
    options.setdefault("extra_starts", exp.starts)
    result = fit(problem, parameters(exp), estimate_noise=estimate or False, progress=progress, **options)
    if exp.controller is None or not direct:
        return result
    return refit_direct(exp, result, progress=progress, **options)


def refit_direct(exp: Experiment, loop_fit: FitResult, *, progress=None, **options) -> FitResult:
    """The direct-method fit of a closed-loop experiment from its loop fit
    (`identify/_fit/direct.py:direct_fit`): the logged command replayed open loop. `options`
    as `fit_experiment`'s (its starts and stages are not used: one of each, from the loop
    fit's optimum)."""
    try:
        replay = problem_from_experiment(exp, replay=True)
    except ValueError as e:
        why = f"the logs cannot be replayed open loop: {e}"
        return dataclasses.replace(loop_fit, direct_note=f"no direct fit (logged command replayed): {why}")
    estimate = [c for c in replay.channels if exp.noise.get(c) is None]
    skip = ("extra_starts", "n_starts", "n_stages", "horizons")
    kept = {k: v for k, v in options.items() if k not in skip}
    return direct_fit(loop_fit, replay, estimate_noise=estimate or False, progress=progress, **kept)


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
    problem = make_problem(
        chain, own, data, _noise_of(result), measurement=result.measurement, controller=exp.controller
    )
    # (nuisances only: one stage; a per-log parameter: the fit's growing horizon and starts,
    # as for the fit logs, from the fit logs' median)
    options = {} if own else {"n_stages": 1}
    return fit(problem, own, estimate_noise=False, progress=progress, **options)


def _noise_of(result: FitResult) -> dict:
    """The noise levels a fit used, by channel; a direct-method fit's (no command channel)
    completed by the loop fit it started from."""
    loop = {} if result.loop_fit is None else result.loop_fit.sigma
    return {**loop, **result.sigma}


def residual_report(result: FitResult, max_lag: int = 25) -> dict:
    """Per log and channel: residual RMS, whiteness test, and cross-correlation with each
    joint input the log applies, by its channel (`torque1`, `voltage1`, ...; MATLAB
    `resid`)."""
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
                ch.input_name(problem.chain, j): diagnostics.input_correlation(r, torque[:, j], max_lag)
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
        controller=experiment.controller,
        split=desc,
        progress=progress,
        **options,
    )


def validate(exp, result, progress=None):
    """The fitted model on every validation log (`identify.evaluate_held_out`: physical
    parameters fixed, each log's own initial-state entries and offsets re-estimated).
    Returns `(outputs, report, nuisances)` in the layout of `identify.fitted_outputs`,
    `identify.residual_report` and `FitResult.initial_states/offsets`."""
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


@dataclasses.dataclass
class FitReport:
    """Everything `identify fit` prints and writes about one joint fit: the fit, its
    outputs and residual tests on the fit and validation logs, the fitted model's natural
    frequencies (Hz) about `modal_configuration`, model checks, and the optional
    cluster-robust intervals and per-log agreement (each `None` with a note saying why)."""

    experiment: Experiment
    result: FitResult
    outputs: dict
    residuals: dict
    natural_frequencies: list
    modal_configuration: str
    model_checks: list
    robust: ClusteredUncertainty | None = None
    robust_note: str | None = None
    agreement: BetweenLogs | None = None
    agreement_note: str | None = None
    validation_outputs: dict = dataclasses.field(default_factory=dict)
    validation_residuals: dict = dataclasses.field(default_factory=dict)
    validation_nuisances: dict = dataclasses.field(default_factory=dict)
    #: the follow-ups that could not be computed, each "step: error" (the fit itself is kept)
    problems: list = dataclasses.field(default_factory=list)

    @classmethod
    def of_fit(cls, exp: Experiment, result: FitResult, problem: str) -> FitReport:
        """The report of a fit whose follow-ups were not computed (`problem` says why)."""
        return cls(exp, result, {}, {}, [], "", [], problems=[problem])

    def to_dict(self, *, options: dict, command: list) -> dict:
        """`result.json`'s content (docs/experiment-format.md): the fit's `to_dict` with the experiment,
        residuals, validation, modal and uncertainty sections, `options`, `command` and
        the package versions."""
        result, val = self.result, self.validation_nuisances
        doc = result.to_dict()
        doc["experiment"] = experiment_document(self.experiment)
        doc["residuals"] = self.residuals
        doc["validation"] = {
            name: {
                "residuals": self.validation_residuals[name],
                "initial_states": {
                    e: {"value": v, "unit": ch.state_unit(e)} for e, v in val[name]["initial_states"].items()
                },
                "offsets": {c: {"value": v, "unit": ch.channel_unit(c)} for c, v in val[name]["offsets"].items()},
                "parameters": {
                    p: {"value": v, "unit": parameter_unit(result.problem, p)}
                    for p, v in val[name]["parameters"].items()
                },
            }
            for name in self.validation_outputs
        }
        doc["natural_frequencies_hz"] = self.natural_frequencies
        doc["model_checks"] = self.model_checks
        doc["clustered_uncertainty"] = None if self.robust is None else self.robust.to_dict()
        doc["per_log_agreement"] = None if self.agreement is None else self.agreement.to_dict()
        doc["modal_configuration"] = self.modal_configuration
        doc["problems"] = list(self.problems)
        doc["options"] = options
        doc["command"] = command
        doc["versions"] = package_versions()
        return doc


def experiment_document(exp: Experiment) -> dict:
    """The experiment's part of result.json: name, description, path, logs."""
    return {
        "name": exp.name,
        "description": exp.description,
        "path": str(Path(exp.path).resolve()),
        "logs": [
            {"name": s.name, "file": str(Path(s.file).resolve()), "role": s.role, "samples": len(s.log), "set": s.set}
            for s in exp.logs
        ],
    }


def _robust_intervals(exp: Experiment, result: FitResult, say) -> tuple[ClusteredUncertainty | None, str | None]:
    """Cluster-robust intervals, each fit log a cluster, where there are enough logs
    (`CLUSTER_MIN_LOGS`) and they apply; else `None` and why not (or no note)."""
    n_fit = len(exp.fit_logs)
    if n_fit < CLUSTER_MIN_LOGS:
        return None, None
    if result.problem.per_log:
        return None, (
            "cluster-robust intervals not computed: a per-log parameter is informed by one log (cluster) only, "
            "so they do not apply"
        )
    if n_fit <= len(result.names):
        return None, (
            f"cluster-robust intervals not computed: {n_fit} fit logs for {len(result.names)} free parameters "
            "(they need more logs than parameters)"
        )
    say(f"cluster-robust intervals ({n_fit} fit logs as clusters) ...")
    return clustered_uncertainty(result), None


def fit_report(exp: Experiment, result: FitResult, *, progress=None, say=print) -> FitReport:
    """The follow-ups of a joint fit that `identify fit` reports: outputs and residual
    tests, natural frequencies, model checks, cluster-robust intervals, the validation
    logs (`validate`) and, for per-log parameters, their agreement (`between_logs`).
    `say` prints what is being computed; `progress` goes to the validation fits.

    A follow-up that fails (a simulation failing on a validation log, say) is left out and
    named in `FitReport.problems` with its error: the finished fit is never lost to it."""
    problems = []

    def attempt(step: str, compute, default):
        try:
            return compute()
        except Exception as e:  # noqa: BLE001 (any failure: reported, the fit kept)
            problems.append(f"{step} not computed: {type(e).__name__}: {runtime_check_message(e) or e}")
            say(f"warning: {problems[-1]}")
            return default

    outputs = attempt("fitted outputs", lambda: fitted_outputs(result), {})
    residuals = attempt("residual tests", lambda: residual_report(result), {})
    freqs, where = attempt("natural frequencies", lambda: fd.natural_frequencies(result.chain), ([], ""))
    robust, robust_note = attempt("cluster-robust intervals", lambda: _robust_intervals(exp, result, say), (None, None))
    val_outputs, val_residuals, val_nuisances = {}, {}, {}
    if exp.validation_logs:
        own = "".join(f", {p.name}" for p in exp.free if p.per_log)
        say(f"checking the fit on the validation log(s) (their initial state, offsets{own} re-estimated) ...")
        val_outputs, val_residuals, val_nuisances = attempt(
            "validation", lambda: validate(exp, result, progress), ({}, {}, {})
        )
    checks = attempt(
        "model checks",
        lambda: evidence.stiffening_checks_of(result.chain, {**outputs, **val_outputs}, key="simulated"),
        [],
    )
    agreement, agreement_note = None, None
    if result.problem.per_log and result.converged and len(exp.fit_logs) >= 2:
        try:  # do the per-log values differ beyond their intervals?
            agreement = between_logs(result)
        except ValueError as e:  # (a per-log value some log does not determine)
            agreement_note = f"per-log values not compared: {e}"
    return FitReport(
        exp,
        result,
        outputs,
        residuals,
        freqs,
        where,
        checks,
        robust,
        robust_note,
        agreement,
        agreement_note,
        val_outputs,
        val_residuals,
        val_nuisances,
        problems,
    )
