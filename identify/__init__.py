"""identify: fit flexdyn models to measured joint and tip-deflection logs.

- `load_experiment(path)`: an experiment file (TOML) and its logs (CSV, .mat); see docs/experiment-format.md.
- `fit_experiment(experiment)`: Levenberg-Marquardt through the diffrax solve, with
  standard errors, confidence intervals and identifiability warnings;
  `clustered_uncertainty(result)`: intervals that hold when the residual is model error
  (cluster-robust, each log a cluster).
- `make_problem` / `fit`: the same on in-memory logs (`LogData`); a parameter may be
  fitted per log beside shared ones (`Parameter(..., per_log=True)`: an unknown payload
  per log); `fit_independent`: each log its own values of every parameter, all in one
  batch; `between_logs(results)`: do they agree (weighted mean and a chi-square test per
  parameter)? `between_logs(result)` asks the same of one fit's per-log values.
- `residual_report`: residual whiteness and input cross-correlation (MATLAB `resid`).
- `noise_floor`: each channel's noise level estimated from the data alone; every fit
  compares its residuals with it (`FitResult.fit_quality`, `poor_fit`: a wrong basin or a
  missing effect).
- `diagnose(experiment)` / `diagnose_logs(...)`: what the fitted model gets wrong, which
  catalogue extension (`identify.catalogue`) explains it, the extended model and its gain
  on held-out data; `write_report` writes the JSON/Markdown report with plots.
- `Controller`: the feedback law a rig ran while a log was recorded; `make_problem(...,
  controller=)` (or an experiment's `[controller]`) simulates its logs closed loop.
- `Measurement`, `Sensor`: sensor gain/offset/delay/high-pass and actuator lag between the
  model and the log (`identify.measurement`), fittable by name like the chain's parameters.
"""

from typing import TYPE_CHECKING

# the public names, imported on first use (`identify._lazy`): `import identify`, and the
# `identify` command before its arguments are parsed, stay free of JAX's seconds of import
if TYPE_CHECKING:
    from ._data import measurement as measurement, noise_floor as noise_floor
    from ._data.channels import check_channel as check_channel, state_names as state_names
    from ._data.columns import LogError as LogError
    from ._data.controller import Controller as Controller
    from ._data.experiment import Experiment as Experiment, FreeParameter as FreeParameter, LogSpec as LogSpec
    from ._data.experiment_file import load_experiment as load_experiment
    from ._data.logs import Log as Log, load_log as load_log, write_log as write_log
    from ._data.measurement import Measurement as Measurement, Sensor as Sensor
    from ._data.toml_reader import ExperimentError as ExperimentError
    from ._diagnose import catalogue as catalogue, evidence as evidence
    from ._diagnose.diagnosis import Diagnosis as Diagnosis
    from ._diagnose.scores import Cause as Cause, Score as Score
    from ._diagnose.search import diagnose_logs as diagnose_logs
    from ._diagnose.split import split_logs as split_logs
    from ._fit.fit import fit as fit
    from ._fit.fit_independent import fit_independent as fit_independent
    from ._fit.result import FitResult as FitResult, fitted_outputs as fitted_outputs
    from ._fit.steps import SimulationFailed as SimulationFailed
    from ._fit.uncertainty import (
        BetweenLogs as BetweenLogs,
        ClusteredUncertainty as ClusteredUncertainty,
        between_logs as between_logs,
        clustered_uncertainty as clustered_uncertainty,
    )
    from ._model.parameters import Parameter as Parameter
    from ._model.problem import (
        LogData as LogData,
        Problem as Problem,
        log_onset as log_onset,
        make_problem as make_problem,
    )
    from ._model.residuals import predict as predict
    from ._model.synthetic import simulate_log as simulate_log
    from ._report.diagnosis_report import write_report as write_report
    from ._workflow import (
        diagnose as diagnose,
        evaluate_held_out as evaluate_held_out,
        fit_experiment as fit_experiment,
        fit_experiment_independent as fit_experiment_independent,
        log_data as log_data,
        problem_from_experiment as problem_from_experiment,
        residual_report as residual_report,
    )

from ._lazy import exports as _exports

__getattr__, __dir__, __all__ = _exports(__name__, __file__)
