"""Issue 61's last acceptance test: the diagnosis of a flexible-link servo rig's logs.

Simulated by an independent stick-slip simulation (tests/servo_rig_flexible.py, checked
against closed forms in tests/test_servo_rig_sim.py): a horizontal 0.45 m aluminium strip
with a 50 g tip mass (first clamped mode 2.35 Hz, 4.35 Hz on the free hub) on a 70:1
geared hub, dry friction 0.085 N m sliding and 0.10 N m breakaway that holds the hub
exactly still for about half of each log while the link keeps ringing, a digital PD +
tip-feedback controller whose torque is held over each 1 ms sample (declared `hold =
"zoh"`), a 4096-count motor encoder (`kind = "encoder"` with its `resolution`) and a
strain gauge calibrated to the tip deflection in 0.1 mm counts (`kind = "strain_gauge"`
with its `resolution`), wired reversed and declared `sign = -1`. Three 2.5 s logs, one
held out. The baseline model (hub inertia, joint damping and EI free) has no friction.

The claim: dry friction is named with its true sliding value inside its 95 % interval,
and no unphysical cause is named. Measured (2026-12-07, on 2 cores shared with other
jobs, load 7-10), with the guard alone, this module 58 min: 1 passed, 2 xfailed. Since the
round scored again after such a refit fits every promising candidate (no n_fit cut),
measured the same day (load about 4, 57.5 min): all 3 pass. Before that: the frictionless baseline ends
on its bounds (hub1.inertia 1.0 kg m^2, joint1.damping 1e-5 N m s/rad, link1.EI
10 N m^2, cost 1.092e12). Round 1's leader, actuator_lag:joint1, does not own its gain
(`identify/_diagnose/own_gain.py`): at its optimum with the lag at 0 s the baseline costs
6.005e11 (dBIC -5981 without a new parameter); the baseline is refitted from there (cost
6.058e10) and the round scored again, and nothing is named. Dry friction is not named:
the screening predicts it dBIC -3186 but ranks it 4th (n_fit=3; sensor_delay:theta1,
actuator_lag:joint1 and quadratic_damping:link1 fitted instead, dBIC -1923, -980, +9,
held-out gains 1.01x or less), and its pair with sensor_delay:theta1 (dBIC -5095)
predicts the held-out log worse (0.868x). Before the guard (46 min): an actuator lag of
1.6e-35 s named in round 1 (dBIC -5972, held-out gain 1.33x), then friction in round 2,
0.07502 N m, HAC interval [0.05894, 0.09549], in a wrong basin (EI 7.25 N m^2 against
0.388, cost 4.97e9), while baseline + friction fitted from the experiment's guesses
reaches cost 5.8e7 (EI 0.3875, friction 0.0866 N m).
"""

import pytest
from servo_rig_flexible import FlexibleServoRig, write_flexible_servo_experiment  # tests/ is on sys.path

import identify

TRUTH = FlexibleServoRig()

pytestmark = pytest.mark.slow  # 46-58 min on 2 loaded cores (the module docstring)


@pytest.fixture(scope="module")
def diagnosis(tmp_path_factory):
    path, _ = write_flexible_servo_experiment(tmp_path_factory.mktemp("flexible_servo"))
    return identify.diagnose(identify.load_experiment(path))


def test_dry_friction_is_named_without_warnings(diagnosis):
    """Friction is named; no named cause carries a warning; a high-pass on the encoder is
    not even tried (`kind = "encoder"`)."""
    labels = [f"{c.name}:{c.where}" for c in diagnosis.causes]
    assert "coulomb_friction:joint1" in labels, diagnosis.summary()
    assert all(not c.warnings for c in diagnosis.causes), diagnosis.summary()
    assert "sensor_highpass:theta1" in diagnosis.not_tried, diagnosis.not_tried


def test_no_unphysical_cause_is_named(diagnosis):
    """No sensor delay or actuator lag standing in for the held command, no high-pass on the
    gauge, no tilt of the horizontal rig."""
    labels = [f"{c.name}:{c.where}" for c in diagnosis.causes]
    assert not {"sensor_delay", "sensor_highpass", "actuator_lag", "base_tilt"} & set(diagnosis.named), labels


def test_dry_friction_interval_contains_the_truth(diagnosis):
    """The sliding friction's 95 % interval holds the simulation's 0.085 N m."""
    (cause,) = [c for c in diagnosis.causes if c.name == "coulomb_friction"]
    p = cause.parameters["joint1.coulomb"]
    lo, hi = p["ci95"]
    assert lo <= TRUTH.sliding_friction_n_m <= hi, p
