"""Motors in the experiment file: `[rig.motors.joint<i>]` puts a `flexdyn.DCMotor` on a
joint (its parameters named `motor<i>.<field>`, settable and fittable like the others), and
a log's `voltage<i>` / `current<i>` column drives it; the mismatches are named."""

import textwrap

import numpy as np
import pytest

import flexdyn as fd
import identify
from identify import ExperimentError, load_experiment


def _log(path, header):
    path.parent.mkdir(parents=True, exist_ok=True)
    t = np.arange(20) * 0.01
    rows = [",".join(header)] + [f"{s:.4f},{0.1 * k:.6f},{3.0 * np.sin(5 * s):.6f}" for k, s in enumerate(t)]
    path.write_text("\n".join(rows) + "\n")


def _experiment(tmp_path, motor, column, header=("time [s]", "angle [rad]", "u [V]")):
    _log(tmp_path / "logs" / "run.csv", header)
    path = tmp_path / "exp.toml"
    path.write_text(
        textwrap.dedent(
            f"""
            [rig]
            base = "rigid_pendulum"

            [rig.motors.joint1]
            {motor}

            [rig.set]
            "joint1.gear_ratio" = 20.0
            "motor1.resistance" = 2.5

            [parameters]
            "motor1.torque_constant" = {{ guess = 0.04, lower = 0.01, upper = 0.2 }}

            [[logs]]
            file = "logs/run.csv"
            columns = {{ time = "time [s]", theta1 = "angle [rad]", {column} = "{header[2]}" }}
            """
        )
    )
    return path


def test_a_voltage_driven_motor_from_the_experiment_file(tmp_path):
    path = _experiment(
        tmp_path, "resistance = 2.0\ntorque_constant = 0.05\nefficiency = 0.9\nvoltage_limit = 12.0", "voltage1"
    )
    exp = load_experiment(path)
    motor = exp.chain.motors[0]
    assert isinstance(motor, fd.DCMotor) and motor.drive == "voltage"
    assert float(motor.resistance) == 2.5  # rig.set applies to the motor's parameters too
    assert float(motor.torque_constant) == 0.05 and float(motor.efficiency) == 0.9
    assert float(motor.voltage_limit) == 12.0 and motor.inductance is None
    assert [p.name for p in exp.free] == ["motor1.torque_constant"]
    log = exp.logs[0].log
    t = np.arange(20) * 0.01
    np.testing.assert_allclose(log.torque(1)[:, 0], 3.0 * np.sin(5 * t), atol=1e-6)  # volts, as recorded
    # and the fit's problem: the motor's parameter free, the volts its logs' input
    problem = identify.problem_from_experiment(exp)
    assert tuple(problem.names) == ("motor1.torque_constant",)
    np.testing.assert_allclose(np.asarray(problem.torque_v)[0, :, 0], 3.0 * np.sin(5 * t), atol=1e-6)


def test_a_current_amplifier_reads_amperes(tmp_path):
    path = _experiment(
        tmp_path,
        'resistance = 2.0\ntorque_constant = 0.05\ndrive = "current"',
        "current1",
        ("time [s]", "angle [rad]", "i [mA]"),
    )
    exp = load_experiment(path)
    assert exp.chain.motors[0].drive == "current"
    t = np.arange(20) * 0.01
    np.testing.assert_allclose(exp.logs[0].log.torque(1)[:, 0], 3e-3 * np.sin(5 * t), atol=1e-9)  # A


@pytest.mark.parametrize(
    "motor, column, message",
    [
        ("resistance = 2.0\ntorque_constant = 0.05", "torque1", "joint 1's motor is driven by voltage"),
        ('resistance = 2.0\ntorque_constant = 0.05\ndrive = "pwm"', "voltage1", 'expected one of "voltage" (V)'),
        ("resistance = 2.0", "voltage1", "DCMotor needs torque_constant"),
        ("resistance = 2.0\ntorque_constant = 0.05\nefficiency = 1.2", "voltage1", "efficiency"),
        (
            'resistance = 2.0\ntorque_constant = 0.05\ninductance = 1e-3\ndrive = "current"',
            "current1",
            "a current amplifier holds the current itself",
        ),
    ],
)
def test_motor_mistakes_are_named(tmp_path, motor, column, message):
    header = ("time [s]", "angle [rad]", "u [N m]" if column == "torque1" else "u [V]")
    if column == "current1":
        header = ("time [s]", "angle [rad]", "u [A]")
    with pytest.raises(ExperimentError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_experiment(_experiment(tmp_path, motor, column, header))


def test_a_voltage_column_on_a_joint_without_a_motor_is_named(tmp_path):
    _log(tmp_path / "logs" / "run.csv", ("time [s]", "angle [rad]", "u [V]"))
    path = tmp_path / "exp.toml"
    path.write_text(
        textwrap.dedent(
            """
            [rig]
            base = "rigid_pendulum"

            [parameters]
            "joint1.damping" = { guess = 1e-3 }

            [[logs]]
            file = "logs/run.csv"
            columns = { time = "time [s]", theta1 = "angle [rad]", voltage1 = "u [V]" }
            """
        )
    )
    with pytest.raises(ExperimentError, match=r"joint 1 has no motor.*\[rig.motors.joint1\]"):
        load_experiment(path)


def test_an_inductive_motors_current_is_a_state_a_log_may_start_from(tmp_path):
    path = _experiment(tmp_path, "resistance = 2.0\ntorque_constant = 0.05\ninductance = 1e-3", "voltage1")
    text = path.read_text().replace('"u [V]" }', '"u [V]" }\ninitial = { charge1_rate = 0.2 }')
    path.write_text(text)
    exp = load_experiment(path)
    assert exp.chain.coordinate_names() == ["theta1", "charge1"]
    assert exp.logs[0].initial["charge1_rate"] == 0.2  # A
    data = identify.log_data(exp.logs[0], 1)
    assert data.initial["charge1_rate"] == 0.2
