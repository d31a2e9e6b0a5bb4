"""The shipped example `identify/examples/servo_flexible_link` (issue 60, item 6): a
servo-driven flexible link under its digital controller, fitted closed loop.

The logs were written by the example's `make_logs.py` (a tick-by-tick loop over
`flexdyn.simulate`, independent of `identify`'s closed-loop model) from the truth below.
`identify fit` must hold the truth inside every 95 % interval; `identify diagnose` on the
experiment without the gear friction must name it. Slow (minutes each on 2 cores)."""

from __future__ import annotations

from pathlib import Path

import pytest
from example_scripts import make_logs_module  # tests/ is on sys.path

import identify

EXAMPLE = Path(identify.__file__).resolve().parent / "examples" / "servo_flexible_link"


def _truth() -> dict:
    return make_logs_module("servo_flexible_link").TRUTH


def test_the_example_loads_and_declares_its_controller():
    """The experiment file reads: three closed-loop logs, the gauge's sign reversed, the
    controller's law as the README writes it."""
    exp = identify.load_experiment(EXAMPLE / "experiment.toml")
    assert exp.controller is not None and exp.controller.command == "voltage1"
    assert exp.controller.gains == {"theta1": 10.0, "tip1": -40.0}
    assert [s.name for s in exp.fit_logs] == ["step_a", "step_b"]
    assert [s.name for s in exp.validation_logs] == ["step_c"]
    for spec in exp.fit_logs + exp.validation_logs:
        assert spec.log.references and set(spec.log.outputs) == {"theta1", "tip1"}


@pytest.mark.slow
def test_the_fit_holds_the_truth_in_its_intervals():
    """The closed-loop fit, then the direct method from its optimum (`identify fit`'s
    default). Measured 2026-12-08 (2 cores, load 2): passed in 206 s. Measured 2026-12-07,
    closed loop only (2 cores, load 8): 711 s; each parameter within 2.3 standard errors."""
    result = identify.fit_experiment(identify.load_experiment(EXAMPLE / "experiment.toml"))
    assert result.converged
    for k, name in enumerate(result.names):
        truth = _truth()[name]
        assert result.ci_low[k] <= truth <= result.ci_high[k], (name, result.value[name], result.std_errors[k])


@pytest.fixture(scope="module")
def diagnosis():
    return identify.diagnose(identify.load_experiment(EXAMPLE / "experiment_no_friction.toml"))


@pytest.mark.slow
def test_diagnose_names_the_gear_friction_left_out_of_the_model(diagnosis):
    """Measured 2026-12-07 (2 cores, load 7-9): 43 min; friction named in round 1 (dBIC
    -114224, held-out gain 568x), nothing else."""
    assert diagnosis.named == ["coulomb_friction"], diagnosis.summary()


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason=(
        "measured 2026-12-07: joint1.coulomb 0.0299959 N m, SE 5.2e-7, 95 % CI [0.0299949, 0.0299969]: the truth "
        "0.03 is 8 SE above it. The logs' only noise is the sensors' quantisation, so the SE is 1.7e-5 of the value, "
        "below the bias of the search's fixed integration step (0.167 ms) on the friction's sharp smoothed switch; "
        "identify fit of experiment.toml (friction free from the start) holds it: 0.0299985, CI [0.0299973, 0.0299998]"
    ),
)
def test_diagnose_interval_of_the_friction_holds_the_truth(diagnosis):
    lo, hi = diagnosis.causes[0].parameters["joint1.coulomb"]["ci95"]
    assert lo <= _truth()["joint1.coulomb"] <= hi, diagnosis.causes[0].parameters
