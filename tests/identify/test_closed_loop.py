"""Closed-loop logs (issue 60, item 3): the rig simulated under its digital controller
inside the residual, against an independent discrete-time simulation of the same loop
(`tests/closed_loop_case.py`: SciPy's DOP853 on the pendulum's own equation of motion,
restarted at each tick with the held, clipped command of a PD on the quantised encoder)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from closed_loop_case import (
    CONTROLLER_TOML,
    ENCODER,
    ENCODER_ZERO,
    LIMIT,
    PERIOD,
    RIG_TOML,
    TRUTH,
    closed_loop_log,
    controller,
    measurement,
    pendulum,
    reference,
    reference_loop,
)

import identify


@pytest.mark.parametrize("delay, quantise", [(False, True), (True, True), (False, False)])
def test_the_closed_loop_prediction_matches_an_independent_discrete_time_loop(delay, quantise):
    """A PD step response of the motor-driven pendulum at 1 kHz for 1.2 s (the command
    saturates after each step: the oracle checks it does), the controller reading the
    encoder's counts (`quantise`) or its unrounded value: the model's hub angle and
    commands agree with the oracle's to 1e-6 (rad, V)."""
    t = np.arange(1201) * PERIOD
    resolution = ENCODER if quantise else None
    theta, _, volts, _ = reference_loop(t, -0.3, reference(t), delay, resolution=resolution)
    assert np.sum(np.abs(volts) == LIMIT) > 20
    assert abs(theta[-1] - (-0.1)) < 0.05  # it settles near the last reference
    problem = identify.make_problem(
        pendulum(),
        [],
        [closed_loop_log(t, -0.3, "step", delay, resolution=resolution)],
        {"theta1": 1e-3, "voltage1": 1e-2},
        measurement=measurement(),
        controller=controller(delay, quantise),
    )
    assert problem.channels == ("theta1", "voltage1")
    pred, ok = identify.predict(problem, jnp.zeros(0), problem.y0_known)
    assert bool(ok[0])
    np.testing.assert_allclose(np.asarray(pred[0, :, 0]), theta + ENCODER_ZERO, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(pred[0, :, 1]), volts, rtol=0, atol=1e-6)


@pytest.mark.parametrize(
    "lag, sensor_delay, highpass_hz",
    [(4e-3, 0.0, 0.0), (0.0, 2.5e-3, 0.0), (3e-3, 0.7e-3, 0.0), (0.0, 0.0, 0.5)],
    ids=["lag", "delay", "lag-and-delay", "highpass"],
)
def test_the_loop_through_a_lag_a_delay_or_a_high_pass_matches_the_independent_loop(lag, sensor_delay, highpass_hz):
    """The amplifier's first-order lag (an extra state in the oracle's ODE), the encoder's
    delay (the oracle reads its own dense output that long before each tick; 2.5 ms spans
    two and a half periods) and a first-order 0.5 Hz high-pass on the angle the
    controller reads (an AC-coupled sensor; the oracle integrates the filter of the angle
    read linearly between ticks): the model's recorded angle and its commands agree with
    the oracle's to 1e-6 (rad, V), and each effect moves them by far more than that."""
    t = np.arange(601) * PERIOD
    ref = reference(t)
    effects = {"lag": lag, "sensor_delay": sensor_delay, "highpass_hz": highpass_hz}
    _, _, volts, readings = reference_loop(t, -0.3, ref, resolution=None, **effects)
    _, _, plain_volts, plain_readings = reference_loop(t, -0.3, ref, resolution=None)
    assert max(np.max(np.abs(volts - plain_volts)), np.max(np.abs(readings - plain_readings))) > 0.01
    sensor = identify.Sensor(offset=ENCODER_ZERO, delay=sensor_delay or None, highpass=highpass_hz or None)
    log = identify.LogData(
        t=t,
        outputs={"theta1": readings},
        torque=volts[:, None],
        initial={"theta1": -0.3},
        name="step",
        hold="zoh",
        reference={"theta1": ref},
    )
    problem = identify.make_problem(
        pendulum(),
        [],
        [log],
        {"theta1": 1e-3, "voltage1": 1e-2},
        measurement=identify.Measurement({"theta1": sensor}, actuator_lag=(lag or None,)),
        controller=controller(quantise=False),
    )
    pred, ok = identify.predict(problem, jnp.zeros(0), problem.y0_known)
    assert bool(ok[0])
    np.testing.assert_allclose(np.asarray(pred[0, :, 0]), readings, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(pred[0, :, 1]), volts, rtol=0, atol=1e-6)


def test_a_sensor_delay_beyond_the_loops_history_fails_the_solve():
    """A delayed reading needs the samples it falls between; one older than the
    `LOOP_HISTORY` intervals the loop keeps is a failed solve, not a silent hold."""
    from identify._model.closed_loop import LOOP_HISTORY

    t = np.arange(200) * PERIOD
    log = closed_loop_log(t, -0.3, "step")
    far = identify.Measurement({"theta1": identify.Sensor(offset=ENCODER_ZERO, delay=(LOOP_HISTORY + 2) * PERIOD)})
    near = identify.Measurement({"theta1": identify.Sensor(offset=ENCODER_ZERO, delay=(LOOP_HISTORY - 2) * PERIOD)})
    for m, expected in ((far, False), (near, True)):
        problem = identify.make_problem(pendulum(), [], [log], measurement=m, controller=controller())
        _, ok = identify.predict(problem, jnp.zeros(0), problem.y0_known)
        assert bool(ok[0]) is expected


# ---------------------------------------------------------------------------
# The experiment file's [controller]
# ---------------------------------------------------------------------------

_CONTROLLER = CONTROLLER_TOML


def _write_case(tmp_path, controller=None, columns=None, extra="", samples=300):
    """An experiment file with one closed-loop log written from the oracle's loop (angles
    in degrees): `(path, theta, volts)`."""
    from closed_loop_case import KD, KP, V_FF

    t = np.arange(samples) * PERIOD
    ref = reference(t)
    theta, _, volts, recorded = reference_loop(t, -0.3, ref)
    rows = ["time [s],enc [deg],ref [deg],u [V]"] + [
        f"{a:.17g},{np.degrees(b):.17g},{np.degrees(c):.17g},{d:.17g}" for a, b, c, d in zip(t, recorded, ref, volts)
    ]
    (tmp_path / "run.csv").write_text("\n".join(rows) + "\n")
    if controller is None:
        controller = _CONTROLLER.format(kp=KP, kd=KD, ff=V_FF, limit=LIMIT)
    if columns is None:
        columns = 'time = "time [s]", theta1 = "enc [deg]", theta1_ref = "ref [deg]", voltage1 = "u [V]"'
    text = (
        RIG_TOML.format(resolution=ENCODER)
        + controller
        + extra
        + f'\n[[logs]]\nfile = "run.csv"\ncolumns = {{ {columns} }}\nhold = "zoh"\ninitial = {{ theta1 = -0.3 }}\n'
    )
    path = tmp_path / "exp.toml"
    path.write_text(text)
    return path, theta, volts


def test_an_experiment_file_declares_the_controller_and_its_logs_are_simulated_closed_loop(tmp_path):
    """The file's [controller] and the log's theta1_ref column (in degrees) give the same
    closed-loop prediction as the oracle's loop, to 1e-6."""
    path, theta, volts = _write_case(tmp_path)
    exp = identify.load_experiment(path)
    assert exp.controller == controller()
    assert set(exp.logs[0].log.references) == {"theta1"}
    assert (
        "controller: voltage1 = clip(0.5 + 20 (theta1_ref - theta1) - 0.3 d(theta1)/dt, +-6), every 0.001 s "
        "(zero-order hold, rates by backward difference, quantised readings)" in exp.summary()
    )
    problem = identify.problem_from_experiment(exp)
    assert problem.channels == ("theta1", "voltage1")
    pred, ok = identify.predict(problem, jnp.zeros(0), problem.y0_known)
    assert bool(ok[0])
    np.testing.assert_allclose(np.asarray(pred[0, :, 0]), theta + ENCODER_ZERO, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(pred[0, :, 1]), volts, rtol=0, atol=1e-6)


def test_the_commands_noise_level_may_be_declared(tmp_path):
    """[noise] takes the command channel of [controller] (in its unit), and the problem
    weighs the command by it; without [controller], voltage1 is not an output there."""
    path, _, _ = _write_case(tmp_path, extra='\n[noise]\nvoltage1 = "20 mV"\ntheta1 = "0.05 deg"\n', samples=30)
    exp = identify.load_experiment(path)
    assert exp.noise["voltage1"] == pytest.approx(0.02)
    problem = identify.problem_from_experiment(exp)
    assert float(problem.sigma[problem.channels.index("voltage1")]) == pytest.approx(0.02)
    assert "voltage1" in problem.declared
    columns = 'time = "time [s]", theta1 = "enc [deg]", voltage1 = "u [V]"'
    path, _, _ = _write_case(tmp_path, "", columns, '\n[noise]\nvoltage1 = "20 mV"\n', samples=30)
    with pytest.raises(identify.ExperimentError, match=r"noise\.voltage1: not an output channel"):
        identify.load_experiment(path)


_BASE = dict(kp=20.0, kd=0.3, ff=0.5, limit=6.0)


@pytest.mark.parametrize(
    "controller, columns, extra, match",
    [
        ("\n[controller]\ngains = { theta1 = 1.0 }\n", None, "", r"controller: missing command"),
        (_CONTROLLER.format(**_BASE).replace('"voltage1"', '"theta1"'), None, "", r"controller\.command.*not an input"),
        (_CONTROLLER.format(**_BASE).replace('"voltage1"', '"torque1"'), None, "", r"controller\.command.*voltage"),
        (
            _CONTROLLER.format(**_BASE).replace("gains = { theta1", "gains = { accel_x"),
            None,
            "",
            r"controller\.gains\.accel_x.*not a channel a controller reads",
        ),
        (
            _CONTROLLER.format(**_BASE).replace("gains = { theta1", "gains = { tip1"),
            None,
            "",
            r"controller\.gains\.tip1.*rigid",
        ),
        (
            _CONTROLLER.format(**_BASE).replace("gains = { theta1 = 20.0", 'gains = { theta1 = "20 V/rad"'),
            None,
            "",
            r"controller\.gains\.theta1.*expected a number in SI units \(V per SI unit",
        ),
        (
            _CONTROLLER.format(**_BASE).replace('references = ["theta1"]', 'references = ["tip1"]'),
            None,
            "",
            r"controller\.references.*'tip1' has no entry in gains",
        ),
        (
            _CONTROLLER.format(**_BASE).replace('limit = "6.0 V"', 'limit = "-1 V"'),
            None,
            "",
            r"controller\.limit.*saturation > 0",
        ),
        (
            _CONTROLLER.format(**_BASE).replace('limit = "6.0 V"', 'limit = "6 N m"'),
            None,
            "",
            r"controller\.limit.*expected a voltage",
        ),
        (_CONTROLLER.format(**_BASE) + "delay = 1\n", None, "", r"controller\.delay.*expected true"),
        (_CONTROLLER.format(**_BASE).replace("quantise = true", 'quantise = "yes"'), None, "", r"controller\.quantise"),
        (_CONTROLLER.format(**_BASE) + "gain = 1\n", None, "", r"controller\.gain: unknown key"),
        (
            _CONTROLLER.format(**_BASE).replace('"1 ms"', '"2 ms"'),
            None,
            "",
            r"controller\.period.*sampled every 0\.001 s.*period is 0\.002 s",
        ),
        (
            _CONTROLLER.format(**_BASE),
            'time = "time [s]", theta1 = "enc [deg]", theta1_ref = "ref [deg]"',
            "",
            r"logs\[1\]\.columns.*no voltage1 column",
        ),
        (
            _CONTROLLER.format(**_BASE),
            'time = "time [s]", theta1 = "enc [deg]", voltage1 = "u [V]"',
            "",
            r"logs\[1\]\.columns.*no theta1_ref column",
        ),
        ("", None, "", r"logs\[1\]\.columns.*theta1's\), but the file has no \[controller\]"),
    ],
)
def test_a_bad_controller_section_is_named(tmp_path, controller, columns, extra, match):
    path, _, _ = _write_case(tmp_path, controller, columns, extra, samples=20)
    with pytest.raises(identify.ExperimentError, match=match):
        identify.load_experiment(path)


def test_a_per_log_offset_on_a_channel_the_controller_reads_is_refused(tmp_path):
    path, _, _ = _write_case(tmp_path, samples=20)
    path.write_text(path.read_text() + 'offsets = ["theta1"]\n')
    with pytest.raises(
        identify.ExperimentError, match=r"logs\[1\]\.offsets.*read by \[controller\].*sensor\.theta1\.offset"
    ):
        identify.load_experiment(path)


def test_what_a_closed_loop_problem_cannot_hold_is_named():
    t = np.arange(50) * PERIOD
    log = closed_loop_log(t, -0.3, "step")
    no_ref = dataclasses.replace(log, reference={})
    with pytest.raises(ValueError, match=r"log 'step': no reference for theta1 \(theta1_ref\)"):
        identify.make_problem(pendulum(), [], [no_ref], controller=controller())
    offset = dataclasses.replace(log, offsets=("theta1",))
    with pytest.raises(ValueError, match=r"log 'step': offsets for \['theta1'\], which the controller reads"):
        identify.make_problem(pendulum(), [], [offset], controller=controller())
    with pytest.raises(ValueError, match=r"log 'step' has a reference, but no controller was given"):
        identify.make_problem(pendulum(), [], [log])
    with pytest.raises(ValueError, match=r"controller\.command 'voltage2'"):
        identify.make_problem(pendulum(), [], [log], controller=identify.Controller("voltage2", {"theta1": 1.0}))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(command="theta1", gains={"theta1": 1.0}), r"Controller\.command: expected the input channel"),
        (dict(command="voltage1", gains={"accel_x": 1.0}), r"Controller\.gains: 'accel_x' is not a channel"),
        (dict(command="voltage1", gains={"theta1": float("nan")}), r"Controller\.gains\['theta1'\]: expected a finite"),
        (dict(command="voltage1"), r"Controller: no gains"),
        (dict(command="voltage1", gains={"theta1": 1.0}, limit=0.0), r"Controller\.limit"),
        (dict(command="voltage1", gains={"theta1": 1.0}, period=-1e-3), r"Controller\.period"),
        (dict(command="voltage1", gains={"theta1": 1.0}, quantise=1), r"Controller\.quantise"),
        (dict(command="voltage1", rate_gains={"theta1": 1.0}, references=("theta1",)), r"Controller\.references"),
    ],
)
def test_a_bad_controller_is_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        identify.Controller(**kwargs)


# ---------------------------------------------------------------------------
# A fit of closed-loop logs, and the open-loop replay of the same logs
# ---------------------------------------------------------------------------

ADC = 2 * np.pi / 65536  # rad: a potentiometer read by a 16-bit converter over one turn
READING_NOISE = 3e-4  # rad, the potentiometer's analog noise, read by the controller too


@pytest.mark.slow
def test_a_fit_of_closed_loop_logs_recovers_the_motor_and_hub():
    """Two 0.8 s logs of the servo pendulum at 1 kHz (the oracle's loop; the controller
    reads a noisy 16-bit angle and its rate by backward difference, so its commands carry
    that noise), fitted from guesses 25-100 % off: closed loop, the motor's resistance and
    torque constant and the hub's inertia come out with the truth inside their 95 %
    intervals and the angle's residual at its noise floor.

    The same logs replayed open loop (the logged command as the input, held as the
    controller held it) recover them as well on logs this short (measured 2026-12-07:
    residual 1.02x the floor, every parameter within 1.1 standard errors). An earlier
    version of this test measured the replay 8x above the floor and asserted it; the change
    that closed the gap was not traced. The drift of an open-loop replay that issue 60
    describes is a long log's with model error, not these logs'.

    The limit is declared but not reached here: with the noise in the loop, a saturating
    command's mean is not the clip of the noise-free law's (the model's), and on these logs
    with a 6 V limit that biased the torque constant by about 2 standard errors (0.02 %)."""
    rng = np.random.default_rng(3)
    t = np.arange(800) * PERIOD
    logs = [
        closed_loop_log(
            t, theta0, f"run{k}", reading_noise=READING_NOISE * rng.standard_normal(t.size), resolution=ADC, limit=100.0
        )
        for k, theta0 in enumerate((-0.3, -0.5))
    ]
    guess = {"motor1.resistance": 3.0, "motor1.torque_constant": 0.06, "hub1.inertia": 2e-3}
    parameters = [identify.Parameter(n, g, g / 5, g * 5) for n, g in guess.items()]
    noise = {"theta1": float(np.hypot(READING_NOISE, ADC / np.sqrt(12)))}
    closed = identify.fit(
        identify.make_problem(
            pendulum(guess),
            parameters,
            logs,
            noise,
            measurement=measurement(ADC),
            controller=controller(quantise=False, limit=100.0),
        ),
        n_starts=1,
    )
    replayed = [dataclasses.replace(log, reference={}) for log in logs]  # (the logged command as the input)
    opened = identify.fit(
        identify.make_problem(pendulum(guess), parameters, replayed, noise, measurement=measurement(ADC)), n_starts=1
    )
    z_closed, z_open = [], []
    for k, name in enumerate(guess):
        z_closed.append((closed.value[name] - TRUTH[name]) / closed.std_errors[k])
        z_open.append((opened.value[name] - TRUTH[name]) / opened.std_errors[k])
    assert closed.converged
    assert np.all(np.abs(z_closed) < 1.96), z_closed
    # (the caveat every closed-loop fit carries, measured where it bites: FitResult.closed_loop_caveat)
    assert "warning: closed-loop fit: the intervals" in closed.summary() and not opened.closed_loop_caveat
    assert closed.to_dict()["closed_loop_caveat"] == closed.closed_loop_caveat
    assert closed.fit_quality["theta1"]["ratio"] < 1.2, closed.fit_quality
    assert opened.converged and opened.fit_quality["theta1"]["ratio"] < 1.2, opened.fit_quality
    assert np.all(np.abs(z_open) < 1.96), z_open


@pytest.mark.slow
def test_the_closed_loop_jacobian_is_the_finite_difference_one():
    """The fit's Jacobian through the loop (`log_jacobian`, forward mode through every
    period's solve and the law) against central differences of the residuals, in the
    motor's, the hub's and a sensor offset the controller reads (unrounded readings:
    the law is smooth there), with a free initial angle, adaptive and at a fixed step."""
    from identify._model.residuals import log_jacobian, residuals

    t = np.arange(120) * PERIOD
    log = dataclasses.replace(closed_loop_log(t, -0.3, "step", resolution=None), fit_initial=("theta1",))
    names = [*TRUTH, "sensor.theta1.offset"]
    problem = identify.make_problem(
        pendulum(),
        [identify.Parameter(n, 1.0) for n in names[:3]] + [identify.Parameter(names[3], 0.0)],
        [log],
        {"theta1": 1e-3, "voltage1": 1e-2},
        measurement=measurement(),
        controller=controller(quantise=False),
    )
    theta = jnp.asarray([TRUTH[n] for n in names[:3]] + [ENCODER_ZERO]) * 1.05
    y0 = jnp.asarray([-0.29])
    off = jnp.zeros(0)
    for step in (None, jnp.asarray(1e-3)):
        jac = log_jacobian(problem, lambda s: s, theta, y0, off, problem.sigma, None, step)

        @jax.jit
        def r(th, y):
            return residuals(problem, th, y, off, problem.sigma, None, step)[0]

        for k in range(4):
            e = jnp.zeros(4).at[k].set(1e-6 * max(abs(float(theta[k])), 1e-3))
            fd_col = (r(theta + e, y0) - r(theta - e, y0)) / (2 * e[k])
            np.testing.assert_allclose(np.asarray(jac.shared[0][:, k]), np.asarray(fd_col), rtol=1e-5, atol=1e-4)
        fd_col = (r(theta, y0 + 1e-7) - r(theta, y0 - 1e-7)) / 2e-7
        np.testing.assert_allclose(np.asarray(jac.y0[0][:, 0]), np.asarray(fd_col), rtol=1e-5, atol=1e-4)


@pytest.mark.slow
def test_a_law_on_the_tip_deflection_is_flexdyns_state_feedback_on_a_flexible_link():
    """A flexible link (one mode) under `torque1 = u_ff + K_theta (theta1_ref - m_theta) -
    K_tip m_tip`, read through an encoder's zero offset and a gauge's gain: the tip
    deflection is linear in the modal coordinate (`tip = c q`), so this is the state
    feedback `u = K (y_ref - y) + u_ff'` with `K = [K_theta, K_tip g c, 0, 0]`,
    `u_ff' = u_ff - K_theta o`, which `flexdyn.simulate_closed_loop` runs (checked against
    SciPy in tests/flexdyn/test_sampled_loop.py). Both loops agree to 1e-9 (rad, N m)."""
    import flexdyn as fd

    chain = fd.Chain(
        [fd.FlexibleLink(0.5, 0.4, 2.0, n_modes=1, damping_ratio=0.01)],
        [fd.RigidJoint(damping=1e-3)],
        [fd.Hub(inertia=2e-3)],
    )
    k_theta, k_tip, u_ff, gauge, zero, limit = 1.5, 40.0, 0.02, 1.3, 0.004, 0.6
    t = np.arange(301) * PERIOD
    ref = np.where(t < 0.05, 0.0, 0.5)
    c = float(fd.tip_deflections(fd.assemble(chain), jnp.asarray([0.0, 1.0]))[0])  # m per m of q1_1
    gain = [[k_theta, k_tip * gauge * c, 0.0, 0.0]]
    run = fd.simulate_closed_loop(
        chain,
        jnp.zeros(4),
        jnp.asarray(t),
        fd.DigitalController(
            fd.LinearFeedback(gain, lambda s: jnp.stack([jnp.interp(s, t, ref), 0.0, 0.0, 0.0]), u_ff - k_theta * zero),
            limit=limit,
        ),
        rtol=1e-11,
        atol=1e-13,
    )
    theta = np.asarray(run.trajectory.Q[:, 0]) + zero
    tip = gauge * c * np.asarray(run.trajectory.Q[:, 1])
    log = identify.LogData(
        t=t,
        outputs={"theta1": theta, "tip1": tip},
        torque=np.asarray(run.commands),
        name="tip",
        hold="zoh",
        reference={"theta1": ref},
    )
    sensors = identify.Measurement({"theta1": identify.Sensor(offset=zero), "tip1": identify.Sensor(gain=gauge)})
    law = identify.Controller("torque1", {"theta1": k_theta, "tip1": k_tip}, {}, ("theta1",), u_ff, limit)
    problem = identify.make_problem(
        chain, [], [log], {"theta1": 1e-3, "tip1": 1e-4}, measurement=sensors, controller=law
    )
    problem = dataclasses.replace(problem, rtol=1e-11, atol=1e-13)
    pred, ok = identify.predict(problem, jnp.zeros(0), problem.y0_known)
    assert bool(ok[0]) and problem.channels == ("theta1", "tip1", "torque1")
    assert np.sum(np.abs(np.asarray(run.commands)) == limit) > 5  # it saturates
    np.testing.assert_allclose(np.asarray(pred[0, :, 0]), theta, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(pred[0, :, 1]), tip, rtol=0, atol=1e-9 * np.abs(tip).max())
    np.testing.assert_allclose(np.asarray(pred[0, :, 2]), np.asarray(run.commands[:, 0]), rtol=0, atol=1e-9)


@pytest.mark.slow
def test_fit_independent_runs_each_closed_loop_log_with_its_own_references():
    """`identify.fit_independent` on two closed-loop logs from different starts (each log
    in the batch its own references and commands): each recovers the motor's resistance
    and the hub's inertia within its 95 % interval (the second log's reference is the
    first's shifted by -0.2 rad, and it starts 0.2 rad lower)."""
    rng = np.random.default_rng(1)
    t = np.arange(300) * PERIOD
    noise = [READING_NOISE * rng.standard_normal(t.size) for _ in range(2)]
    logs = [
        closed_loop_log(t, -0.3, "run0", reading_noise=noise[0], resolution=ADC, limit=100.0),
        closed_loop_log(t, -0.5, "run1", reading_noise=noise[1], resolution=ADC, limit=100.0, shift=-0.2),
    ]
    guess = {"motor1.resistance": 3.0, "hub1.inertia": 2e-3}
    parameters = [identify.Parameter(n, g, g / 5, g * 5) for n, g in guess.items()]
    problem = identify.make_problem(
        pendulum(guess),
        parameters,
        logs,
        {"theta1": float(np.hypot(READING_NOISE, ADC / np.sqrt(12)))},
        measurement=measurement(ADC),
        controller=controller(quantise=False, limit=100.0),
    )
    for result in identify.fit_independent(problem):
        for k, name in enumerate(guess):
            assert abs(result.value[name] - TRUTH[name]) < 1.96 * result.std_errors[k], (name, result.value[name])


def test_new_gains_or_limits_do_not_compile_the_simulation_again():
    """The law's numbers are arrays of the problem (`FeedbackLaw`), not static: a problem
    with other gains, feedforward and limit runs the same compiled simulation."""
    import equinox as eqx

    from identify._model.residuals import predict

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def run(problem):
        return predict(problem, jnp.zeros(0), problem.y0_known)

    t = np.arange(60) * PERIOD
    log = closed_loop_log(t, -0.3, "step")
    outputs = []
    for kp, kd, ff, limit in ((20.0, 0.3, 0.5, 6.0), (25.0, 0.2, 0.0, 4.0)):
        law = identify.Controller("voltage1", {"theta1": kp}, {"theta1": kd}, ("theta1",), ff, limit, PERIOD)
        problem = identify.make_problem(pendulum(), [], [log], {"theta1": 1e-3}, controller=law)
        outputs.append(np.asarray(run(problem)[0]))
    assert not np.allclose(outputs[0][0, :, 1], outputs[1][0, :, 1])  # (the commands differ)


def test_each_joints_input_is_named_by_its_drive():
    """The residual report's input-correlation column names a voltage-driven motor's
    input `voltage1`, a torque-driven joint's `torque1`."""
    from identify._data import channels as ch

    assert ch.input_name(pendulum(), 0) == "voltage1"
    import flexdyn as fd

    assert ch.input_name(fd.rigs.rigid_pendulum(), 0) == "torque1"
