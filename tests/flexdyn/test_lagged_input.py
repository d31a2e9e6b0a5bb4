"""`flexdyn.LaggedTorque` against closed forms of the lag `T u_a' = u - u_a` and against an
independent SciPy integration of a free rotor with the lag as a state."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate

import flexdyn as fd


def _at(u, ts):
    return np.asarray(jax.vmap(lambda t: u(t, None))(jnp.asarray(ts)))


def test_a_held_step_relaxes_exponentially():
    """Held command 0 until 0.1 s, then 1 N m: `u_a = 1 - e^{-(t - 0.1)/T}` after the step,
    0 before, also across later samples of the same value and after the last sample."""
    T = 0.03
    times = np.arange(0.0, 0.5, 0.01)
    values = np.where(times >= 0.1 - 1e-12, 1.0, 0.0)
    u = fd.LaggedTorque(fd.SampledTorque(times, values, hold="zoh"), T)
    ts = np.linspace(0.0, 0.8, 1601)
    expected = np.where(ts < 0.1, 0.0, -np.expm1(-(ts - 0.1) / T))
    np.testing.assert_allclose(_at(u, ts)[:, 0], expected, rtol=0, atol=1e-13)


def test_a_linear_ramp_lags_by_the_time_constant():
    """Linear command `u = c t` from rest: `u_a = c (t - T) + c T e^{-t/T}`."""
    c, T = 2.0, 0.05
    times = np.linspace(0.0, 1.0, 37)
    u = fd.LaggedTorque(fd.SampledTorque(times, c * times), T)
    ts = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(_at(u, ts)[:, 0], c * (ts - T) + c * T * np.exp(-ts / T), rtol=0, atol=1e-13)


@pytest.mark.parametrize("hold", ["zoh", "linear"])
def test_no_lag_is_the_command(hold):
    rng = np.random.default_rng(0)
    times = np.cumsum(rng.uniform(0.005, 0.02, 40))
    values = rng.normal(size=(40, 2))
    command = fd.SampledTorque(times, values, hold=hold)
    ts = np.concatenate([times, 0.5 * (times[1:] + times[:-1]), [times[0] - 1.0, times[-1] + 1.0]])
    # to round-off: `u_k + m_k s` here, `jnp.interp` in the command
    np.testing.assert_allclose(_at(fd.LaggedTorque(command, [0.0, 0.0]), ts), _at(command, ts), rtol=1e-14, atol=1e-15)


def test_a_linear_command_at_zero_lag_has_the_first_order_derivative():
    """d u_a / dT at T = 0 is `-u'` for a linear command (`u_a ~ u - T u'`)."""
    times = np.linspace(0.0, 1.0, 11)
    values = np.sin(3 * times)
    command = fd.SampledTorque(times, values)
    t = 0.437
    d = jax.grad(lambda T: fd.LaggedTorque(command, T)(t)[0])(0.0)
    k = 4  # 0.4 <= t < 0.5
    slope = (values[k + 1] - values[k]) / (times[k + 1] - times[k])
    assert float(d) == pytest.approx(-slope, rel=1e-12)


def test_a_free_rotor_under_a_lagged_held_command_matches_an_independent_integration():
    """A rigid link in the horizontal plane (free rotor, J = J_hub + m l^2 / 3, viscous
    damping b) driven through a 12 ms lag by random commands held at 200 Hz. Oracle:
    SciPy's DOP853 on `[theta, omega, u_a]` with `T u_a' = u_k - u_a`, restarted at every
    sample so the held command is exact in each piece."""
    length, mass, hub, b, T = 0.5, 0.2, 0.02, 0.01, 0.012
    chain = fd.Chain([fd.RigidLink(length, mass)], joints=[fd.RigidJoint(damping=b)], hubs=[fd.Hub(inertia=hub)])
    J = hub + mass * length**2 / 3
    rng = np.random.default_rng(3)
    times = np.arange(0.0, 0.6, 0.005)
    values = rng.uniform(-0.05, 0.05, times.size)
    u = fd.LaggedTorque(fd.SampledTorque(times, values, hold="zoh"), T)
    traj = fd.simulate(
        chain, fd.initial_state(chain, joint_angles=[0.0]), jnp.asarray(times), u, rtol=1e-11, atol=1e-13
    )

    def rhs(t, x, uk):
        theta, omega, ua = x
        return [omega, (ua - b * omega) / J, (uk - ua) / T]

    x = np.array([0.0, 0.0, values[0]])
    expected = [0.0]
    for k in range(times.size - 1):
        sol = scipy.integrate.solve_ivp(
            rhs, (times[k], times[k + 1]), x, args=(values[k],), method="DOP853", rtol=1e-12, atol=1e-14
        )
        x = sol.y[:, -1]
        expected.append(x[0])
    assert np.max(np.abs(expected)) > 1e-3  # it moves
    np.testing.assert_allclose(np.asarray(traj.Q[:, 0]), expected, rtol=0, atol=1e-10)
    # the knots are the lag's values at the samples
    np.testing.assert_allclose(np.asarray(u.knots[-1, 0]), x[2], rtol=0, atol=1e-12)


def test_bad_time_constants_are_named():
    command = fd.SampledTorque([0.0, 1.0], [[0.0, 1.0], [1.0, 0.0]])
    with pytest.raises(ValueError, match="LaggedTorque.time_constant.*>= 0"):
        fd.LaggedTorque(command, [0.01, -0.01])
    with pytest.raises(ValueError, match="LaggedTorque.time_constant.*or 2"):
        fd.LaggedTorque(command, [0.01, 0.02, 0.03])
