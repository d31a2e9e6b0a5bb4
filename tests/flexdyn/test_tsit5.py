"""Tests of `flexdyn.tsit5` (adaptive Tsit5 with a discrete-adjoint reverse-mode derivative).

Oracles: a Dopri8 solution at rtol 1e-12 for the states; diffrax's own reverse-mode
gradient through the same solve (`fd.simulate` with Tsit5: its checkpointed reverse pass
through its general Runge-Kutta stage loop, an implementation independent of ours) for
the discrete gradient; central finite differences of a tightly solved loss for the
derivative of the solution itself.
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from adjoint_cases import PENDULUM, PENDULUM_PARAMS, PENDULUM_Y0, pd_tracking  # tests/ is on sys.path

import flexdyn as fd

# The shared flexible pendulum (`tests/adjoint_cases.py`); bang-bang jumps at 0.1 s and
# 0.2 s, which are output times of the 1 kHz log.
PARAMS = PENDULUM_PARAMS
Y0 = PENDULUM_Y0
TS = jnp.linspace(0.0, 0.3, 301)
BANG = fd.BangBang([0.02], 0.1)
TOL = dict(rtol=1e-7, atol=1e-9)


def _loss(values, y0, torque, how, tol=TOL):
    chain = fd.with_parameters(PENDULUM, dict(zip(PARAMS, values)))
    if isinstance(tol, tuple):  # (rtol, atol): hashable, for static_argnums
        tol = dict(rtol=tol[0], atol=tol[1])
    if how == "ours":
        traj = fd.tsit5_trajectory(chain, y0, TS, torque, **tol)
    elif how == "dopri8":  # the reference solution
        traj = fd.simulate(chain, y0, TS, torque, solver=diffrax.Dopri8(), rtol=1e-12, atol=1e-14)
    else:  # diffrax's own reverse mode through the same solve
        traj = fd.simulate(chain, y0, TS, torque, **tol)
    return jnp.sum(traj.Q**2) + jnp.sum(traj.Qd[-1] ** 2)


X = jnp.asarray([float(fd.get_parameter(PENDULUM, n)) for n in PARAMS]) * 1.1


def test_states_are_simulate_s_and_converge_to_dopri8():
    ours = fd.tsit5_trajectory(PENDULUM, Y0, TS, BANG, **TOL)
    same = fd.simulate(PENDULUM, Y0, TS, BANG, **TOL)
    reference = fd.simulate(PENDULUM, Y0, TS, BANG, solver=diffrax.Dopri8(), rtol=1e-12, atol=1e-14)
    assert ours.names == same.names and int(ours.num_steps) == int(same.num_steps) > 10
    np.testing.assert_allclose(ours.y, same.y, rtol=0, atol=1e-13)
    assert float(jnp.max(jnp.abs(ours.Q - reference.Q))) < 1e-7


def test_gradient_equals_diffrax_reverse_mode():
    # Parameters, y0 and the input's amplitude, across two input jumps at output times.
    grad = jax.jit(jax.grad(_loss, argnums=(0, 1, 2)), static_argnums=3)
    ours, peer = grad(X, Y0, BANG, "ours"), grad(X, Y0, BANG, "diffrax")
    for a, b in zip((ours[0], ours[1], ours[2].amplitude), (peer[0], peer[1], peer[2].amplitude)):
        np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-11 * float(jnp.max(jnp.abs(b))))
    assert float(jnp.max(jnp.abs(ours[2].amplitude))) > 0  # the input's array fields get a gradient
    # (The switching times' derivatives differ by design: diffrax differentiates its step
    # times, ours is the solution's derivative; see the next test.)


def test_switching_time_derivative_is_the_solution_s():
    # BangBang's width and start move its jumps: dL/dJ = lambda(J)^T (f(J^-) - f(J^+)),
    # against central differences of the loss solved with Dopri8 at rtol 1e-12,
    # Richardson-extrapolated (h = 2e-6 and 1e-6: error O(h^4)). The jumps (0.0213,
    # 0.11495, 0.2086 s) are not output times (the log's 1 ms grid), where the solution's
    # second derivative jumps and so does the loss's: with a jump on one (width 0.0937:
    # 0.115 s), a central difference's error is O(h), 5e-7 relative at h = 1e-6, the
    # test's tolerance (measured on an Intel Xeon, where it failed). Plain central
    # differences at h = 1e-6 are 5.3e-7 from ours here (the loss's third derivative is
    # large: ~4.7e6); extrapolated, 1.5e-7. diffrax's reverse mode (its
    # step times differentiated) is far off at rtol 1e-7 (-3055 for the start against
    # 11.05 at width 0.0937: measured when this test was written) and 35 % off at 1e-10.
    def loss(wp, how, tol):
        return _loss(X, Y0, fd.BangBang([0.02], wp[0], wp[1]), how, tol)

    wp = jnp.asarray([0.09365, 0.0213])
    tight = jax.jit(lambda v: loss(v, "dopri8", None))

    def central(i, h):
        return (float(tight(wp.at[i].add(h))) - float(tight(wp.at[i].add(-h)))) / (2 * h)

    fd_ = [(4 * central(i, 1e-6) - central(i, 2e-6)) / 3 for i in range(2)]
    grad = jax.jit(jax.grad(loss), static_argnums=(1, 2))
    for tol, rtol in (((1e-10, 1e-12), 1e-6), ((1e-7, 1e-9), 1e-4)):
        g = grad(wp, "ours", tol)
        np.testing.assert_allclose(g, fd_, rtol=rtol, err_msg=f"tsit5_trajectory at rtol {tol[0]}")
    assert abs(fd_[1]) > 1.0  # both switching times matter to the loss


@pytest.mark.slow  # 65 s in a 2-worker run; jumps stay in CI (the two jumps of the diffrax and switching tests)
def test_gradient_with_a_zero_order_hold_log():
    # A sampled torque held between samples (`hold="zoh"`): a jump at every sample time, 30
    # of them inside the log, each a step boundary. The samples' gradient against diffrax's.
    times = jnp.linspace(0.0, 0.29, 30)
    torque = fd.SampledTorque(times, 0.02 * jnp.sin(40.0 * times), hold="zoh")
    grad = jax.jit(jax.grad(_loss, argnums=(0, 2)), static_argnums=3)
    ours, peer = grad(X, Y0, torque, "ours"), grad(X, Y0, torque, "diffrax")
    np.testing.assert_allclose(ours[0], peer[0], rtol=1e-8)
    scale = float(jnp.max(jnp.abs(peer[1].values)))
    np.testing.assert_allclose(ours[1].values, peer[1].values, rtol=1e-7, atol=1e-10 * scale)
    assert scale > 0


@pytest.mark.slow  # 56 s in a 2-worker run; a vmapped discrete adjoint with PDTracking stays in CI (rk4_trajectory's,
# test_fixed_step)
def test_gradient_under_vmap_with_state_feedback():
    # A PD controller tracking a quintic move: the torque depends on the state, so each
    # stage's transpose carries the controller's derivative into the state's cotangent. The
    # batch takes different numbers of steps per entry (the while loop's trip counts differ).
    torque = pd_tracking()
    xs = jnp.stack([X, X * jnp.asarray([1.3, 0.8, 2.0, 3.0])])
    batched = jax.jit(jax.vmap(lambda v: jax.grad(_loss)(v, Y0, torque, "ours")))(xs)
    peer = jax.jit(jax.grad(_loss), static_argnums=3)
    for i in range(2):
        np.testing.assert_allclose(batched[i], peer(xs[i], Y0, torque, "diffrax"), rtol=1e-8)


def test_gradient_is_the_solution_s_derivative():
    # Central differences of the loss solved at rtol 1e-12 (Dopri8): the discrete gradient at
    # rtol 1e-10 is the derivative of the solution to well within the tolerances.
    g = jax.jit(jax.grad(lambda v: _loss(v, Y0, BANG, "ours", dict(rtol=1e-10, atol=1e-12))))(X)

    @jax.jit
    def tight(v):
        chain = fd.with_parameters(PENDULUM, dict(zip(PARAMS, v)))
        traj = fd.simulate(chain, Y0, TS, BANG, solver=diffrax.Dopri8(), rtol=1e-12, atol=1e-14)
        return jnp.sum(traj.Q**2) + jnp.sum(traj.Qd[-1] ** 2)

    for i in range(len(PARAMS)):
        h = 1e-4 * float(X[i])
        e = jnp.zeros_like(X).at[i].set(h)
        fd_i = (float(tight(X + e)) - float(tight(X - e))) / (2 * h)
        assert abs(float(g[i]) - fd_i) <= 1e-5 * abs(fd_i) + 1e-9, (PARAMS[i], float(g[i]), fd_i)


def test_tsit5_trajectory_errors():
    with pytest.raises(ValueError, match=r"y0 expected shape \(6,\)"):
        fd.tsit5_trajectory(PENDULUM, Y0[:2], TS, BANG)
    with pytest.raises(ValueError, match="at least 2 times"):
        fd.tsit5_trajectory(PENDULUM, Y0, TS[:1], BANG)
    with pytest.raises(ValueError, match="max_steps expected a positive int"):
        fd.tsit5_trajectory(PENDULUM, Y0, TS, BANG, max_steps=0)
    with pytest.raises(Exception, match="reached max_steps=5"):
        jax.block_until_ready(fd.tsit5_trajectory(PENDULUM, Y0, TS, BANG, max_steps=5).Q)
    with pytest.raises(TypeError, match="custom_vjp"):  # forward mode is not defined
        jax.jacfwd(lambda v: _loss(v, Y0, BANG, "ours"))(X)
