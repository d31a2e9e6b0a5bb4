"""identify: fit flexdyn models to measured joint and tip-deflection logs.

- `load_experiment(path)`: an experiment file (TOML) and its logs (CSV, .mat); see FORMAT.md.
- `fit_experiment(experiment)`: Levenberg-Marquardt through the diffrax solve, with
  standard errors, confidence intervals and identifiability warnings.
- `make_problem` / `fit`: the same on in-memory logs (`LogData`).
- `residual_report`: residual whiteness and input cross-correlation (MATLAB `resid`).
"""

from .channels import check_channel as check_channel, state_names as state_names
from .experiment import (
    Experiment as Experiment,
    ExperimentError as ExperimentError,
    FreeParameter as FreeParameter,
    LogSpec as LogSpec,
    load_experiment as load_experiment,
)
from .fit import (
    FitResult as FitResult,
    LogData as LogData,
    Parameter as Parameter,
    Problem as Problem,
    fit as fit,
    fit_independent as fit_independent,
    fitted_outputs as fitted_outputs,
    make_problem as make_problem,
    predict as predict,
)
from .logs import Log as Log, LogError as LogError, load_log as load_log
from .run import (
    evaluate_held_out as evaluate_held_out,
    fit_experiment as fit_experiment,
    log_data as log_data,
    problem_from_experiment as problem_from_experiment,
    residual_report as residual_report,
)
from .synthetic import simulate_log as simulate_log
