"""The chain and inputs the discrete-adjoint tests share (`tests/flexdyn/test_fixed_step.py`,
`tests/flexdyn/test_tsit5.py`).

A one-link flexible pendulum with every kind of force the Lagrange residual carries:
gravity, an elastic joint with rotor, viscous and dry friction, structural damping, and air
drag on the link (it compiles 2.5x faster than the two-link arm).
"""

import jax.numpy as jnp

import flexdyn as fd

PENDULUM = fd.Chain(
    [fd.FlexibleLink(0.3, 0.39, 3.3, n_modes=1, damping_ratio=0.02, drag=0.05)],
    joints=[fd.ElasticJoint(stiffness=2.0, rotor_inertia=1e-3, damping=1.9e-3, coulomb=5e-3)],
    hubs=[fd.Hub(inertia=2e-5)],
    gravity=(0.0, -9.81),
)
PENDULUM_PARAMS = ("link1.EI", "link1.drag", "joint1.coulomb", "joint1.stiffness")
PENDULUM_Y0 = fd.initial_state(PENDULUM, joint_angles=[0.3], modal=[1e-3])


def pd_tracking() -> fd.PDTracking:
    """A PD controller tracking a quintic move of the pendulum's joint (0.3 -> 0.8 rad in
    0.2 s): a torque that depends on the state."""
    return fd.PDTracking(
        reference=fd.QuinticReference([0.3], [0.8], 0.2),
        kp=jnp.array([0.5]),
        kd=jnp.array([0.02]),
        actuated=PENDULUM.layout.actuated,
        n_dof=PENDULUM.n_dof,
    )
