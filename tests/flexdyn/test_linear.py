"""Tests of `flexdyn.linear.stable_step` and of its use: derivatives of a trajectory that
starts at rest.

Oracles: diffrax's own Tsit5 and our RK4 with constant steps on the linearised system
`x' = A x` (a perturbation along the limiting eigenvector decays below the step, grows above
it); central differences of a Dopri8 solution at rtol 1e-12 for the derivatives.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import flexdyn as fd

# A flexible link on an elastic joint, no gravity: at rest it stays at rest, and the
# adaptive steps then grow without bound (the error estimate is 0).
ARM = fd.Chain(
    [fd.FlexibleLink(0.3, 0.39, 3.3, n_modes=1, damping_ratio=0.02)],
    joints=[fd.ElasticJoint(stiffness=2.0, rotor_inertia=1e-3, damping=1.9e-3)],
    hubs=[fd.Hub(inertia=2e-5)],
    gravity=(0.0, 0.0),
)
Y0 = fd.initial_state(ARM, joint_angles=[0.2])


@pytest.mark.parametrize("solver", ["tsit5", "rk4"])
def test_stable_step_is_the_solver_s_stability_limit(solver):
    h = fd.stable_step(ARM, Y0, solver=solver, safety=1.0)
    A = np.asarray(fd.linearize(ARM, Y0).A)
    lam, vec = np.linalg.eig(A)
    worst = np.argmax(np.abs(lam))  # the stiffest mode limits the step here
    x0 = jnp.asarray(np.real(vec[:, worst]))
    method = diffrax.Tsit5() if solver == "tsit5" else fd.solvers.RK4()

    def growth(step):
        steps = 400
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(lambda t, x, args: jnp.asarray(A) @ x),
            method,
            t0=0.0,
            t1=steps * step,
            dt0=step,
            y0=x0,
            stepsize_controller=diffrax.ConstantStepSize(),
            saveat=diffrax.SaveAt(t1=True),
            max_steps=steps + 1,
        )
        return float(jnp.linalg.norm(sol.ys[-1]) / jnp.linalg.norm(x0))

    assert growth(0.97 * h) < 10.0  # within the limit: the mode stays bounded
    assert growth(1.03 * h) > 1e3  # beyond it: it grows by orders of magnitude
    assert fd.stable_step(ARM, Y0, solver=solver) == pytest.approx(0.9 * h)  # the default safety


def test_stable_step_errors():
    with pytest.raises(ValueError, match="solver expected one of"):
        fd.stable_step(ARM, Y0, solver="dopri5")
    with pytest.raises(ValueError, match="safety expected"):
        fd.stable_step(ARM, Y0, safety=1.5)


@pytest.mark.slow  # 95 s in a 2-worker run; stable_step itself stays in CI (the two tests above)
def test_derivatives_from_rest_need_dtmax():
    # The gradient of a loss over 0.5 s at rest w.r.t. y0, through tsit5_trajectory (the
    # discrete adjoint of the steps taken) and simulate (diffrax's reverse pass), against
    # central differences of a Dopri8 solution.
    ts = jnp.linspace(0.0, 0.5, 6)
    n = ARM.n_dof

    def loss(y, fn, dtmax):
        if fn is None:
            Q = fd.simulate(ARM, y, ts, None, solver=diffrax.Dopri8(), rtol=1e-12, atol=1e-14).Q
        else:
            Q = fn(ARM, y, ts, None, rtol=1e-6, atol=1e-8, dtmax=dtmax).Q
        return jnp.sum(Q**2)

    tight = jax.jit(lambda y: loss(y, None, None))
    e = 1e-6
    want = np.array([(float(tight(Y0.at[i].add(e))) - float(tight(Y0.at[i].add(-e)))) / (2 * e) for i in range(2 * n)])
    h = fd.stable_step(ARM, Y0)
    for fn in (fd.tsit5_trajectory, fd.simulate):
        grad = jax.jit(jax.grad(loss), static_argnums=(1, 2))
        # Without dtmax the steps at rest reach ~0.1 s, far beyond the stability limit
        # (~4 ms): the states are right, their derivatives blow up (documented in simulate).
        assert float(jnp.max(jnp.abs(grad(Y0, fn, None)))) > 1e10
        np.testing.assert_allclose(grad(Y0, fn, h / 4), want, rtol=1e-6, err_msg=fn.__name__)


@pytest.mark.slow  # (CI's 30-minute budget: one of the slowest in the fresh-clone run, 2026-12-07)
def test_mode_shape_gradients_are_finite_with_two_rigid_body_modes():
    """Found in a new-user review: an arm with two free joints has two rigid-body modes
    (omega^2 = 0 twice), where JAX's eigenvector derivative divides by zero; the reverse
    pass then made the gradient of every mode shape NaN. Oracle: central differences of
    the squared tip deflection of the first flexible mode (sign-free) w.r.t. the payload
    mass and the inertia of the hub between the links (not EI: a uniform link's
    mass-normalised shapes do not depend on it)."""
    import equinox as eqx

    arm = fd.Chain(
        links=[
            fd.RigidLink(length=0.3, mass=0.4),
            fd.FlexibleLink(length=0.5, rho=0.3, EI=1.0, n_modes=3, damping_ratio=0.01),
        ],
        hubs=[fd.Hub(inertia=0.01), fd.Hub(mass=0.3, inertia=0.002)],
        payload=fd.Payload(mass=0.2),
        gravity=(0.0, 0.0),
    )

    def tip_squared(p, where):
        chain = eqx.tree_at(where, arm, p)
        modes = fd.modal_analysis(chain)
        return fd.tip_deflections(chain, modes.shapes[:, 2])[1] ** 2

    f = np.asarray(fd.modal_analysis(arm).natural_frequency)
    assert f[0] == f[1] == 0.0 and f[2] > 0.0  # two rigid-body modes, then the flexible one
    for where, p0 in ((lambda c: c.payload.mass, 0.2), (lambda c: c.hubs[1].inertia, 0.002)):
        g = float(jax.grad(tip_squared)(jnp.asarray(p0), where))
        h = 1e-6 * p0
        fdiff = (float(tip_squared(jnp.asarray(p0 + h), where)) - float(tip_squared(jnp.asarray(p0 - h), where))) / (
            2 * h
        )
        assert np.isfinite(g) and abs(g - fdiff) <= 1e-6 * abs(fdiff), (g, fdiff)


def test_an_unstable_equilibrium_has_negative_frequencies():
    """Review: `modal_analysis` reported an unstable mode (omega^2 < 0) as 0 Hz, like a
    free rotation. It is now `-sqrt(-omega^2) / 2 pi`. Oracles: the inverted rigid
    pendulum's closed form, omega^2 = -m g l_c / I_pivot (hanging: +); for a floppy link
    hanging under gravity without geometric stiffening (without the shortening terms its
    weight couples swing and bending, and the model's stiffness matrix is indefinite, a
    spurious instability the stiffening removes), the real eigenvalue of `linearize`'s A
    (the growth rate)."""
    chain = fd.rigs.rigid_pendulum(joint_damping=0.0)
    link, L = chain.links[0], 0.30
    m, m_p = float(link.mass), float(chain.payload.mass)
    inertia = m * L**2 / 3 + m_p * L**2 + float(chain.hubs[0].inertia)
    f = np.sqrt((m * L / 2 + m_p * L) * 9.81 / inertia) / (2 * np.pi)
    up = fd.modal_analysis(chain, jnp.array([np.pi / 2]))
    down = fd.modal_analysis(chain, jnp.array([-np.pi / 2]))
    np.testing.assert_allclose(up.natural_frequency, [-f], rtol=1e-12)
    np.testing.assert_allclose(down.natural_frequency, [f], rtol=1e-12)
    assert bool(up.unstable) and not bool(down.unstable)
    # a floppy strip hanging (1 m, rho 1 kg/m, EI 0.5 N m^2, gravity 9.81)
    floppy = fd.Chain(
        [fd.FlexibleLink(1.0, 1.0, 0.5, n_modes=2)],
        joints=[fd.RigidJoint()],
        hubs=[fd.Hub(inertia=1e-3)],
        gravity=(0.0, -9.81),
    )
    hanging = jnp.array([-np.pi / 2, 0.0, 0.0])
    modes = fd.modal_analysis(floppy, hanging)
    eig = np.linalg.eigvals(np.asarray(fd.linearize(floppy, jnp.concatenate([hanging, jnp.zeros(3)])).A))
    growth = np.max(eig.real)
    assert growth > 1.0 and bool(modes.unstable)
    (negative,) = [f for f in np.asarray(modes.natural_frequency) if f < 0]
    np.testing.assert_allclose(-2 * np.pi * negative, growth, rtol=1e-8)


def test_damped_modes_of_a_free_arm_report_its_rigid_rotation_as_zero():
    """Review: paper 004's arm (two free joints) showed damping ratios -1 and +1 for its
    rigid rotations (round-off splits the double zero eigenvalue into +-1e-5 1/s), read as
    an instability. Oracle: the undamped free joints' four zero eigenvalues are four
    entries of frequency 0 and ratio 0; the flexible modes are those of
    `modal_analysis` with the arm's damping, and a growing real eigenvalue (the inverted
    pendulum) keeps its ratio -1."""
    arm = fd.rigs.flexible_link_joint_arm()
    freqs, zeta = fd.damped_modes(fd.linearize(arm))
    assert np.all(freqs[:4] == 0) and np.all(zeta[:4] == 0), (freqs, zeta)
    assert np.all(freqs[4:] > 1.0) and np.all((zeta[4:] > 0) & (zeta[4:] < 1)), (freqs, zeta)
    up = fd.rigs.rigid_pendulum(joint_damping=0.0)
    model = fd.linearize(up, jnp.array([np.pi / 2, 0.0]))
    freqs, zeta = fd.damped_modes(model)
    assert sorted(zeta) == [-1.0, 1.0] and list(freqs) == [0.0, 0.0], (freqs, zeta)
    rate = 2 * np.pi * -float(fd.modal_analysis(up, jnp.array([np.pi / 2])).natural_frequency[0])
    np.testing.assert_allclose(sorted(np.linalg.eigvals(np.asarray(model.A)).real), [-rate, rate], rtol=1e-10)


def test_natural_frequencies_of_a_hanging_rigid_pendulum_match_the_compound_pendulum():
    """`fd.natural_frequencies` analyses a chain about its hanging equilibrium
    (`fd.modal_configuration`). Oracle: the compound pendulum's small-swing frequency,
    `f = sqrt(g (m_l L / 2 + m_p L) / (J_h + m_l L^2 / 3 + m_p L^2)) / (2 pi)` (uniform rod
    of mass `m_l`, length `L`; point payload `m_p` at its tip; hub inertia `J_h`); and
    without gravity the configuration is the zero one, with only the rigid-body mode."""
    g, L, m_l, m_p, J_h = 9.81, 0.30, 0.180, 0.020, 2e-5  # (paper 000: g = 9.81 m/s^2)
    chain = fd.rigs.rigid_pendulum(payload_mass=m_p, hub_inertia=J_h)
    freqs, where = fd.natural_frequencies(chain)
    expected = np.sqrt(g * (m_l * L / 2 + m_p * L) / (J_h + m_l * L**2 / 3 + m_p * L**2)) / (2 * np.pi)
    assert freqs == pytest.approx([expected], rel=1e-10)
    assert "hanging equilibrium" in where and "-90 deg" in where
    Q0, _ = fd.modal_configuration(chain)
    assert Q0[0] == pytest.approx(-np.pi / 2, rel=1e-15)
    free, where = fd.natural_frequencies(eqx.tree_at(lambda c: c.gravity, chain, jnp.zeros(2)))
    assert where == "zero configuration" and free == pytest.approx([0.0], abs=1e-6)
