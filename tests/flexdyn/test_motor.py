"""DC motor drives (flexdyn.motor) against closed forms: the no-load speed per volt and the
stall torque, the mechanical time constant of a voltage step, a current amplifier running
into its voltage limit (piecewise closed form), the inductive motor against the matrix
exponential of its linear ODE and its electrical time constant L/R, the back-EMF damping of
the linearisation; and the energy balance of a saturating, braking, gravity-loaded run
(electrical power in = mechanical power + every loss), computed here with NumPy."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg

import flexdyn as fd
from flexdyn.chain import checked_chain

# A small lab drive: 2 ohm, 0.05 N m/A, 20:1 gear, rotor 1e-5 kg m^2 (4e-3 at the joint).
R, K, N, J_ROTOR = 2.0, 0.05, 20.0, 1e-5
LENGTH, MASS = 0.3, 0.2  # a uniform rigid rod about its end: m l^2 / 3
J_LINK = MASS * LENGTH**2 / 3.0
J_HUB = 1e-3


def _chain(motor, gravity=(0.0, 0.0), joint_damping=0.0):
    joint = fd.RigidJoint(damping=joint_damping, rotor_inertia=J_ROTOR, gear_ratio=N)
    return fd.Chain([fd.RigidLink(LENGTH, MASS)], [joint], [fd.Hub(inertia=J_HUB)], gravity=gravity, motors=[motor])


J_TOTAL = J_LINK + J_HUB + N**2 * J_ROTOR  # kg m^2 at the joint


def _run(chain, command, ts, y0=None, **options):
    y0 = fd.initial_state(chain, [0.0]) if y0 is None else y0
    return fd.simulate(chain, y0, jnp.asarray(ts), command, **options)


def test_voltage_step_speed_follows_the_mechanical_time_constant_to_the_no_load_speed():
    # J w' = eta N K (V - K N w) / R: w = V / (K N) (1 - exp(-t / tau_m)), tau_m = J R / (eta N^2 K^2)
    eta, V = 0.8, 6.0
    # (a smoothing speed far below the motion's: the efficiency is eta from the first instant)
    chain = _chain(fd.DCMotor(R, K, efficiency=eta, smoothing_velocity=1e-7))
    tau_m = J_TOTAL * R / (eta * N**2 * K**2)
    assert float(fd.motor.mechanical_time_constant(chain.motors[0], N, J_TOTAL)) == pytest.approx(tau_m, rel=1e-14)
    ts = np.linspace(0.0, 8 * tau_m, 41)
    traj = _run(chain, lambda t: jnp.array([V]), ts)
    expected = V / (K * N) * (1.0 - np.exp(-ts / tau_m))
    np.testing.assert_allclose(traj.Qd[:, 0], expected, rtol=1e-6, atol=1e-7 * V / (K * N))
    # observe's torque is the motor's torque on the joint, eta N K i, not its command (volts);
    # at rest (t = 0) the smoothed gear loses nothing: N K V / R
    torque = np.asarray(fd.observe(chain, traj, lambda t: jnp.array([V])).torque[:, 0])
    closed_form = eta * N * K * (V - K * N * expected) / R
    np.testing.assert_allclose(torque[1:], closed_form[1:], rtol=1e-6, atol=1e-7 * N * K * V / R)
    assert torque[0] == pytest.approx(N * K * V / R, rel=1e-12)
    # the speed per volt at no load, 1 / (K_b N), does not depend on the gear's efficiency
    assert traj.Qd[-1, 0] / V == pytest.approx(1.0 / (K * N) * (1 - math.exp(-8)), rel=1e-6)


def test_no_load_speed_with_the_motors_own_friction_referred_through_the_gear():
    # steady state: eta K (V - K N w) / R = b_m N w + c_m (tanh = 1 at this speed), w the joint rate
    eta, V, b_m, c_m = 0.9, 9.0, 2e-5, 4e-3
    chain = _chain(fd.DCMotor(R, K, efficiency=eta, viscous=b_m, coulomb=c_m))
    w = (eta * K * V / R - c_m) / (N * (eta * K**2 / R + b_m))
    tau = J_TOTAL / (N**2 * (eta * K**2 / R + b_m))
    traj = _run(chain, lambda t: jnp.array([V]), [0.0, 30 * tau])
    assert traj.Qd[-1, 0] == pytest.approx(w, rel=1e-7)


def test_torque_speed_line_stall_torque_and_the_braking_torque_of_a_back_driven_gear():
    # driving at speeds far above the smoothing speed, the torque is on the catalogue's
    # line eta N K (V - K N w) / R: intercept eta N K V / R (the stall torque), and zero at
    # the no-load speed V / (K N)
    eta, V = 0.7, 4.0
    chain = _chain(fd.DCMotor(R, K, efficiency=eta))
    asm = fd.assemble(chain)
    zero = jnp.zeros(1)
    for v in (V, -V):
        rates = np.sign(v) * np.array([0.2, 0.4, 0.6, 0.9]) * V / (K * N)  # between stall and no load
        torques = [J_TOTAL * float(fd.accelerations(asm, zero, jnp.array([r]), jnp.array([v]))[0]) for r in rates]
        slope, intercept = np.polyfit(rates, torques, 1)
        assert intercept == pytest.approx(eta * N * K * v / R, rel=1e-9)
        assert -intercept / slope == pytest.approx(v / (K * N), rel=1e-9)  # the no-load speed
    # at exactly zero speed the smoothed gear has no loss (as smoothed dry friction has none)
    torque = J_TOTAL * float(fd.accelerations(asm, zero, zero, jnp.array([V]))[0])
    assert torque == pytest.approx(N * K * V / R, rel=1e-12)
    # V = 0 at a joint rate far above the smoothing speed: the load drives the motor, whose
    # braking torque N K i reaches the joint divided by eta: -N^2 K^2 rate / (eta R)
    rate = 2.0
    torque = J_TOTAL * float(fd.accelerations(asm, zero, jnp.array([rate]), zero)[0])
    assert torque == pytest.approx(-(N**2) * K**2 * rate / (eta * R), rel=1e-12)


def test_back_emf_damping_of_the_linearisation_is_n2_kt_kb_over_r():
    # issue 61's physical floor: a voltage-driven joint at rest has damping N^2 K_t K_b / R
    damping = 3e-3
    chain = _chain(fd.DCMotor(R, K), joint_damping=damping)
    model = fd.linearize(chain)
    floor = float(fd.motor.back_emf_damping(chain.motors[0], N))
    assert floor == pytest.approx(N**2 * K**2 / R, rel=1e-14)
    assert -float(model.A[1, 1]) * J_TOTAL == pytest.approx(floor + damping, rel=1e-12)
    # and the input matrix: a volt at rest gives N K / R of torque (the smoothed gear loses nothing at rest)
    assert float(model.B[1, 0]) * J_TOTAL == pytest.approx(N * K / R, rel=1e-12)


@pytest.mark.parametrize("drive", ["current", "torque"])
def test_current_amplifier_accelerates_uniformly_until_its_voltage_limit_then_slows_to_the_no_load_speed(drive):
    # below the limit: J w' = eta N K i (uniform acceleration); the amplifier needs
    # R i + K N w, which reaches V_max at w_s = (V_max - R i) / (K N); from then on the
    # voltage is V_max and w -> V_max / (K N) with the time constant tau_m.
    eta, i_cmd, v_max = 0.85, 1.5, 12.0
    motor = fd.DCMotor(R, K, efficiency=eta, voltage_limit=v_max, drive=drive, smoothing_velocity=1e-7)
    chain = _chain(motor)
    command = i_cmd if drive == "current" else N * K * i_cmd  # a torque amplifier's command, N m
    accel = eta * N * K * i_cmd / J_TOTAL
    w_s = (v_max - R * i_cmd) / (K * N)
    t_s = w_s / accel
    w_inf, tau_m = v_max / (K * N), J_TOTAL * R / (eta * N**2 * K**2)
    ts = np.sort(np.concatenate([np.linspace(0.0, t_s, 6), np.linspace(t_s, t_s + 5 * tau_m, 11)[1:]]))
    traj = _run(chain, lambda t: jnp.array([command]), ts)
    expected = np.where(ts <= t_s, accel * ts, w_inf + (w_s - w_inf) * np.exp(-(ts - t_s) / tau_m))
    np.testing.assert_allclose(traj.Qd[:, 0], expected, rtol=1e-6, atol=1e-7 * w_inf)


def test_voltage_saturation_is_honoured():
    # a command of twice the limit runs at the limit's no-load speed, step response and all
    v_max = 5.0
    chain = _chain(fd.DCMotor(R, K, voltage_limit=v_max))
    tau_m = J_TOTAL * R / (N**2 * K**2)
    ts = np.linspace(0.0, 6 * tau_m, 13)
    traj = _run(chain, lambda t: jnp.array([2 * v_max]), ts)
    np.testing.assert_allclose(traj.Qd[:, 0], v_max / (K * N) * (1 - np.exp(-ts / tau_m)), rtol=1e-6, atol=1e-7)
    traj = _run(chain, lambda t: jnp.array([-3 * v_max]), ts)
    np.testing.assert_allclose(traj.Qd[:, 0], -v_max / (K * N) * (1 - np.exp(-ts / tau_m)), rtol=1e-6, atol=1e-7)


def test_inductive_motor_matches_the_matrix_exponential_of_its_linear_ode():
    # L i' = V - R i - K N w, J w' = N K i, charge' = i (eta = 1, no friction):
    # x' = A x + b V with x = [i, w, charge], exact by the matrix exponential
    L, V = 2e-3, 3.0
    chain = _chain(fd.DCMotor(R, K, inductance=L))
    assert chain.coordinate_names() == ["theta1", "charge1"]
    A = np.array([[-R / L, -K * N / L, 0.0], [N * K / J_TOTAL, 0.0, 0.0], [1.0, 0.0, 0.0]])
    b = np.array([1.0 / L, 0.0, 0.0])
    tau_e = L / R
    ts = np.linspace(0.0, 20 * tau_e, 41)
    traj = _run(chain, lambda t: jnp.array([V]), ts)
    augmented = np.block([[A, b[:, None] * V], [np.zeros((1, 4))]])  # [x; 1]' = [[A, b V], [0, 0]] [x; 1]
    exact = np.array([scipy.linalg.expm(augmented * t)[:3, 3] for t in ts])  # from x(0) = 0
    np.testing.assert_allclose(traj.Qd[:, 1], exact[:, 0], rtol=1e-6, atol=1e-7 * V / R)  # current, A
    np.testing.assert_allclose(traj.Qd[:, 0], exact[:, 1], rtol=1e-6, atol=1e-9)  # joint rate, rad/s
    np.testing.assert_allclose(traj.Q[:, 1], exact[:, 2], rtol=1e-6, atol=1e-12)  # charge, C


def test_electrical_time_constant_of_a_locked_rotor_is_l_over_r():
    # a load so heavy that the back-EMF stays negligible over a few L/R: i = V/R (1 - exp(-t R / L))
    L, V = 5e-3, 2.0
    joint = fd.RigidJoint(rotor_inertia=J_ROTOR, gear_ratio=N)
    chain = fd.Chain([fd.RigidLink(LENGTH, 1e6)], [joint], motors=[fd.DCMotor(R, K, inductance=L)])
    tau_e = L / R
    ts = np.linspace(0.0, 5 * tau_e, 11)
    traj = _run(chain, lambda t: jnp.array([V]), ts)
    np.testing.assert_allclose(traj.Qd[:, 1], V / R * (1 - np.exp(-ts / tau_e)), rtol=1e-6, atol=1e-9)
    k = int(np.argmin(np.abs(ts - tau_e)))
    assert traj.Qd[k, 1] / (V / R) == pytest.approx(1 - math.exp(-1), rel=1e-6)


def _efficiency_factor(eta, current, w, v_s):
    return eta ** np.tanh(np.sign(current) * w / v_s)


@pytest.mark.parametrize("inductance", [None, 1e-3])
def test_energy_balance_of_a_saturating_braking_pendulum_drive(inductance):
    # electrical energy in = change of (kinetic + gravity + magnetic) energy + the losses:
    # copper R i^2, gear (1 - e) N K i w_j, the motor's friction (b_m w + c_m tanh(w/v_s)) w,
    # the joint's viscous damping b_j w_j^2. Every term computed here from the state alone.
    eta, b_m, c_m, v_max, b_j, v_s = 0.75, 3e-5, 2e-3, 8.0, 2e-3, 0.3
    motor = fd.DCMotor(
        R,
        K,
        efficiency=eta,
        inductance=inductance,
        viscous=b_m,
        coulomb=c_m,
        voltage_limit=v_max,
        smoothing_velocity=v_s,
    )
    g = 9.81
    chain = _chain(motor, gravity=(0.0, -g), joint_damping=b_j)
    amplitude, f = 12.0, 1.5  # V, Hz: saturates at the peaks, reverses while the link still swings
    command = lambda t: jnp.array([amplitude * jnp.sin(2 * jnp.pi * f * t)])  # noqa: E731
    ts = np.linspace(0.0, 2.0, 40001)
    traj = _run(chain, command, ts, rtol=1e-11, atol=1e-12)
    theta, rate = np.asarray(traj.Q[:, 0]), np.asarray(traj.Qd[:, 0])
    volts = np.clip(amplitude * np.sin(2 * np.pi * f * ts), -v_max, v_max)
    w = N * rate  # motor shaft
    current = (volts - K * w) / R if inductance is None else np.asarray(traj.Qd[:, 1])
    e = _efficiency_factor(eta, current, w, v_s)
    power_in = volts * current
    losses = R * current**2 + (1 - e) * N * K * current * rate + (b_m * w + c_m * np.tanh(w / v_s)) * w + b_j * rate**2
    com = LENGTH / 2
    energy = 0.5 * J_TOTAL * rate**2 + MASS * g * com * np.sin(theta)
    if inductance is not None:
        energy = energy + 0.5 * inductance * current**2
    # the run is not a trivial one: it saturates, and the load back-drives the motor
    assert np.any(np.abs(amplitude * np.sin(2 * np.pi * f * ts)) > v_max)
    braking = current * rate < 0
    assert braking.mean() > 0.05
    # the gear never makes power
    assert np.all((1 - e) * N * K * current * rate >= -1e-15)
    work_in = scipy.integrate.simpson(power_in, x=ts)
    lost = scipy.integrate.simpson(losses, x=ts)
    assert abs(work_in - (energy[-1] - energy[0]) - lost) < 1e-6 * scipy.integrate.simpson(np.abs(power_in), x=ts)


@pytest.mark.slow  # (12 to 30 s on 2 cores, most of it compiling the reverse pass)
def test_gradient_of_the_speed_in_the_resistance_matches_finite_differences():
    V = 5.0
    ts = jnp.linspace(0.0, 0.05, 3)

    def speed(resistance):
        chain = _chain(fd.DCMotor(resistance, K, efficiency=0.9, viscous=1e-5))
        return fd.simulate(chain, fd.initial_state(chain, [0.0]), ts, lambda t: jnp.array([V])).Qd[-1, 0]

    h = 1e-5
    fdiff = (speed(R + h) - speed(R - h)) / (2 * h)
    assert float(jax.grad(speed)(jnp.asarray(R))) == pytest.approx(float(fdiff), rel=1e-6)


def test_named_motor_parameters():
    chain = _chain(fd.DCMotor(R, K, efficiency=0.9, coulomb=1e-3))
    names = fd.parameter_names(chain)
    for name in (
        "motor1.resistance",
        "motor1.torque_constant",
        "motor1.efficiency",
        "motor1.viscous",
        "motor1.coulomb",
    ):
        assert name in names
    assert "motor1.inductance" not in names and "motor1.voltage_limit" not in names
    assert fd.parameter_unit(chain, "motor1.resistance") == "ohm"
    changed = fd.with_parameters(chain, {"motor1.resistance": 3.0})
    assert float(fd.get_parameter(changed, "motor1.resistance")) == 3.0
    with pytest.raises(ValueError, match="motor1.inductance.*build it with DCMotor"):
        fd.get_parameter(chain, "motor1.inductance")
    bare = fd.Chain([fd.RigidLink(LENGTH, MASS)])
    with pytest.raises(ValueError, match="joint 1 has no motor"):
        fd.get_parameter(bare, "motor1.resistance")
    with pytest.raises(ValueError, match="efficiency"):
        fd.with_parameters(chain, {"motor1.efficiency": 1.2})


def test_bad_motors_are_named():
    with pytest.raises(ValueError, match="DCMotor.drive"):
        fd.DCMotor(R, K, drive="pwm")
    with pytest.raises(ValueError, match="DCMotor.inductance: a current amplifier"):
        fd.DCMotor(R, K, inductance=1e-3, drive="current")
    with pytest.raises(ValueError, match="DCMotor.efficiency"):
        fd.DCMotor(R, K, efficiency=1.5)
    with pytest.raises(ValueError, match="DCMotor.resistance"):
        fd.DCMotor(0.0, K)
    with pytest.raises(ValueError, match=r"Chain.motors: expected 1 entries"):
        fd.Chain([fd.RigidLink(LENGTH, MASS)], motors=[None, None])
    with pytest.raises(ValueError, match=r"Chain.motors\[0\]: expected DCMotor or None"):
        fd.Chain([fd.RigidLink(LENGTH, MASS)], motors=[fd.Hub()])
    # a traced efficiency above 1 is refused at run time
    chain = _chain(fd.DCMotor(R, K))

    @jax.jit
    def assembled(eta):
        return checked_chain(fd.with_parameters(chain, {"motor1.efficiency": eta})).motors[0].efficiency

    assert float(assembled(0.5)) == 0.5
    with pytest.raises(Exception, match="motor1.efficiency must be <= 1"):
        assembled(1.5)


def test_formulations_that_take_torques_refuse_motors():
    chain = _chain(fd.DCMotor(R, K))
    with pytest.raises(ValueError, match="not in the DeNOC formulation"):
        fd.denoc.denoc_accelerations(chain, jnp.zeros(1), jnp.zeros(1), jnp.zeros(1))
    with pytest.raises(ValueError, match="composite controller"):
        fd.control.rigid_embedding(chain)


def test_new_motor_values_do_not_retrace_a_jitted_simulation():
    # the motor's parameters are array leaves (drive, smoothing speed: static structure)
    ts = jnp.linspace(0.0, 0.02, 3)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def final_rate(chain):
        return fd.simulate(chain, fd.initial_state(chain, [0.0]), ts, lambda t: jnp.array([5.0])).Qd[-1, 0]

    base = _chain(fd.DCMotor(R, K, efficiency=0.9, coulomb=1e-3, voltage_limit=10.0))
    first = final_rate(base)
    names = ("motor1.resistance", "motor1.torque_constant", "motor1.efficiency", "motor1.coulomb")
    second = final_rate(fd.with_parameters(base, dict(zip(names, (3.0, 0.06, 0.8, 2e-3)))))
    assert float(first) != float(second)
