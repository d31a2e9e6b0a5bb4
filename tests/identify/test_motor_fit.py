"""A rig whose joint is driven by a DC motor through its voltage: a fit of a simulated,
noisy, voltage-driven log recovers the motor's resistance and torque constant within their
intervals (the log's input column is the voltage: `LogData.torque` carries each joint's
input, read by the motor as its command)."""

import numpy as np
import pytest

import flexdyn as fd
import identify

R_TRUE, K_TRUE, N = 2.4, 0.045, 15.0


def _pendulum(resistance, torque_constant):
    motor = fd.DCMotor(resistance, torque_constant, efficiency=0.9, voltage_limit=8.0)
    joint = fd.RigidJoint(damping=1e-3, rotor_inertia=1e-5, gear_ratio=N)
    return fd.Chain([fd.RigidLink(0.3, 0.2)], [joint], [fd.Hub(inertia=1e-3)], gravity=(0.0, -9.81), motors=[motor])


@pytest.mark.slow
def test_fit_of_a_voltage_driven_log_recovers_the_resistance_and_torque_constant():
    t = np.arange(400) * 5e-3  # 2 s at 200 Hz; the voltage peaks at 9 V: it saturates at 8 V
    volts = 6.0 * np.sin(2 * np.pi * 0.8 * t) + 3.0 * np.sign(np.sin(2 * np.pi * 2.1 * t))
    log = identify.simulate_log(
        _pendulum(R_TRUE, K_TRUE),
        t,
        initial={"theta1": -np.pi / 2},
        torque=volts[:, None],
        channels=("theta1",),
        noise={"theta1": 2e-4},
        rng=np.random.default_rng(7),
        name="volts",
    )
    params = [
        identify.Parameter("motor1.resistance", 3.0, 0.5, 10.0),
        identify.Parameter("motor1.torque_constant", 0.06, 0.01, 0.2),
    ]
    problem = identify.make_problem(_pendulum(3.0, 0.06), params, [log], {"theta1": 2e-4})
    result = identify.fit(problem, n_starts=1)
    for k, (name, truth) in enumerate((("motor1.resistance", R_TRUE), ("motor1.torque_constant", K_TRUE))):
        value, se = result.value[name], result.std_errors[k]
        assert abs(value - truth) < 3 * se, (name, value, se, truth)
        assert se < 0.05 * truth, (name, se)
    # the summary reports the back-EMF damping floor at the fitted values (issue 61)
    r, k = result.value["motor1.resistance"], result.value["motor1.torque_constant"]
    assert f"joint1: back-EMF damping N^2 K_t^2 / R = {N**2 * k**2 / r:.4g} N m s/rad" in result.summary()
