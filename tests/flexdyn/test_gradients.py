"""Issue test 7: derivatives of a simulated trajectory with respect to physical
parameters, reverse mode (`jax.grad`, recursive checkpointing) and forward mode
(`jax.jacfwd` with `diffrax.ForwardMode()`), against central finite differences.

The solve is fixed-step RK4 at 1 ms (steps aligned with the bang-bang switches), so
AD and finite differences differentiate the same discrete map: the only error in
the comparison is the finite-difference one, O(h^2) truncation + O(eps / h) round-off.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import flexdyn as fd

# EI of both links [N m^2], joint 1 viscous damping [N m s/rad], hub 1 inertia
# [kg m^2], payload mass [kg]: paper 002's arm, with some joint damping and a payload.
P0 = np.array([1.0, 0.01, 0.02, 0.05])
TS = jnp.linspace(0.0, 1.0, 51)
DT = 1e-3


def _chain(p):
    base = fd.rigs.two_link_flexible_arm()
    return eqx.tree_at(
        lambda c: (c.links[0].EI, c.links[1].EI, c.joints[0].damping, c.hubs[0].inertia, c.payload.mass),
        base,
        (p[0], p[0], p[1], p[2], p[3]),
    )


def _loss(p, adjoint=None):
    """Sum of squares of the joint angles (rad) and tip deflections (in cm) over 1 s of
    paper 002's bang-bang manoeuvre (0.2 N m on both joints, 0.5 s pulses)."""
    chain = _chain(p)
    y0 = fd.initial_state(chain, [0.0, 0.0])
    torque = fd.BangBang(jnp.array([0.2, 0.2]), 0.5)
    traj = fd.simulate(chain, y0, TS, torque, dt=DT, adjoint=adjoint)
    asm = fd.assemble(chain)
    theta = traj.Q[:, jnp.asarray(chain.layout.theta)]
    tip = jax.vmap(lambda Q: fd.tip_deflections(asm, Q))(traj.Q)
    return jnp.sum(theta**2) + jnp.sum((tip / 1e-2) ** 2)


_loss_jit = jax.jit(_loss)
_grad_jit = jax.jit(jax.grad(_loss))  # shared: compiling it is most of these tests' cost


@pytest.fixture(scope="module")
def finite_difference_gradient():
    """Central differences with a relative step of 1e-4: truncation ~1e-8, round-off
    ~1e-16 / 1e-4 relative, both far below the 1e-5 tolerance."""
    p0 = jnp.asarray(P0)
    grad = np.zeros(len(P0))
    for i in range(len(P0)):
        h = 1e-4 * P0[i]
        e = jnp.zeros(len(P0)).at[i].set(h)
        grad[i] = (float(_loss_jit(p0 + e)) - float(_loss_jit(p0 - e))) / (2 * h)
    return grad


def _assert_gradient_close(ad, fd_grad):
    ad = np.asarray(ad)
    assert np.all(np.isfinite(ad))
    # Every parameter matters (a zero derivative would make the check vacuous).
    assert np.all(np.abs(fd_grad) > 1e-6 * np.max(np.abs(fd_grad))), fd_grad
    np.testing.assert_allclose(ad, fd_grad, rtol=1e-5, atol=0)


def test_reverse_mode_gradient_matches_finite_differences(finite_difference_gradient):
    grad = _grad_jit(jnp.asarray(P0))
    _assert_gradient_close(grad, finite_difference_gradient)


@pytest.mark.slow  # ~25 s of compilation; the reverse-mode test covers the default run
def test_forward_mode_jacobian_matches_finite_differences(finite_difference_gradient):
    jac = jax.jit(jax.jacfwd(lambda p: _loss(p, adjoint=diffrax.ForwardMode())))(jnp.asarray(P0))
    _assert_gradient_close(jac, finite_difference_gradient)


@pytest.mark.slow  # ~30 s of compilation
def test_vmap_of_grad_over_payloads_equals_loop():
    params = jnp.stack([jnp.asarray(P0).at[3].set(m) for m in (0.0, 0.03, 0.1)])
    batched = np.asarray(jax.jit(jax.vmap(jax.grad(_loss)))(params))
    looped = np.stack([np.asarray(_grad_jit(p)) for p in params])
    np.testing.assert_allclose(batched, looped, rtol=1e-10, atol=1e-12)
    assert not np.allclose(looped[0], looped[-1])  # the payload changes the gradient
