r"""Non-linear joint and link forces: dry friction, aerodynamic drag, gear backlash.

These are the model extensions that linear-viscous models (papers 000, 002, 004) lack
and that real rigs show: paper 000's pendulum matched its linear-damping model for
only ~7 s "due to the non-linear effect of damping". Each is an optional field of a
part (`None`: the term is not in the equations at all; a number, `0.0` included:
present), so a chain without them compiles to the same program as before.

**Dry friction** on joint i's actuated rate `s_dot` (the link rate of a rigid joint,
the rotor rate of an elastic one), smoothed so that it is differentiable:

    tau_f = -F_c tanh(s_dot / v_s),         F_c = `joint.coulomb` [N m], v_s = `joint.coulomb_velocity` [rad/s]

For `|s_dot| > 2.65 v_s` it is within 1 % of the discontinuous `-F_c sign(s_dot)`;
below, it acts as a stiff viscous damper `F_c / v_s`, the usual regularisation of
stiction (no stick-slip state). A free linear oscillator with this friction loses
`2 F_c / k` of amplitude per half period (a straight-line envelope, not an
exponential one): the signature `identify.diagnose` looks for.

**Aerodynamic drag** on link i (Morison's quadratic drag, per unit length):

    f(x) = -c |v_n(x)| v_n(x) [N/m],       v_n(x) = u_y + omega x + v_dot(x)

with `c = link.drag` [kg/m^2] (`rho_air C_d w / 2` for a strip of width w), `u` the
joint's velocity in the link frame, `omega` the link frame's angular rate and
`v_dot(x)` the elastic rate. (The slope of the deflected link tilts the normal by
`v'(x)`; that changes `v_n` at second order in the deflection and is neglected, like
axial shortening in the kinematics.) The generalised force is the gradient of the
"drag potential" `D = c/3 int |v_n|^3 dx` w.r.t. `Q_dot` (because `v_n` is linear in
`Q_dot`, `-dD/dQ_dot = int f dv_n/dQ_dot dx`), by 32-point Gauss quadrature. For a
rigid link turning about a fixed joint this is the closed form `tau = -c omega |omega|
l^4 / 4`.

**Backlash** of an elastic joint's gear: the spring acts on a smoothed dead zone of
the deflection `delta = alpha - theta`,

    dz(delta) = delta - b tanh(delta / b),       V = k int dz = k (delta^2 / 2 - b^2 log cosh(delta / b))

(`b = joint.backlash` [rad]): `dz ~ delta^3 / (3 b^2)` inside the gap, `delta - b sign(delta)`
outside, and `dz = delta` for `b = 0` (the linear spring, exactly). The potential is
closed-form, so energy conservation holds with backlash too.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .kinematics import frames_and_rates, modal_slice, rotation_matrix
from .modes import evaluate_shapes

# Gauss-Legendre nodes/weights on [0, 1] for the drag integral (|v_n|^3 is twice
# differentiable, so 32 points give ~1e-6 relative even where v_n changes sign).
_DRAG_N = 32
_dx, _dw = np.polynomial.legendre.leggauss(_DRAG_N)
DRAG_X = 0.5 * (_dx + 1.0)
DRAG_W = 0.5 * _dw


def log_cosh(x):
    """`log(cosh(x))` without overflow."""
    ax = jnp.abs(x)
    return ax + jnp.log1p(jnp.exp(-2.0 * ax)) - np.log(2.0)


def coulomb_torque(coulomb, rate, velocity_scale: float):
    """Smoothed dry-friction torque `-F_c tanh(rate / v_s)`, N m."""
    return -coulomb * jnp.tanh(rate / velocity_scale)


def backlash_deflection(delta, backlash):
    """Smoothed dead zone `dz(delta) = delta - b tanh(delta / b)` (rad); `delta` for `b = 0`."""
    positive = backlash > 0
    b = jnp.where(positive, backlash, 1.0)
    return delta - jnp.where(positive, b * jnp.tanh(delta / b), 0.0)


def backlash_energy(stiffness, delta, backlash):
    """Spring energy `k (delta^2 / 2 - b^2 log cosh(delta / b))`, J (`k delta^2 / 2` for `b = 0`)."""
    positive = backlash > 0
    b = jnp.where(positive, backlash, 1.0)
    return stiffness * (0.5 * delta**2 - jnp.where(positive, b**2 * log_cosh(delta / b), 0.0))


def has_nonlinear_forces(chain) -> bool:
    """True when any joint has dry friction or any link has drag (static structure)."""
    return any(j.coulomb is not None for j in chain.joints) or any(lk.drag is not None for lk in chain.links)


def drag_potential(asm, Q, Qd):
    """`D(Q, Q_dot) = sum_i c_i/3 int_0^l_i |v_n(x)|^3 dx`, W (see the module docstring)."""
    lay, chain = asm.layout, asm.chain
    f, fd = frames_and_rates(asm, Q, Qd)
    D = jnp.zeros(())
    xi = jnp.asarray(DRAG_X)
    for i, lm in enumerate(asm.links):
        c = chain.links[i].drag
        if c is None:
            continue
        x = xi * lm.length
        u = rotation_matrix(f.angle[i]).T @ fd.origin[i]
        vn = u[1] + fd.angle[i] * x
        if lay.modal[i]:
            vn = vn + evaluate_shapes(lm.lam, lm.coef, xi) @ modal_slice(lay, Qd, i)
        D = D + c / 3.0 * lm.length * (jnp.asarray(DRAG_W) @ jnp.abs(vn) ** 3)
    return D


def nonlinear_forces(asm, Q, Qd):
    """Generalised forces of dry friction and aerodynamic drag, shape (n_dof,): N m on
    angles, N on modal coordinates. Zero-size work for a chain that has neither."""
    chain, lay = asm.chain, asm.layout
    F = jnp.zeros_like(Qd)
    for i, joint in enumerate(chain.joints):
        if joint.coulomb is not None:
            k = lay.actuated[i]
            F = F.at[k].add(coulomb_torque(joint.coulomb, Qd[k], joint.coulomb_velocity))
    if any(lk.drag is not None for lk in chain.links):
        F = F - jax.grad(drag_potential, argnums=2)(asm, Q, Qd)
    return F
