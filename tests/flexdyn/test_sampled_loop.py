"""`flexdyn.simulate_closed_loop` against an independent discrete-time simulation of the
same loop written here: SciPy's DOP853 on a pendulum's own equation of motion, restarted
at every controller tick with the held, clipped command."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate

import flexdyn as fd

L, M, HUB, B, G = 0.30, 0.18, 2e-5, 1.9e-3, 9.81
KP, KD, LIMIT, REF = 6.0, 0.15, 0.6, 0.6  # N m/rad, N m s/rad, N m, rad
PERIOD = 1e-3


def _pendulum():
    """A uniform rod on a hub, vertical plane (gravity -y), viscous joint damping."""
    return fd.Chain([fd.RigidLink(L, M)], [fd.RigidJoint(damping=B)], [fd.Hub(inertia=HUB)], gravity=(0.0, -G))


def _reference_loop(ticks, theta0, delay):
    """The same loop, independently: `J theta'' = u - B theta' - M G (L/2) cos(theta)`
    (theta from the horizontal, J = HUB + M L^2 / 3); `u_k = clip(KP (REF - theta_k) -
    KD omega_k, +-LIMIT)`, held over each period (from tick k - 1's state with `delay`)."""
    J = HUB + M * L**2 / 3

    def rhs(t, x, u):
        theta, omega = x
        return [omega, (u - B * omega - M * G * (L / 2) * math.cos(theta)) / J]

    def law(x):
        return float(np.clip(KP * (REF - x[0]) - KD * x[1], -LIMIT, LIMIT))

    x = np.array([theta0, 0.0])
    u = 0.0 if delay else law(x)
    states, commands = [x.copy()], [u]
    for k in range(len(ticks) - 1):
        sol = scipy.integrate.solve_ivp(
            rhs, (ticks[k], ticks[k + 1]), x, args=(u,), method="DOP853", rtol=1e-12, atol=1e-14
        )
        u = law(x) if delay else law(sol.y[:, -1])
        x = sol.y[:, -1]
        states.append(x.copy())
        commands.append(u)
    return np.array(states), np.array(commands)


@pytest.mark.parametrize("delay", [False, True])
def test_a_pd_loop_with_saturation_matches_an_independent_discrete_time_simulation(delay):
    """A PD step of the pendulum from -0.3 rad to 0.6 rad at 1 kHz for 1.5 s: the
    command saturates at the start (the oracle checks it does), then settles."""
    chain = _pendulum()
    ticks = np.arange(1501) * PERIOD
    target = lambda t: jnp.array([REF, 0.0])  # noqa: E731
    controller = fd.DigitalController(fd.LinearFeedback([[KP, KD]], target), limit=LIMIT, delay=delay)
    run = fd.simulate_closed_loop(
        chain, fd.initial_state(chain, [-0.3]), jnp.asarray(ticks), controller, rtol=1e-11, atol=1e-13
    )
    states, commands = _reference_loop(ticks, -0.3, delay)
    assert np.sum(np.abs(commands) == LIMIT) > 10  # the actuator saturates
    assert abs(states[-1, 0] - REF) < 0.1  # and the loop settles near the reference
    np.testing.assert_allclose(np.asarray(run.trajectory.Q[:, 0]), states[:, 0], rtol=0, atol=1e-8)
    np.testing.assert_allclose(np.asarray(run.trajectory.Qd[:, 0]), states[:, 1], rtol=0, atol=1e-7)
    np.testing.assert_allclose(np.asarray(run.commands[:, 0]), commands, rtol=0, atol=1e-8)


def test_an_unstable_loop_is_an_error_not_nans():
    """Positive feedback with a huge gain: the state runs away and a period's solve fails;
    the run says so instead of returning NaNs."""
    chain = _pendulum()
    controller = fd.DigitalController(fd.LinearFeedback([[-1e6, 0.0]]))
    with pytest.raises(Exception, match="simulate_closed_loop: a controller period's solve failed"):
        fd.simulate_closed_loop(
            chain, fd.initial_state(chain, [0.1]), jnp.asarray(np.arange(200) * 1e-2), controller, max_steps_per_tick=64
        )


def test_a_bad_limit_is_named():
    with pytest.raises(ValueError, match="DigitalController.limit"):
        fd.DigitalController(fd.LinearFeedback([[1.0, 0.1]]), limit=0.0)
