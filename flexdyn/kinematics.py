"""Planar kinematics of an assembled chain: each body's frame (origin and rotation) and its
rates, from the generalised coordinates `Q` (rad, m) and velocities `Qd`.

`asm` is an `AssembledChain` (`flexdyn.assemble(chain)`), `lay` its `Layout`. The chain
imports this module, not the other way round, so the types are named here, not imported.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jaxtyping import Array


def rotation_matrix(angle):
    """The planar rotation by `angle` (rad), `[[cos, -sin], [sin, cos]]`."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.array([[c, -s], [s, c]])


class Frames(NamedTuple):
    """Positions and absolute angles along the chain (base frame)."""

    origin: tuple  # o_i, joint positions, (2,) each
    angle: tuple  # phi_i, absolute angle of link i's root frame
    tip_angle: tuple  # psi_i = phi_i + v_i'(l_i)
    rotor_carrier: tuple  # absolute angle of the frame carrying rotor i (psi_{i-1})
    end: Array  # o_{n+1}, position of the tip of the last link


def frames(asm, Q) -> Frames:
    lay = asm.layout
    o = jnp.zeros(2)
    psi = jnp.zeros(())
    origins, angles, tips, carriers = [], [], [], []
    for i, lm in enumerate(asm.links):
        phi = psi + Q[lay.theta[i]]
        q = modal_slice(lay, Q, i)
        origins.append(o)
        angles.append(phi)
        carriers.append(psi)
        tip_local = jnp.stack([reach_length(asm, i, q), jnp.dot(lm.tip_shape, q)])
        o = o + rotation_matrix(phi) @ tip_local
        psi = phi + jnp.dot(lm.tip_slope, q)
        tips.append(psi)
    return Frames(tuple(origins), tuple(angles), tuple(tips), tuple(carriers), o)


def frames_and_rates(asm, Q, Qd) -> tuple[Frames, Frames]:
    """`frames(asm, Q)` and its time derivative along `Qd`, by the velocity recursion

        phi_dot_i = psi_dot_{i-1} + theta_dot_i,
        o_dot_{i+1} = o_dot_i + phi_dot_i S R(phi_i) [l_i + u_i(l_i), v_i(l_i)]
                    + R(phi_i) [u_dot_i(l_i), v_dot_i(l_i)],
        psi_dot_i = phi_dot_i + v_dot_i'(l_i),

    (`S` the 90-degree rotation; `u_i = 0` without geometric stiffening), written out so
    that the kinetic energy carries no nested derivative (smaller graphs to compile and to
    differentiate)."""
    lay = asm.layout
    o, o_dot = jnp.zeros(2), jnp.zeros(2)
    psi, psi_dot = jnp.zeros(()), jnp.zeros(())
    pos = ([], [], [], [])
    vel = ([], [], [], [])
    for i, lm in enumerate(asm.links):
        phi = psi + Q[lay.theta[i]]
        phi_dot = psi_dot + Qd[lay.theta[i]]
        q, qd = modal_slice(lay, Q, i), modal_slice(lay, Qd, i)
        for lst, val in zip(pos, (o, phi, None, psi)):
            lst.append(val)
        for lst, val in zip(vel, (o_dot, phi_dot, None, psi_dot)):
            lst.append(val)
        R = rotation_matrix(phi)
        tip_local = jnp.stack([reach_length(asm, i, q), jnp.dot(lm.tip_shape, q)])
        tip_rate = jnp.stack([reach_rate(asm, i, q, qd), jnp.dot(lm.tip_shape, qd)])
        arm = R @ tip_local
        o_dot = o_dot + phi_dot * jnp.stack([-arm[1], arm[0]]) + R @ tip_rate
        o = o + arm
        psi = phi + jnp.dot(lm.tip_slope, q)
        psi_dot = phi_dot + jnp.dot(lm.tip_slope, qd)
        pos[2][-1] = psi
        vel[2][-1] = psi_dot
    f = Frames(tuple(pos[0]), tuple(pos[1]), tuple(pos[2]), tuple(pos[3]), o)
    fd = Frames(tuple(vel[0]), tuple(vel[1]), tuple(vel[2]), tuple(vel[3]), o_dot)
    return f, fd


def modal_slice(lay, Q, i):
    idx = lay.modal[i]
    return Q[idx[0] : idx[-1] + 1] if idx else jnp.zeros((0,), Q.dtype)


def stiffening_of(asm, i: int) -> bool:
    """Whether link i has geometric stiffening (static structure)."""
    return bool(getattr(asm.chain.links[i], "geometric_stiffening", False))


def quadratic_of(A, x, y):
    """`x^T A y` on scalar components (see `kinetic_energy`)."""
    return jnp.sum(x[:, None] * A * y[None, :])


def reach_length(asm, i: int, q):
    """Axial position of link i's tip in its root frame, m: `l + u(l)`, `u(l) = -1/2 q^T
    shortening q` with geometric stiffening, `l` without."""
    lm = asm.links[i]
    return lm.length - 0.5 * quadratic_of(lm.shortening, q, q) if stiffening_of(asm, i) else lm.length


def reach_rate(asm, i: int, q, qd):
    """Time derivative of `_reach`, m/s."""
    if not stiffening_of(asm, i):
        return jnp.zeros((), q.dtype)
    return -quadratic_of(asm.links[i].shortening, q, qd)
