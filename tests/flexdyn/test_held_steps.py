"""Constant steps stopped at a held command's jumps (`flexdyn.held_steps`).

Oracle: a free rotor `J theta'' = u(t)` under a held (piecewise-constant) torque has the
exact piecewise-quadratic solution summed in the test. A Runge-Kutta step over a stretch
where `u` is constant integrates it exactly, so with the steps stopped at the jumps any
step size gives the closed form to rounding; plain constant steps straddle the jumps and
are off by `O(h |du|)`."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import flexdyn as fd
from flexdyn.held_steps import clipped_constant_steps
from flexdyn.inputs import held_changes

J = 0.02  # kg m^2
TIMES = np.arange(0.0, 1.0 + 1e-12, 0.01)  # 100 Hz samples
RNG = np.random.default_rng(4)
# a held command that changes at 17 irregular samples (as a digital controller's bang-bang)
VALUES = np.repeat(
    RNG.normal(0.0, 0.3, 18), np.diff(np.r_[0, np.sort(RNG.choice(np.arange(1, 101), 17, replace=False)), 101])
)


def _exact(t_end: float) -> tuple[float, float]:
    """Angle (rad) and rate (rad/s) at `t_end` from rest: sum of the quadratic pieces."""
    theta = rate = 0.0
    for k in range(len(TIMES) - 1):
        a, b = TIMES[k], min(TIMES[k + 1], t_end)
        if b <= a:
            break
        h, acc = b - a, VALUES[k] / J
        theta += rate * h + 0.5 * acc * h * h
        rate += acc * h
    return theta, rate


def _solve(controller, solver, dt):
    torque = fd.SampledTorque(TIMES, VALUES, hold="zoh")
    field = lambda t, y, args: jnp.array([y[1], torque(t)[0] / J])  # noqa: E731
    return diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        solver,
        t0=0.0,
        t1=0.9137,
        dt0=dt,
        y0=jnp.zeros(2),
        stepsize_controller=controller,
        max_steps=10_000,
    )


@pytest.mark.parametrize("solver", [fd.RK4(), diffrax.Tsit5()], ids=["rk4", "tsit5"])
@pytest.mark.parametrize("dt", [0.0037, 0.01, 0.05])
def test_steps_stopped_at_the_jumps_give_the_closed_form(solver, dt):
    jumps = held_changes(jnp.asarray(TIMES), jnp.asarray(VALUES)[:, None])
    sol = _solve(clipped_constant_steps(jumps), solver, dt)
    theta, rate = _exact(0.9137)
    np.testing.assert_allclose(np.asarray(sol.ys[-1]), [theta, rate], rtol=1e-12, atol=1e-13)
    # at most one step more per jump than the plain constant steps
    n_jumps = int(np.sum(np.isfinite(np.asarray(jumps)) & (np.asarray(jumps) < 0.9137)))
    assert int(sol.stats["num_steps"]) <= int(np.ceil(0.9137 / dt)) + n_jumps


def test_plain_constant_steps_straddle_the_jumps():
    """The failure the clipping removes (so the test above can fail): 0.0037 s steps over
    100 Hz held samples are off by far more than rounding."""
    sol = _solve(diffrax.ConstantStepSize(), fd.RK4(), 0.0037)
    theta, _ = _exact(0.9137)
    assert abs(float(sol.ys[-1][0]) - theta) > 1e-6


def test_traced_jumps_and_no_jumps():
    """The jumps may be traced (one compiled solve for any command); without jumps the
    controller is diffrax's plain constant step."""
    assert isinstance(clipped_constant_steps(None), diffrax.ConstantStepSize)

    @jax.jit
    def final_angle(values):
        jumps = held_changes(jnp.asarray(TIMES), values[:, None])
        torque = fd.SampledTorque(TIMES, values, hold="zoh")
        field = lambda t, y, args: jnp.array([y[1], torque(t)[0] / J])  # noqa: E731
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(field),
            fd.RK4(),
            t0=0.0,
            t1=0.9137,
            dt0=0.0037,
            y0=jnp.zeros(2),
            stepsize_controller=clipped_constant_steps(jumps),
            max_steps=10_000,
        )
        return sol.ys[-1][0]

    np.testing.assert_allclose(float(final_angle(jnp.asarray(VALUES))), _exact(0.9137)[0], rtol=1e-12)
