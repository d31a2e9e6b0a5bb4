"""Issue 60's hidden-effect grid in closed loop: `identify diagnose` on logs of the servo
pendulum under its digital PD controller (`tests/closed_loop_case.py`: the independent
DOP853 loop, the controller reading a noisy 16-bit potentiometer), each with one effect
the baseline model lacks. Every candidate is simulated in the loop: the law reads the
channel through the candidate's sensor delay, and the amplifier applies the command
through the candidate's lag.

Each must be named, alone, with the truth inside its 95 % interval; the same logs without
a hidden effect name nothing. The structural joint-elasticity candidate is left out
(`closed_loop_case.SLOW_STRUCTURAL` says why). Slow: a few minutes per diagnosis on 2
cores."""

from __future__ import annotations

import pytest
from closed_loop_case import diagnose_closed, noisy_logs  # tests/ is on sys.path

from identify._diagnose.notes import CLOSED_LOOP_NOTE

pytestmark = pytest.mark.slow

CASES = {
    # name: (the hidden effect, as `reference_loop` takes it; its parameter; the truth)
    "actuator_lag": (dict(lag=4e-3), "actuator1.lag", 4e-3),
    "sensor_delay": (dict(sensor_delay=3e-3), "sensor.theta1.delay", 3e-3),
    "coulomb_friction": (dict(coulomb=0.01), "joint1.coulomb", 0.01),
}


@pytest.mark.parametrize("name", list(CASES))
def test_a_hidden_effect_is_named_in_closed_loop(name):
    hidden, parameter, truth = CASES[name]
    diagnosis = diagnose_closed(noisy_logs(1, **hidden))
    assert diagnosis.named == [name], diagnosis.summary()
    lo, hi = diagnosis.causes[0].parameters[parameter]["ci95"]
    assert lo <= truth <= hi, diagnosis.causes[0].parameters


def test_closed_loop_logs_without_an_effect_name_nothing():
    """... and say that their intervals are the loop's (`identify fit` refits by the direct method)."""
    diagnosis = diagnose_closed(noisy_logs(1))
    assert diagnosis.named == [], diagnosis.summary()
    assert {"round": 0, "text": CLOSED_LOOP_NOTE} in diagnosis.notes, diagnosis.notes
