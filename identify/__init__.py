"""identify: fit flexdyn models to measured joint and tip-deflection logs.

- `load_experiment(path)`: an experiment file (TOML) and its logs (CSV, .mat); see FORMAT.md.
- `fit_experiment(experiment)`: Levenberg-Marquardt through the diffrax solve, with
  standard errors, confidence intervals and identifiability warnings.
- `make_problem` / `fit`: the same on in-memory logs (`LogData`).
- `residual_report`: residual whiteness and input cross-correlation (MATLAB `resid`).
"""

from .channels import check_channel as check_channel
from .channels import state_names as state_names
from .experiment import (
    Experiment as Experiment,
)
from .experiment import (
    ExperimentError as ExperimentError,
)
from .experiment import (
    FreeParameter as FreeParameter,
)
from .experiment import (
    LogSpec as LogSpec,
)
from .experiment import (
    load_experiment as load_experiment,
)
from .fit import (
    FitResult as FitResult,
)
from .fit import (
    LogData as LogData,
)
from .fit import (
    Parameter as Parameter,
)
from .fit import (
    Problem as Problem,
)
from .fit import (
    fit as fit,
)
from .fit import (
    fitted_outputs as fitted_outputs,
)
from .fit import (
    make_problem as make_problem,
)
from .fit import (
    predict as predict,
)
from .logs import Log as Log
from .logs import LogError as LogError
from .logs import load_log as load_log
from .run import (
    fit_experiment as fit_experiment,
)
from .run import (
    log_data as log_data,
)
from .run import (
    problem_from_experiment as problem_from_experiment,
)
from .run import (
    residual_report as residual_report,
)
from .synthetic import simulate_log as simulate_log
