"""The full grid of hidden effects (slow; `pytest -m slow tests/identify/test_diagnose_grid.py`).

For every catalogue entry (on the rig of the papers it applies to, see
`tests/diagnose_cases.py`), a seeded random magnitude is hidden in the logs; `diagnose`
must name it (and nothing else), gain at least 2x in held-out RMS and bracket the truth with its 95 %
interval. Null logs must name nothing in at least 95 % of 20 seeded trials; two stacked
effects must both be named; the confusable pair sensor delay / actuator lag on the driven
arm must be told apart. `benchmarks/bench_diagnose_confusion.py` prints the confusion
matrix over more seeds.
"""

from __future__ import annotations

import pytest
from diagnose_cases import (
    ARM_ENTRIES,
    PENDULUM_ENTRIES,
    arm,
    arm_logs,
    diagnose_arm,
    diagnose_pendulum,
    hidden,
    pendulum,
    pendulum_logs,
)

from identify import measurement as meas

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("name", PENDULUM_ENTRIES + ARM_ENTRIES)
@pytest.mark.parametrize("seed", [1, 2])
def test_hidden_effect_is_named_and_recovered(name, seed):
    run, truth, param = hidden(name, seed)
    diag = run()
    # exactly this one: a second, spurious cause stacked on it is a false positive (seen
    # before the accepted model was refitted alone between rounds: sensor_highpass seed 2
    # named a calibration gain of 0.9999 as well)
    assert diag.named == [name], diag.summary()
    gains = diag.held_out["gain"]
    assert diag.held_out["gain_total"] >= 2.0 or max(gains.values()) >= 2.0, diag.summary()
    if param is not None:
        lo, hi = diag.causes[0].parameters[param]["ci95"]
        assert lo <= truth <= hi, (diag.causes[0].parameters, truth)


@pytest.mark.parametrize("rig", ["null_pendulum", "null_arm"])
def test_null_logs_name_no_cause_in_95_percent_of_trials(rig):
    trials = 20 if rig == "null_pendulum" else 10
    named = []
    for seed in range(trials):
        run, _, _ = hidden(rig, 100 + seed)
        diag = run()
        named.append(diag.named)
    false = sum(bool(n) for n in named)
    assert false <= int(0.05 * trials), named


def test_two_stacked_effects_are_both_named():
    m = meas.Measurement({"theta1": meas.Sensor(delay=0.03)})
    diag = diagnose_pendulum(pendulum_logs(pendulum(coulomb=1.2e-3), 7, m))
    assert sorted(diag.named) == ["coulomb_friction", "sensor_delay"], diag.summary()


def test_sensor_delay_and_actuator_lag_are_told_apart_on_the_driven_arm():
    for m, name in (
        (meas.Measurement({"theta1": meas.Sensor(delay=0.02), "tip1": meas.Sensor(delay=0.02)}), "sensor_delay"),
        (meas.Measurement(actuator_lag=[0.02]), "actuator_lag"),
    ):
        diag = diagnose_arm(arm_logs(arm(), 9, m))
        assert diag.named[:1] == [name], diag.summary()
        other = "actuator_lag" if name == "sensor_delay" else "sensor_delay"
        scores = {s.name: s for s in diag.rounds[0]}
        assert scores[other].delta_bic > scores[name].delta_bic + 10
