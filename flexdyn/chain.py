"""A planar serial chain of rigid and flexible links: kinematics, energies and the
equations of motion.

Design note (how the equations are formed, and why they are exact)
==================================================================

**Coordinates.** Joint i contributes, in this order, the rotor angle `alpha_i`
(elastic joints only, referred to the link side), the link angle `theta_i`
(relative to the tip frame of link i-1, or to the base x axis for i = 1) and the
modal coordinates `q_i1..q_im` of link i (flexible links only, metres; see
`flexdyn.modes`); after all of them, the armature charge `charge_i` (C) of each joint
driven by a `DCMotor` with an inductance, whose rate is the motor's current
(`flexdyn.motor`). The state is `y = [Q, Q_dot]`.

**Kinematics** (papers 002/004 eq. 1-5, with the elastic rotation kept as an
angle). Link i has a body frame at its joint with origin `o_i` and absolute
angle `phi_i = psi_{i-1} + theta_i`, `psi_0 = 0`. A material point at distance
`x` along the undeformed link is at

    r_i(x) = o_i + R(phi_i) [x, v_i(x)]^T,     v_i(x) = sum_j phi_ij(x) q_ij,

(no axial shortening; small elastic deflection). The next joint is at
`o_{i+1} = r_i(l_i)` and the tip frame turns with the tip slope,
`psi_i = phi_i + v_i'(l_i)`. Papers 002/004 write the last step with the
linearised rotation `E_i = [[1, -v'], [v', 1]]`; we add the slope to the angle,
which is the same to first order and keeps `R` orthogonal. Large rigid
rotations are exact; no small-angle assumption is made anywhere.

**Geometric stiffening** (`FlexibleLink(geometric_stiffening=True)`). The linear
kinematics above keep every point at its undeformed axial station `x`, so a bent link
gets longer, and nothing resists bending but `EI`: a spinning link's centrifugal load
then *softens* its in-plane modes (`-1/2 omega^2 q^T Mq q` in `V - T`), and a floppy
link spinning faster than its first frequency diverges. With the option, the centreline
keeps its length to second order in the deflection: the point at `x` is at
`[x + u(x), v(x)]` with the axial shortening (the "foreshortening" of Kane, Ryan &
Banerjee, J. Guidance 10 (1987) 139; Banerjee & Dickens, J. Guidance 13 (1990) 221)

    u(x) = -1/2 int_0^x v'(s)^2 ds = -1/2 q^T G(x) q,    G(x) = int_0^x phi' phi'^T ds.

The distal parts ride on the shortened tip `[l + u(l), v(l)]` exactly, and the link's
own kinetic and gravitational energies gain, to second order in `(q, q_dot)` (terms
of third order, e.g. `omega v u_dot`, dropped):

    T += -u_x (q^T H0 q_dot) - 1/2 u_y omega (q^T H0 q) - 1/2 omega^2 (q^T H1 q),
    int rho r += R(phi) [-1/2 q^T H0 q, 0],

`H0 = int rho G(x) dx`, `H1 = int rho x G(x) dx` (`LinkMatrices`). For a link spinning
at a steady rate `Omega` about a fixed joint, `-1/2 Omega^2 q^T H1 q` is the potential
`1/2 int N(x) v'^2` of the centrifugal tension `N(x) = rho Omega^2 (l^2 - x^2)/2`: the
in-plane rotating-beam equation `EI v'''' - (N v')' - rho Omega^2 v = -rho v_tt` is
recovered (tested against an independent Rayleigh-Ritz solution and the published
frequencies of rotating cantilevers). Gravity does the same through the `H0` term:
tension in a hanging link, compression in a standing one (tested against Greenhill's
self-weight buckling load, `rho g l^3 / EI = 7.837`). `T` stays a quadratic form in
`Q_dot`, so energy is still conserved exactly. Not included: the shortening in the
aerodynamic drag's normal velocity (`omega u`, second order) and axial elasticity.

**Kinetic energy.** With `w = [u, omega, q_dot]` (origin velocity `u = R^T
o_dot` in the body frame, `omega = phi_dot`) the link's kinetic energy is, exactly
for the kinematics above,

    T_i = 1/2 m |u|^2 - u_x omega (a.q) + u_y (omega c1 + a.q_dot)
          + 1/2 omega^2 (c2 + q^T Mq q) + omega (b.q_dot) + 1/2 q_dot^T Mq q_dot

with the constant shape integrals `m = int rho`, `c1 = int rho x`, `c2 = int rho
x^2`, `a_j = int rho phi_j`, `b_j = int rho x phi_j`, `Mq_jk = int rho phi_j phi_k`
(Gauss-Legendre quadrature, exact to double precision). The `omega^2 q^T Mq q`
term is paper 000's `S1 b^2 theta_ddot` term (eq. 10); nothing quadratic in the
deflection is dropped. A rigid link is the same expression with no modes,
`c1 = m com`, `c2 = I_c + m com^2`. Hubs add `1/2 m_h |o_dot_i|^2 + 1/2 J_h
phi_dot_i^2`, the payload `1/2 M_p |o_dot_{n+1}|^2 + 1/2 I_p psi_dot_n^2`, rotors
`1/2 I_r (psi_dot_{i-1} + G s_dot_i)^2` (`s = alpha` or `theta`; with
`spong_approximation`, `1/2 G^2 I_r s_dot^2` as in paper 004 eq. 7).

**Potential energy.** Bending `1/2 q^T K q`, `K_jk = EI int phi_j'' phi_k''`
(paper 004 eq. 19-20), joint springs `1/2 k_s (alpha - theta)^2` (eq. 21), and
gravity `-g . sum(mass-weighted positions)`, with `int rho r_i = m o_i + R(phi_i)
[c1, a.q]` exactly; `g` is any vector in the plane (vertical-plane pendulums of
paper 000, horizontal arms of papers 002/004 with `g = 0`).

**Equations of motion.** Lagrange's equations

    M(Q) Q_ddot + (d/dQ (M(Q) Q_dot)) Q_dot - dT/dQ = F - dV/dQ - dR/dQ_dot

are formed by automatic differentiation of the scalar `T(Q, Q_dot)`: `M` is its
Hessian in `Q_dot`, the velocity terms are a forward-mode derivative of
`dT/dQ_dot` along `Q_dot` minus a gradient. No Christoffel symbol is typed by
hand, so the velocity terms are exactly those of `T` (this is what the
energy-conservation tests check). `R` is the Rayleigh dissipation (joint
viscous damping, modal damping `D`).

**Derivatives of the forward dynamics.** `accelerations` solves `M Q_ddot = F - h`
with a Cholesky factorisation, but is not differentiated through it: its tangent
comes from the implicit-function theorem on the Lagrange residual
`r = d/dt (dT/dQ_dot) - dT/dQ - F`, which is formed without `M` (one forward
derivative of the momentum along `(Q_dot, Q_ddot)`): `dQ_ddot = -M^-1 dr` at fixed
`Q_ddot`, with the factor of the primal solve. Reverse mode transposes that rule.
Forward-mode Jacobians and gradients through a solve are then a few right-hand
sides per step rather than `n` (tested against AD through the hand-written
equations of `flexdyn.denoc` and against finite differences).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jaxtyping import Array, Float

from ._checks import NONNEGATIVE, POSITIVE, as_float_array, checked_part
from .kinematics import frames, modal_slice, quadratic_of, reach_length, stiffening_of
from .modes import GAUSS_W, GAUSS_X, evaluate_shapes, mode_shapes
from .motor import DCMotor, joint_torque, motor_torque, saturated
from .nonlinear import backlash_energy, has_nonlinear_forces, nonlinear_forces
from .parts import ElasticJoint, FlexibleLink, Hub, Payload, RigidJoint, RigidLink

Link = RigidLink | FlexibleLink


Joint = RigidJoint | ElasticJoint


class Chain(eqx.Module):
    """A planar serial chain: the model every rig of the papers is a case of.

    **Arguments:**
    - `links`: tuple of `RigidLink` / `FlexibleLink`, from the base outwards.
    - `joints`: tuple of `RigidJoint` / `ElasticJoint`; joint i drives link i.
    - `hubs`: tuple of `Hub`, one per joint (default: massless).
    - `payload`: `Payload` at the tip of the last link (default: none).
    - `gravity`: gravitational acceleration in the base frame, m/s^2, shape (2,)
      (default `(0, 0)`: a horizontal-plane arm; a vertical pendulum has `(0, -9.81)`).
    - `motors`: tuple of `flexdyn.DCMotor` or `None`, one per joint (default: none, every
      joint driven by its torque input directly). A joint with a motor reads its input as
      the motor's command (a voltage, a current or a torque: `DCMotor.drive`); see
      `flexdyn.motor`.
    """

    links: tuple[Link, ...]
    joints: tuple[Joint, ...]
    hubs: tuple[Hub, ...]
    payload: Payload
    gravity: Float[Array, "2"]
    motors: tuple[DCMotor | None, ...]

    def __init__(self, links, joints=None, hubs=None, payload=None, gravity=(0.0, 0.0), motors=None):
        for name, parts in (("links", links), ("joints", joints), ("hubs", hubs), ("motors", motors)):
            if isinstance(parts, eqx.Module):
                raise TypeError(
                    f"Chain.{name}: expected a list of parts, one per link "
                    f"(e.g. {name}=[{type(parts).__name__}(...)]), got a single {type(parts).__name__}"
                )
        links = tuple(links)
        n = len(links)
        if n == 0:
            raise ValueError("Chain.links: expected at least one link")
        joints = tuple(RigidJoint() for _ in range(n)) if joints is None else tuple(joints)
        hubs = tuple(Hub() for _ in range(n)) if hubs is None else tuple(hubs)
        motors = (None,) * n if motors is None else tuple(motors)
        for name, parts, kinds in (
            ("links", links, (RigidLink, FlexibleLink)),
            ("joints", joints, (RigidJoint, ElasticJoint)),
            ("hubs", hubs, (Hub,)),
            ("motors", motors, (DCMotor, type(None))),
        ):
            if len(parts) != n:
                raise ValueError(f"Chain.{name}: expected {n} entries (one per link), got {len(parts)}")
            for k, part in enumerate(parts):
                if not isinstance(part, kinds):
                    expected = " or ".join("None" if t is type(None) else t.__name__ for t in kinds)
                    raise ValueError(f"Chain.{name}[{k}]: expected {expected}, got {type(part).__name__}")
        self.links, self.joints, self.hubs, self.motors = links, joints, hubs, motors
        self.payload = Payload() if payload is None else payload
        if not isinstance(self.payload, Payload):
            raise ValueError(f"Chain.payload: expected Payload, got {type(self.payload).__name__}")
        self.gravity = as_float_array(gravity)
        if tuple(np.shape(self.gravity)) != (2,):
            raise ValueError(f"Chain.gravity: expected shape (2,) [m/s^2], got {np.shape(self.gravity)}")
        if not isinstance(self.gravity, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(self.gravity))):
            raise ValueError(f"Chain.gravity: expected finite values [m/s^2], got {np.asarray(self.gravity)}")

    # -- structure (static) --------------------------------------------------
    @property
    def n_links(self) -> int:
        return len(self.links)

    @property
    def layout(self) -> Layout:
        return layout(self)

    @property
    def n_dof(self) -> int:
        return self.layout.n_dof

    def coordinate_names(self) -> list[str]:
        """Names of the generalised coordinates, e.g. `['theta1', 'q1_1', 'q1_2', ...]`."""
        return list(self.layout.names)


class Layout(NamedTuple):
    """Static index map of the generalised coordinates."""

    rotor: tuple[int | None, ...]  # index of alpha_i, or None for a rigid joint
    theta: tuple[int, ...]
    modal: tuple[tuple[int, ...], ...]
    actuated: tuple[int, ...]  # coordinate each joint torque acts on
    names: tuple[str, ...]
    charge: tuple[int | None, ...] = ()  # armature charge of an inductive motor (flexdyn.motor), or None

    @property
    def n_dof(self) -> int:
        return len(self.names)


def layout(chain: Chain) -> Layout:
    rotor, theta, modal, actuated, names = [], [], [], [], []
    k = 0
    for i, (link, joint) in enumerate(zip(chain.links, chain.joints), start=1):
        if joint.elastic:
            rotor.append(k)
            actuated.append(k)
            names.append(f"alpha{i}")
            k += 1
        else:
            rotor.append(None)
            actuated.append(k)
        theta.append(k)
        names.append(f"theta{i}")
        k += 1
        idx = tuple(range(k, k + link.n_modes))
        modal.append(idx)
        names.extend(f"q{i}_{j}" for j in range(1, link.n_modes + 1))
        k += link.n_modes
    charge = []  # after every mechanical coordinate, so that theirs do not move
    for i, motor in enumerate(chain.motors, start=1):
        if motor is not None and motor.inductive:
            charge.append(k)
            names.append(f"charge{i}")
            k += 1
        else:
            charge.append(None)
    return Layout(tuple(rotor), tuple(theta), tuple(modal), tuple(actuated), tuple(names), tuple(charge))


class LinkMatrices(eqx.Module):
    """Constant shape integrals of one link (SI units). A rigid link has no modes.

    `mass = int rho dx`, `c1 = int rho x dx`, `c2 = int rho x^2 dx` (about the joint),
    `a = int rho phi dx`, `b = int rho x phi dx`, `modal_mass = int rho phi phi^T dx`,
    `stiffness = EI int phi'' phi''^T dx`, `damping` (modal), `tip_shape = phi(l)`,
    `tip_slope = phi'(l)` [1/m], `root_curvature = phi''(0)` [1/m^2], `lam = beta l`,
    `coef` (shape coefficients, `flexdyn.modes`), `frequency` = clamped-mass
    natural frequencies [rad/s]. With geometric stiffening (zero otherwise):
    `shortening = int phi' phi'^T dx` [1/m] (the tip moves in by `1/2 q^T shortening q`),
    `shortening_mass = int rho G(x) dx = int rho (l - x) phi' phi'^T dx` [kg/m] and
    `shortening_moment = int rho x G(x) dx = int rho (l^2 - x^2)/2 phi' phi'^T dx` [kg],
    `G(x) = int_0^x phi' phi'^T`.
    """

    length: Array
    mass: Array
    c1: Array
    c2: Array
    a: Array
    b: Array
    modal_mass: Array
    stiffness: Array
    damping: Array
    tip_shape: Array
    tip_slope: Array
    root_curvature: Array
    lam: Array
    coef: Array
    frequency: Array
    tip_load: Array  # (M, S, J) used for the clamped-mass shapes
    shortening: Array
    shortening_mass: Array
    shortening_moment: Array


class AssembledChain(eqx.Module):
    """A `Chain` with its mode shapes solved and shape integrals evaluated."""

    chain: Chain
    links: tuple[LinkMatrices, ...]

    @property
    def layout(self) -> Layout:
        return layout(self.chain)


def _rigid_moments(link):
    """(mass, first moment, second moment) about the joint of the undeformed link."""
    if isinstance(link, RigidLink):
        m = link.mass
        return m, m * link.com, link.inertia + m * link.com**2
    m = link.rho * link.length
    return m, m * link.length / 2.0, m * link.length**2 / 3.0


def tip_load(chain: Chain, i: int):
    """Mass M, first moment S and inertia J (about the tip of link i) of everything
    distal to link i, in the straight configuration with the distal joints locked:
    paper 004 eq. (47)-(48) (`M_E`, `M_DE`, `I_E`), computed for any chain."""
    M = S = J = jnp.zeros(())
    x = jnp.zeros(())
    for k in range(i + 1, chain.n_links):
        hub, joint, link = chain.hubs[k], chain.joints[k], chain.links[k]
        rotor = jnp.zeros(()) if joint.spong_approximation else joint.rotor_inertia
        M, S, J = M + hub.mass, S + hub.mass * x, J + hub.inertia + rotor + hub.mass * x**2
        m, c1, c2 = _rigid_moments(link)
        M, S, J = M + m, S + m * x + c1, J + c2 + 2.0 * x * c1 + m * x**2
        x = x + link.length
    p = chain.payload
    return M + p.mass, S + p.mass * x, J + p.inertia + p.mass * x**2


def _assemble_link(chain: Chain, i: int) -> LinkMatrices:
    link = chain.links[i]
    length = link.length
    mass, c1, c2 = _rigid_moments(link)
    M, S, J = tip_load(chain, i)
    empty = jnp.zeros((0,))
    if isinstance(link, RigidLink):
        return LinkMatrices(
            length,
            mass,
            c1,
            c2,
            empty,
            empty,
            jnp.zeros((0, 0)),
            jnp.zeros((0, 0)),
            jnp.zeros((0, 0)),
            empty,
            empty,
            empty,
            empty,
            jnp.zeros((0, 4)),
            empty,
            jnp.stack([M, S, J]),
            jnp.zeros((0, 0)),
            jnp.zeros((0, 0)),
            jnp.zeros((0, 0)),
        )
    rho = link.rho
    EI = link.EI
    n = link.n_modes
    lam, coef = mode_shapes(n, M / (rho * length), S / (rho * length**2), J / (rho * length**3))
    xi = jnp.asarray(GAUSS_X)
    w = jnp.asarray(GAUSS_W) * length  # weights for dx
    phi = evaluate_shapes(lam, coef, xi)  # (G, n)
    phi2 = evaluate_shapes(lam, coef, xi, 2) / length**2
    x = xi * length
    a = rho * (w @ phi)
    b = rho * ((w * x) @ phi)
    modal_mass = rho * (phi.T * w) @ phi
    stiffness = EI * (phi2.T * w) @ phi2
    one, zero = jnp.ones((1,)), jnp.zeros((1,))
    tip_shape = evaluate_shapes(lam, coef, one)[0]
    tip_slope = evaluate_shapes(lam, coef, one, 1)[0] / length
    root_curvature = evaluate_shapes(lam, coef, zero, 2)[0] / length**2
    frequency = lam**2 / length**2 * jnp.sqrt(EI / rho)
    generalised_mass = jnp.diag(modal_mass) + M * tip_shape**2 + 2.0 * S * tip_shape * tip_slope + J * tip_slope**2
    k_diag = jnp.diag(stiffness)
    d = 2.0 * link.damping_ratio * jnp.sqrt(k_diag * generalised_mass) + link.sqrt_stiffness_damping * jnp.sqrt(k_diag)
    if link.geometric_stiffening:
        slope = evaluate_shapes(lam, coef, xi, 1) / length  # phi'(x), 1/m
        # double integrals int_0^l f(x) int_0^x phi' phi'^T, with the order of integration swapped
        shortening = (slope.T * w) @ slope
        shortening_mass = rho * (slope.T * (w * (length - x))) @ slope
        shortening_moment = rho * (slope.T * (w * 0.5 * (length**2 - x**2))) @ slope
    else:
        shortening = shortening_mass = shortening_moment = jnp.zeros((n, n))
    return LinkMatrices(
        length,
        mass,
        c1,
        c2,
        a,
        b,
        modal_mass,
        stiffness,
        jnp.diag(d),
        tip_shape,
        tip_slope,
        root_curvature,
        lam,
        coef,
        frequency,
        jnp.stack([M, S, J]),
        shortening,
        shortening_mass,
        shortening_moment,
    )


def assemble(chain: Chain | AssembledChain) -> AssembledChain:
    """Solve the clamped-mass mode shapes of every flexible link and evaluate the shape
    integrals. Pure and differentiable; call it inside `jit` with the chain as input."""
    if isinstance(chain, AssembledChain):
        return chain
    chain = checked_chain(chain)
    return AssembledChain(chain, tuple(_assemble_link(chain, i) for i in range(chain.n_links)))


def checked_chain(chain: Chain) -> Chain:
    """The chain with every part's parameters checked (`flexdyn._checks.checked_part`,
    named as in `flexdyn.with_parameters`: `link1.EI`, `hub2.inertia`, `payload.mass`):
    finite, and > 0 or >= 0 where the part's constructor requires it. Values set after
    construction (`eqx.tree_at`, `with_parameters`) and traced values (under jit, vmap or
    grad: an `eqx.error_if` at run time) are held to the constructor's rules."""
    return Chain(
        links=[checked_part(p, f"link{i + 1}") for i, p in enumerate(chain.links)],
        joints=[checked_part(p, f"joint{i + 1}") for i, p in enumerate(chain.joints)],
        hubs=[checked_part(p, f"hub{i + 1}") for i, p in enumerate(chain.hubs)],
        payload=checked_part(chain.payload, "payload"),
        gravity=chain.gravity,
        motors=[None if m is None else checked_motor(m, f"motor{i + 1}") for i, m in enumerate(chain.motors)],
    )


def checked_motor(motor: DCMotor, owner: str) -> DCMotor:
    """`checked_part` for a motor, and its efficiency at most 1 (a run-time check when traced)."""
    motor = checked_part(motor, owner)
    eta = motor.efficiency
    message = f"{owner}.efficiency must be <= 1"
    if not isinstance(eta, jax.core.Tracer):
        if not float(eta) <= 1.0:
            raise ValueError(f"{message}, got {float(eta):g}")
        return motor
    return eqx.tree_at(lambda m: m.efficiency, motor, eqx.error_if(eta, eta > 1.0, message))


def check_batch(chain: Chain, caller: str) -> None:
    """Check a concrete batch of chains (parameters with a leading batch axis) on the host,
    with the rules `checked_chain` applies inside the computation, and raise a `ValueError`
    naming the parameter and the batch entries: under `vmap` the assembly's `eqx.error_if`
    can say only "payload.mass must be finite and >= 0". Parameters
    without a batch axis, and traced ones, are left to `checked_chain`."""
    parts = (
        [(f"link{i + 1}", p) for i, p in enumerate(chain.links)]
        + [(f"joint{i + 1}", p) for i, p in enumerate(chain.joints)]
        + [(f"hub{i + 1}", p) for i, p in enumerate(chain.hubs)]
        + [("payload", chain.payload)]
        + [(f"motor{i + 1}", p) for i, p in enumerate(chain.motors) if p is not None]
    )
    for owner, part in parts:
        for name, kind in part.PARAMETERS:
            value = getattr(part, name)
            batched = np.ndim(value) >= (2 if name == "damping_ratio" else 1)
            if value is None or isinstance(value, jax.core.Tracer) or not batched:
                continue
            arr = np.asarray(value, dtype=float)
            rows = arr.reshape(arr.shape[0], -1)
            bad = ~np.isfinite(rows)
            if kind == POSITIVE:
                bad |= rows <= 0
            elif kind == NONNEGATIVE:
                bad |= rows < 0
            entries = np.flatnonzero(bad.any(axis=1))
            if entries.size:
                shown = ", ".join(f"{k} ({np.array2string(arr[k], precision=6)})" for k in entries[:5])
                more = f", ... ({entries.size} in all)" if entries.size > 5 else ""
                expected = {POSITIVE: "finite and > 0", NONNEGATIVE: "finite and >= 0"}.get(kind, "finite")
                raise ValueError(
                    f"{caller}: {owner}.{name} expected {expected} in every batch entry; "
                    f"entr{'y' if entries.size == 1 else 'ies'} {shown}{more} of {arr.shape[0]}"
                )


def kinetic_energy(asm: AssembledChain | Chain, Q, Qd):
    """Total kinetic energy T(Q, Q_dot), J (formula in the module docstring).

    Written on scalar components (`o = (o_x, o_y)`, `R(phi)` as `cos`/`sin` products; the
    velocity recursion of `frames_and_rates` inlined) rather than 2-vectors and 2 x 2
    matrices: `M` and the velocity terms are derivatives of this function, and on the CPU
    XLA fuses scalar arithmetic into a few kernels where every tiny `dot` is a library
    call of its own, and under `vmap` the scalars become contiguous batch vectors (the
    measured gain: `docs/performance.md`)."""
    asm = assemble(asm)
    check_coordinates(asm.layout, Q, "kinetic_energy")
    check_coordinates(asm.layout, Qd, "kinetic_energy", "Qd")
    lay, chain = asm.layout, asm.chain
    zero = jnp.zeros((), Q.dtype)
    vx = vy = psi = psi_dot = zero  # o_dot of the current joint, tip angle and rate of the previous link
    T = zero
    for i, lm in enumerate(asm.links):
        q, qd = modal_slice(lay, Q, i), modal_slice(lay, Qd, i)
        carrier_rate = psi_dot
        phi = psi + Q[lay.theta[i]]
        omega = psi_dot + Qd[lay.theta[i]]
        c, s = jnp.cos(phi), jnp.sin(phi)
        ux, uy = c * vx + s * vy, c * vy - s * vx  # R(phi)^T o_dot
        aq, aqd, bqd = jnp.sum(lm.a * q), jnp.sum(lm.a * qd), jnp.sum(lm.b * qd)
        qdMqd = jnp.sum(qd[:, None] * lm.modal_mass * qd[None, :])
        c1 = lm.c1
        if stiffening_of(asm, i):  # the axial shortening u(x) = -1/2 q^T G(x) q, to second order:
            # c1 -> c1 - 1/2 q^T H0 q, Mq -> Mq - H1 in the omega^2 term, and -u_x q^T H0 q_dot
            H0q = jnp.sum(lm.shortening_mass * q[None, :], axis=1)
            c1 = c1 - 0.5 * jnp.sum(q * H0q)
            qMq = quadratic_of(lm.modal_mass - lm.shortening_moment, q, q)
            T = T - ux * jnp.sum(qd * H0q)
        else:
            qMq = jnp.sum(q[:, None] * lm.modal_mass * q[None, :])
        T = T + 0.5 * lm.mass * (ux * ux + uy * uy)
        T = T + 0.5 * omega**2 * (lm.c2 + qMq) + uy * omega * c1
        T = T - ux * omega * aq + uy * aqd + omega * bqd + 0.5 * qdMqd
        hub, joint = chain.hubs[i], chain.joints[i]
        T = T + 0.5 * hub.mass * (vx * vx + vy * vy) + 0.5 * hub.inertia * omega**2
        s_dot = Qd[lay.actuated[i]]
        if joint.spong_approximation:
            T = T + 0.5 * joint.rotor_inertia * (joint.gear_ratio * s_dot) ** 2
        else:
            T = T + 0.5 * joint.rotor_inertia * (carrier_rate + joint.gear_ratio * s_dot) ** 2
        # next joint: o_dot += omega S R(phi) [l, d] + R(phi) [0, d_dot] (the position o itself is not needed)
        d, d_dot = jnp.sum(lm.tip_shape * q), jnp.sum(lm.tip_shape * qd)
        if stiffening_of(asm, i):  # the tip also moves along the link as it bends: + R(phi) [reach_dot, 0]
            Gq = jnp.sum(lm.shortening * q[None, :], axis=1)
            reach, reach_dot = lm.length - 0.5 * jnp.sum(q * Gq), -jnp.sum(qd * Gq)
        else:
            reach, reach_dot = lm.length, None
        ax, ay = c * reach - s * d, s * reach + c * d
        vx, vy = vx - omega * ay - s * d_dot, vy + omega * ax + c * d_dot
        if reach_dot is not None:
            vx, vy = vx + c * reach_dot, vy + s * reach_dot
        psi = phi + jnp.sum(lm.tip_slope * q)
        psi_dot = omega + jnp.sum(lm.tip_slope * qd)
    p = chain.payload
    T = T + 0.5 * p.mass * (vx * vx + vy * vy) + 0.5 * p.inertia * psi_dot**2
    for motor, k in zip(chain.motors, lay.charge):
        if k is not None:  # the armature's magnetic energy, 1/2 L i^2 (flexdyn.motor)
            T = T + 0.5 * motor.inductance * Qd[k] ** 2
    return T


def potential_energy(asm: AssembledChain | Chain, Q):
    """Gravity + bending + joint-spring potential energy V(Q), J. Zero at Q = 0 for the
    elastic parts; the gravity datum is the base joint. (Scalar components, as
    `kinetic_energy`; the position recursion of `frames` inlined.)"""
    asm = assemble(asm)
    check_coordinates(asm.layout, Q, "potential_energy")
    lay, chain = asm.layout, asm.chain
    zero = jnp.zeros((), Q.dtype)
    ox = oy = psi = zero
    wx = wy = zero  # sum of mass-weighted positions, kg m
    V = zero
    for i, lm in enumerate(asm.links):
        q = modal_slice(lay, Q, i)
        phi = psi + Q[lay.theta[i]]
        c, s = jnp.cos(phi), jnp.sin(phi)
        aq = jnp.sum(lm.a * q)
        m = lm.mass + chain.hubs[i].mass
        c1 = lm.c1 - 0.5 * quadratic_of(lm.shortening_mass, q, q) if stiffening_of(asm, i) else lm.c1
        wx = wx + m * ox + c * c1 - s * aq  # + R(phi) [c1 + int rho u, a.q]
        wy = wy + m * oy + s * c1 + c * aq
        V = V + 0.5 * jnp.sum(q[:, None] * lm.stiffness * q[None, :])
        joint = chain.joints[i]
        if joint.elastic:
            delta = Q[lay.rotor[i]] - Q[lay.theta[i]]
            if joint.backlash is None:
                V = V + 0.5 * joint.stiffness * delta**2
            else:
                V = V + backlash_energy(joint.stiffness, delta, joint.backlash)
        d, reach = jnp.sum(lm.tip_shape * q), reach_length(asm, i, q)
        ox, oy = ox + c * reach - s * d, oy + s * reach + c * d
        psi = phi + jnp.sum(lm.tip_slope * q)
    mp = chain.payload.mass
    wx, wy = wx + mp * ox, wy + mp * oy
    return V - (chain.gravity[0] * wx + chain.gravity[1] * wy)


def dissipation(asm: AssembledChain, Qd):
    """Rayleigh dissipation function R(Q_dot), W: joint and modal viscous damping."""
    lay, chain = asm.layout, asm.chain
    R = jnp.zeros(())
    for i, lm in enumerate(asm.links):
        joint = chain.joints[i]
        R = R + 0.5 * joint.damping * Qd[lay.actuated[i]] ** 2
        if joint.elastic:
            R = R + 0.5 * joint.spring_damping * (Qd[lay.rotor[i]] - Qd[lay.theta[i]]) ** 2
        qd = modal_slice(lay, Qd, i)
        R = R + 0.5 * jnp.sum(qd[:, None] * lm.damping * qd[None, :])
    for motor, k in zip(chain.motors, lay.charge):
        if k is not None:  # the armature's resistance, 1/2 R i^2 (flexdyn.motor)
            R = R + 0.5 * motor.resistance * Qd[k] ** 2
    return R


def total_energy(asm: AssembledChain | Chain, Q, Qd):
    """`kinetic_energy + potential_energy`, J (conserved without damping and input)."""
    asm = assemble(asm)
    return kinetic_energy(asm, Q, Qd) + potential_energy(asm, Q)


def mass_matrix(asm: AssembledChain | Chain, Q) -> Float[Array, "n n"]:
    """Generalised mass matrix M(Q) = d^2 T / dQ_dot^2 (T is exactly quadratic in Q_dot)."""
    asm = assemble(asm)
    check_coordinates(asm.layout, Q, "mass_matrix")  # (a short Q would give a smaller M)
    zero = jnp.zeros_like(Q)
    return jax.jacfwd(jax.grad(kinetic_energy, argnums=2), argnums=2)(asm, Q, zero)


def velocity_terms(asm: AssembledChain | Chain, Q, Qd) -> Float[Array, " n"]:
    """Coriolis/centrifugal vector h = (d/dQ (M Q_dot)) Q_dot - dT/dQ: the momentum
    `p = dT/dQ_dot` differentiated forward along `Q_dot`, minus a gradient."""
    asm = assemble(asm)
    momentum = lambda Q_: jax.grad(kinetic_energy, argnums=2)(asm, Q_, Qd)  # noqa: E731
    _, mdot_qd = jax.jvp(momentum, (Q,), (Qd,))
    return mdot_qd - jax.grad(kinetic_energy, argnums=1)(asm, Q, Qd)


def mass_and_velocity_terms(asm: AssembledChain | Chain, Q, Qd):
    """`(M(Q), h(Q, Q_dot))`, see `mass_matrix` and `velocity_terms` (three separate AD
    passes: they compile to a smaller, faster graph than one vmapped jvp over n + 1
    tangents)."""
    asm = assemble(asm)
    return mass_matrix(asm, Q), velocity_terms(asm, Q, Qd)


def input_matrix(asm: AssembledChain | Chain) -> Float[Array, "n n_joints"]:
    """B such that the generalised force of joint torques tau [N m] is B tau."""
    lay = assemble(asm).layout if isinstance(asm, AssembledChain) else layout(asm)
    B = np.zeros((lay.n_dof, len(lay.actuated)))
    for j, k in enumerate(lay.actuated):
        B[k, j] = 1.0
    return jnp.asarray(B)


def has_motors(chain: Chain) -> bool:
    """True when any joint is driven by a `DCMotor` (static structure)."""
    return any(m is not None for m in chain.motors)


def motor_forces(asm: AssembledChain, Qd, inputs):
    """The generalised forces of the motors, shape (n_dof,), for the joints' inputs
    `inputs` (their commands, V, A or N m, per `DCMotor.drive`; a joint without a motor:
    its torque, N m): each motor's joint torque (`flexdyn.motor.joint_torque`) on its
    joint's actuated coordinate, with the quasi-static current, or with the current
    `Qd[charge]` of an inductive motor, whose charge coordinate gets the armature's
    voltage balance `V - K_t w` (the resistance's `R i` is in `dissipation`, `L di/dt` in
    the kinetic energy). A joint without a motor gets its input as a torque."""
    lay, chain = asm.layout, asm.chain
    F = jnp.zeros_like(Qd)
    for j, (joint, motor) in enumerate(zip(chain.joints, chain.motors)):
        s = lay.actuated[j]
        if motor is None:
            F = F.at[s].add(inputs[j])
            continue
        G, s_dot = joint.gear_ratio, Qd[s]
        if motor.inductive:
            k = lay.charge[j]
            current, w = Qd[k], G * s_dot
            F = F.at[s].add(joint_torque(motor, G, current, s_dot))
            F = F.at[k].add(saturated(motor, inputs[j]) - motor.torque_constant * w)
        else:
            F = F.at[s].add(motor_torque(motor, G, inputs[j], s_dot))
    return F


def generalised_forces(asm: AssembledChain, Q, Qd, torque):
    """F - dV/dQ - dR/dQ_dot (+ dry friction and drag, `flexdyn.nonlinear`) for joint
    torques `torque` [N m] (for a joint with a motor: its command, `motor_forces`)."""
    drive = motor_forces(asm, Qd, torque) if has_motors(asm.chain) else input_matrix(asm) @ torque
    F = drive - jax.grad(potential_energy, argnums=1)(asm, Q) - jax.grad(dissipation, argnums=1)(asm, Qd)
    if has_nonlinear_forces(asm.chain):
        F = F + nonlinear_forces(asm, Q, Qd)
    return F


def accelerations(asm: AssembledChain | Chain, Q, Qd, torque) -> Float[Array, " n"]:
    """Forward dynamics: Q_ddot = M^-1 (F - dV/dQ - dR/dQ_dot - h).

    Differentiated by the implicit-function rule of `_forward_dynamics` (not through the
    construction of `M`), so forward- and reverse-mode derivatives through a solve cost a
    few right-hand sides, not `n` of them."""
    asm = assemble(asm)
    Q, Qd = jnp.asarray(Q), jnp.asarray(Qd)
    torque = jnp.asarray(torque, dtype=jnp.result_type(Q.dtype, jnp.asarray(torque).dtype, float))
    dynamic, static = eqx.partition(asm, eqx.is_inexact_array)
    return _forward_dynamics(static, dynamic, Q, Qd, torque)


def lagrange_residual(asm: AssembledChain, Q, Qd, Qdd, torque):
    """`d/dt (dT/dQ_dot) - dT/dQ - F` along `(Q_dot, Q_ddot)`, = `M Q_ddot + h - F`, formed
    without `M`: the momentum `p = dT/dQ_dot` differentiated forward along `(Q_dot, Q_ddot)`
    gives `M_dot Q_dot + M Q_ddot` in one Jacobian-vector product."""
    momentum = lambda Q_, Qd_: jax.grad(kinetic_energy, argnums=2)(asm, Q_, Qd_)  # noqa: E731
    _, p_dot = jax.jvp(momentum, (Q, Qd), (Qd, Qdd))
    return p_dot - jax.grad(kinetic_energy, argnums=1)(asm, Q, Qd) - generalised_forces(asm, Q, Qd, torque)


# `solve_forward_dynamics` and `_forward_dynamics_and_tangent` are jitted so that JAX
# traces each once per structure and shapes and reuses the jaxpr: one trace of `simulate`
# calls the vector field four times, a fit traces the model in each of its programs, and
# each trace of the forward dynamics is seconds of Python (the energies' derivatives).
# Inside an outer `jit` the nested programs are inlined by XLA, so the compiled code is
# the same (the tracing time saved: `docs/performance.md`).
@eqx.filter_jit
def solve_forward_dynamics(asm: AssembledChain, Q, Qd, torque):
    M, h = mass_and_velocity_terms(asm, Q, Qd)
    factor = jsl.cho_factor(M)
    return jsl.cho_solve(factor, generalised_forces(asm, Q, Qd, torque) - h), factor


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _forward_dynamics(static, dynamic, Q, Qd, torque):
    return solve_forward_dynamics(eqx.combine(dynamic, static), Q, Qd, torque)[0]


@_forward_dynamics.defjvp
def _forward_dynamics_jvp(static, primals, tangents):
    r"""Tangent of `Q_ddot` by the implicit-function theorem on the Lagrange residual
    `r(x, Q_ddot) = M(Q) Q_ddot + h(Q, Q_dot) - F(Q, Q_dot, tau) = 0` (`x`: the parameters,
    `Q`, `Q_dot`, `tau`): `dQ_ddot = -M^-1 (dr/dx . dx)` at fixed `Q_ddot`, with `M`'s
    Cholesky factor from the primal solve.

    Differentiating the primal instead pushes every tangent through the `n` columns of
    `M = d^2 T / dQ_dot^2` (a third-order derivative of `T`) and through the Cholesky
    factorisation. Here a tangent costs one Jacobian-vector product of the residual
    (second order in `T`, no `n`-fold work) and one triangular solve pair (measured costs:
    `docs/performance.md`). Reverse mode transposes the linear map below, so it is
    covered too."""
    return _forward_dynamics_and_tangent(static, primals, tangents)


@eqx.filter_jit
def _forward_dynamics_and_tangent(static, primals, tangents):
    dynamic, Q, Qd, torque = primals
    Qdd, factor = solve_forward_dynamics(eqx.combine(dynamic, static), Q, Qd, torque)
    residual = lambda dyn_, Q_, Qd_, tau_: lagrange_residual(eqx.combine(dyn_, static), Q_, Qd_, Qdd, tau_)  # noqa: E731
    _, d_residual = jax.jvp(residual, primals, tangents)
    return Qdd, -jsl.cho_solve(factor, d_residual)


def inverse_dynamics(asm: AssembledChain | Chain, Q, Qd, Qdd):
    """Generalised force that produces `Qdd`: M Qdd + h + dV/dQ + dR/dQ_dot (- dry
    friction and drag), formed without `M` (`lagrange_residual`)."""
    asm = assemble(asm)
    zero = jnp.zeros(len(asm.layout.actuated), dtype=Q.dtype)
    return lagrange_residual(asm, Q, Qd, Qdd, zero)


def end_point(asm: AssembledChain | Chain, Q):
    """Position of the tip of the last link (where the payload sits), m."""
    asm = assemble(asm)
    return frames(asm, Q).end


def check_coordinates(lay, Q, caller: str, name: str = "Q") -> None:
    """`Q` (or the rates `Qd`) must hold one entry per coordinate (a trace-time check)."""
    n = lay.n_dof
    if jnp.shape(Q) != (n,):
        what = f"(a mode shape, or the first half of a state: y[:{n}])" if name == "Q" else f"(y[{n}:] of a state)"
        raise ValueError(
            f"{caller}: {name} expected shape ({n},), the coordinates {list(lay.names)} {what}, got {jnp.shape(Q)}"
        )


def tip_deflections(asm: AssembledChain | Chain, Q):
    """Elastic tip deflection v_i(l_i) of every link, m (0 for rigid links)."""
    asm = assemble(asm)
    lay = asm.layout
    check_coordinates(lay, Q, "tip_deflections")
    return jnp.stack(
        [lm.tip_shape @ modal_slice(lay, Q, i) if lay.modal[i] else jnp.zeros(()) for i, lm in enumerate(asm.links)]
    )


def root_curvatures(asm: AssembledChain | Chain, Q):
    """Bending curvature v_i''(0) at each link root, 1/m (what root strain gauges read:
    strain = curvature * half thickness)."""
    asm = assemble(asm)
    lay = asm.layout
    check_coordinates(lay, Q, "root_curvatures")
    return jnp.stack(
        [
            lm.root_curvature @ modal_slice(lay, Q, i) if lay.modal[i] else jnp.zeros(())
            for i, lm in enumerate(asm.links)
        ]
    )
