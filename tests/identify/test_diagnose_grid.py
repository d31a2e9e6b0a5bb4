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

import math

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

from identify._data import measurement as meas

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


def test_a_calibration_error_is_found_after_a_structural_change():
    """An elastic joint (40 N m/rad) and a 5 % strain-gauge gain error on the tip channel,
    hidden together in the driven arm's logs. The elastic joint wins the first round (a
    structural change: a model of its own); the search then goes on from that model as a
    new baseline and names the calibration error. Measured 2026-11-25: round 1
    joint_elasticity dBIC -3116 (the gain error -395); from the elastic model the tip gain
    dBIC -2034; stiffness 40.04 [39.98, 40.11] N m/rad, gain 1.050 [1.048, 1.052]."""
    m = meas.Measurement({"tip1": meas.Sensor(gain=1.05)})
    diag = diagnose_arm(arm_logs(arm(elastic=(40.0, 0.01, None)), 5, m))
    assert diag.named == ["joint_elasticity", "sensor_gain_offset"], diag.summary()
    assert diag.causes[1].where == "tip1"
    # found from the structural model: the elastic joint is not a candidate there
    assert all(s.label != "joint_elasticity:joint1" for scores in diag.rounds[1:] for s in scores)
    # backlash needs an elastic joint: not applicable to the rigid baseline, tried on the
    # elastic model, so not among the entries the stacked search never tried
    assert any(s.name == "backlash" for scores in diag.rounds[1:] for s in scores)
    assert "backlash" not in diag.not_tried and "joint_elasticity" not in diag.not_tried, diag.not_tried
    for cause, name, truth in (
        (0, "joint1.stiffness", 40.0),
        (0, "joint1.rotor_inertia", 0.01),
        (1, "sensor.tip1.gain", 1.05),
    ):
        lo, hi = diag.causes[cause].parameters[name]["ci95"]
        assert lo <= truth <= hi, (name, diag.causes[cause].parameters[name])
    # the extended model holds both
    assert diag.extended_chain.joints[0].elastic
    gain = float(meas.get_parameter(diag.extended_measurement, "sensor.tip1.gain"))
    assert gain == pytest.approx(diag.extended_parameters["sensor.tip1.gain"])
    assert diag.held_out["gain_total"] >= 2.0, diag.summary()


def test_a_joint_elasticity_masked_by_a_large_tilt_is_found_after_it():
    """A 1.5 deg base tilt and an elastic joint (40 N m/rad). From the rigid, level
    baseline (cost 4.7e7 over 2404 residuals) the tilt dominates and elasticity's fit
    looks insignificant (dBIC +10: it takes 1.1e5 off, a small fraction); once the tilt is
    accepted that drop is most of what is left, so the structural candidate must be
    refitted. Before this was decided on the absolute cost drop, elasticity was not
    refitted and the search ended at cost 16067 (6.7x the noise) naming the tilt only."""
    tilt, az = math.radians(1.5), 1.0
    g = (9.81 * math.sin(tilt) * math.cos(az), 9.81 * math.sin(tilt) * math.sin(az))
    diag = diagnose_arm(arm_logs(arm(gravity=g, elastic=(40.0, 0.01, None)), 5))
    assert diag.named == ["base_tilt", "joint_elasticity"], diag.summary()
    lo, hi = diag.causes[1].parameters["joint1.stiffness"]["ci95"]
    assert lo <= 40.0 <= hi, diag.causes[1].parameters
    for i in (0, 1):
        lo, hi = diag.causes[0].parameters[f"gravity[{i}]"]["ci95"]
        assert lo <= g[i] <= hi, (g, diag.causes[0].parameters)


def test_two_missing_modes_are_found_one_after_the_other():
    """The arm's link has three modes; the baseline one. A quieter root strain gauge (5e-5
    1/m) sees the third mode (the second changes the root curvature by ~40x the noise, the
    third by 0.3-0.6x on the fitted logs, the fourth by a quarter of that). The second mode
    wins round 1 (a structural change); from the two-mode model the search offers one more
    mode on the same link, which wins round 2; the three-mode model (the truth) is at the
    noise on the held-out logs, so a fourth is not tried (`diagnose.held_out_headroom`).
    Measured 2026-11-25 (seed 1, 5 min): round 2 missing_mode dBIC -2375, held-out gain
    1.46x; round 3 (tried then) missing_mode dBIC +240; total held-out gain 11.4x
    (curvature 15.6x)."""
    noise = {"curvature1": 5e-5}
    logs = arm_logs(arm(n_modes=3), 1, channels=("theta1", "curvature1"), noise=noise)
    diag = diagnose_arm(logs, noise=noise)
    assert diag.named == ["missing_mode", "missing_mode"], diag.summary()
    assert diag.extended_chain.links[0].n_modes == 3
    # from the three-mode model the fourth is not tried: its held-out residual is white at
    # its noise floor, and the notes say so (before, it was tried and rejected: dBIC +240)
    assert "missing_mode:link1" not in {s.label for s in diag.rounds[-1]}
    assert [(n["round"], n["text"].split(" not refitted")[0]) for n in diag.notes[1:]] == [(3, "missing_mode:link1")]
    # round 1's elastic joint, fitted to an arm whose joint is rigid, ends far above the
    # rigid model it holds as a limit (measured: cost 767443 against 520802): a local
    # minimum, and the first note says so (`diagnose._stuck_above_nested`)
    first = diag.notes[0]
    assert first["round"] == 1 and first["text"].startswith("joint_elasticity:joint1: its fit ended above"), first
    assert diag.held_out["gain"]["curvature1"] >= 2.0, diag.summary()
