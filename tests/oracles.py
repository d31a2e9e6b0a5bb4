"""Independent reference implementations ("oracles") for the physics tests.

Plain numpy / scipy / mujoco only: this module must never import jax or flexdyn,
so that the tests compare the JAX model against formulas derived separately.
All quantities are SI (kg, m, s, rad, N, N m).
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
from scipy.optimize import brentq
from scipy.special import ellipk

_BRENT_KW = dict(xtol=1e-15, rtol=4.0 * np.finfo(float).eps, maxiter=500)


# ---------------------------------------------------------------------------
# 1. Compound pendulum
# ---------------------------------------------------------------------------


def pendulum_period_small(inertia: float, m_g_lc: float) -> float:
    """Small-amplitude period of a compound pendulum.

    I th'' + m g l_c th = 0  ->  T0 = 2 pi sqrt(I / (m g l_c)).
    ``inertia`` is I about the pivot, ``m_g_lc`` the product m g l_c (N m).
    Source: any mechanics text, e.g. Thornton & Marion, Classical Dynamics, sec. 4.4.
    """
    return 2.0 * math.pi * math.sqrt(inertia / m_g_lc)


def pendulum_period_exact(inertia: float, m_g_lc: float, amplitude: float) -> float:
    """Exact period of the compound pendulum I th'' + m g l_c sin(th) = 0.

    Released from rest at th = ``amplitude`` (rad, measured from the hanging
    equilibrium):  T = 4 sqrt(I / (m g l_c)) K(k),  k = sin(amplitude / 2),
    with K the complete elliptic integral of the first kind.  scipy's
    ``ellipk`` takes the parameter m = k**2.
    Source: Thornton & Marion, Classical Dynamics, sec. 4.4 (eq. 4.41);
    Abramowitz & Stegun 17.3.  Limit amplitude -> 0 gives 2 pi sqrt(I/(m g l_c)).
    """
    k = math.sin(0.5 * amplitude)
    return 4.0 * math.sqrt(inertia / m_g_lc) * float(ellipk(k * k))


# ---------------------------------------------------------------------------
# 2./3. Clamped-free beam, with and without tip body
# ---------------------------------------------------------------------------


def _sech(x):
    """1/cosh(x) without overflow: 2 e^{-|x|} / (1 + e^{-2|x|})."""
    ax = np.abs(x)
    e = np.exp(-ax)
    return 2.0 * e / (1.0 + e * e)


def cantilever_roots(n: int) -> np.ndarray:
    """First n roots x = beta*l of the clamped-free beam equation 1 + cos x cosh x = 0.

    Solved in the bounded form  cos(x) + 1/cosh(x) = 0  (the equation divided by
    cosh x).  Root k lies within pi/4 of (k - 1/2) pi, where cos changes sign by
    +-0.707 while 1/cosh(x) < 0.75, so [(k-1/2)pi -+ pi/4] always brackets it.
    Natural frequencies omega_k = x_k^2 / l^2 sqrt(EI / (rho A)).
    Values: 1.8751040687, 4.6940911330, 7.8547574382, 10.9955407349, ...
    Source: Blevins, Formulas for Natural Frequency and Mode Shape, table 8-1;
    Meirovitch, Elements of Vibration Analysis, sec. 5.10.
    """

    def f(x):
        return math.cos(x) + float(_sech(x))

    roots = []
    for k in range(1, n + 1):
        c = (k - 0.5) * math.pi
        roots.append(brentq(f, c - 0.25 * math.pi, c + 0.25 * math.pi, **_BRENT_KW))
    return np.array(roots)


def _scan_roots(f, n, x0=1e-6, step=1e-3, chunk=50.0):
    """First n sign changes of a continuous bounded function f on (x0, inf), refined by brentq."""
    roots = []
    a = x0
    while len(roots) < n:
        xs = np.arange(a, a + chunk + 0.5 * step, step)
        fs = np.array([f(x) for x in xs])
        for i in range(len(xs) - 1):
            if fs[i] == 0.0:
                roots.append(float(xs[i]))
            elif fs[i] * fs[i + 1] < 0.0:
                roots.append(brentq(f, xs[i], xs[i + 1], **_BRENT_KW))
            if len(roots) == n:
                break
        a = xs[-1]
    return np.array(roots[:n])


def clamped_mass_roots(n: int, mu: float, j: float) -> np.ndarray:
    """First n roots x = beta*l of a clamped-free beam carrying a tip body.

    Tip point mass M and rotary inertia J (about the tip point) on a uniform
    Euler-Bernoulli cantilever of mass per length rho (= rho A), length l:
    mu = M / (rho l), j = J / (rho l^3).  Frequency equation (Ahmad et al.,
    eq. (23); Laura, Pombo & Susemihl, J. Sound Vib. 37 (1974); Blevins table 8-8):

      1 + cos x cosh x + mu x (cos x sinh x - sin x cosh x)
        - j x^3 (sin x cosh x + cos x sinh x) + mu j x^4 (1 - cos x cosh x) = 0.

    It is evaluated divided by the positive scale cosh(x) (1 + mu x + j x^3 + mu j x^4),
    scanned on a fine grid for sign changes and refined with brentq.
    Natural frequency omega = x^2 / l^2 sqrt(EI / rho).
    Checks: mu = j = 0 -> cantilever roots; mu = 1, j = 0 -> x1 = 1.2479 (Blevins).
    """
    mu = float(mu)
    j = float(j)

    def f(x):
        c, s = math.cos(x), math.sin(x)
        sh = float(_sech(x))
        th = math.tanh(x)
        mx = mu * x
        jx3 = j * x**3
        val = (sh + c) + mx * (c * th - s) - jx3 * (s + c * th) + mx * jx3 * (sh - c)
        return val / (1.0 + mx + jx3 + mx * jx3)

    return _scan_roots(f, n)


# ---------------------------------------------------------------------------
# 4. Beam pinned to a free rigid hub (no spring), optional tip body
# ---------------------------------------------------------------------------


def _hub_beam_det(x, jh, mu, j):
    """Bounded 4x4 frequency determinant of the hub-beam, x = beta l.

    Basis on xi = x_phys / l in [0, 1]: cos(x xi), sin(x xi), exp(-x xi),
    exp(x (xi - 1)); every entry is O(1) for all x.  Rows (derivatives divided
    by the matching power of beta, omega^2 = EI beta^4 / rho):
      root:  v(0) = 0
             [v''(0)/b^2 + jh x^3 v'(0)/b] / (1 + jh x^3) = 0
      tip:   [v''(l)/b^2 - j x^3 v'(l)/b] / (1 + j x^3) = 0
             [v'''(l)/b^3 + mu x v(l)] / (1 + mu x) = 0
    """
    c, s = math.cos(x), math.sin(x)
    E = math.exp(-x)
    a = jh * x**3
    bj = j * x**3
    m = mu * x
    A = np.array(
        [
            [1.0, 0.0, 1.0, E],
            [-1.0 / (1 + a), a / (1 + a), (1 - a) / (1 + a), E],
            [(-c + bj * s) / (1 + bj), (-s - bj * c) / (1 + bj), E, (1 - bj) / (1 + bj)],
            [(s + m * c) / (1 + m), (-c + m * s) / (1 + m), E * (m - 1) / (1 + m), 1.0],
        ]
    )
    return float(np.linalg.det(A))


def hub_beam_frequencies(
    n: int,
    EI: float,
    rho: float,
    length: float,
    hub_inertia: float,
    tip_mass: float = 0.0,
    tip_inertia: float = 0.0,
) -> np.ndarray:
    """Exact nonzero natural frequencies (rad/s, ascending) of a free hub + flexible beam.

    Uniform Euler-Bernoulli beam (bending stiffness EI, mass per length rho,
    length l) whose root is pinned to a rigid hub of rotary inertia J_h that
    rotates freely (no spring, no gravity, no centrifugal stiffening); linear
    theory, v(x, t) is the total small transverse displacement (rigid rotation
    plus bending) in the inertial frame, with v'(0) = theta (hub angle).
    EI v'''' = rho omega^2 v with boundary conditions
      x = 0:  v = 0,   EI v''(0) = -J_h omega^2 v'(0)   (hub: J_h theta'' = EI v''(0))
      x = l:  EI v''(l) =  J omega^2 v'(l),   EI v'''(l) = -M omega^2 v(l)
    (M, J: tip mass and tip rotary inertia).  These follow from Hamilton's principle
    for T = J_h th'^2/2 + int rho v_t^2/2 + M v_t(l)^2/2 + J v_xt(l)^2/2,
    V = int EI v_xx^2/2.  The determinant is built in the bounded basis
    cos, sin, exp(-b x), exp(b(x-l)) (see _hub_beam_det), roots x = beta l are
    found by grid scan + brentq, omega = x^2/l^2 sqrt(EI/rho).  The rigid-body
    mode omega = 0 is excluded.
    Checks: J_h -> 0 gives pinned-free roots (tan x = tanh x: 3.9266, 7.0686,
    10.2102); J_h -> inf gives the cantilever roots.
    Sources: Meirovitch, Principles and Techniques of Vibrations (boundary-value
    problem for beams with lumped end inertias);
    Bellezza, Lanari & Ulivi, "Exact modeling of the flexible slewing link", ICRA 1990.
    """
    rl = rho * length
    jh = hub_inertia / (rl * length**2)
    mu = tip_mass / rl
    j = tip_inertia / (rl * length**2)
    xs = _scan_roots(lambda x: _hub_beam_det(x, jh, mu, j), n, x0=1e-3)
    return xs**2 / length**2 * math.sqrt(EI / rho)


def hub_beam_roots(n, jh, mu=0.0, j=0.0):
    """Nondimensional roots x = beta l of the hub-beam (jh = J_h/(rho l^3), mu, j as above)."""
    return _scan_roots(lambda x: _hub_beam_det(x, jh, mu, j), n, x0=1e-3)


# ---------------------------------------------------------------------------
# 4b. Cantilever under an axial load: rotating beams, hanging and standing columns
# ---------------------------------------------------------------------------


def _clamped_legendre_basis(n_basis: int, x: np.ndarray):
    """w_k(x) = x^2 P_k(2x - 1) on [0, 1], k < n_basis (w(0) = w_x(0) = 0), with its first
    and second derivatives: a polynomial Ritz basis, independent of any beam mode shapes."""
    w, w1, w2 = [], [], []
    t = np.polynomial.Polynomial([-1.0, 2.0])  # 2x - 1
    for k in range(n_basis):
        p = np.polynomial.Polynomial([0.0, 0.0, 1.0]) * np.polynomial.Legendre.basis(k).convert(
            kind=np.polynomial.Polynomial
        )(t)
        w.append(p(x))
        w1.append(p.deriv(1)(x))
        w2.append(p.deriv(2)(x))
    return np.array(w), np.array(w1), np.array(w2)


def axially_loaded_cantilever_frequencies(
    tension, softening: float = 0.0, tip_mass: float = 0.0, n_basis: int = 14
) -> np.ndarray:
    """Dimensionless natural frequencies `omega sqrt(rho l^4 / EI)` (ascending) of a uniform
    cantilever (clamped at x = 0, free at x = l) carrying the axial force `N(x)` (tension
    positive), in units `x -> x/l`, `N -> N l^2 / EI`:

        EI v_xxxx - (N(x) v_x)_x - s rho v = rho omega^2 v,   v(0) = v_x(0) = 0, v_xx(l) = v_xxx(l) = 0

    (`s = softening`, in units `EI / (rho l^4)`: `Omega^2` for the in-plane vibration of a
    beam spinning at `Omega`, whose centrifugal load also pulls each point outwards;
    0 for out-of-plane). `tension` is a function of `x` in [0, 1]; for a beam spinning
    about its root, `N(x) = lam^2 (1 - x^2)/2` with `lam = Omega sqrt(rho l^4 / EI)`; for a
    hanging (standing) column under its own weight, `N(x) = +-gamma (1 - x)` with
    `gamma = rho g l^3 / EI`. `tip_mass` (`mu = M / (rho l)`) adds a point mass at the free
    end: kinetic energy `mu v(1)^2` (and `-s mu v(1)^2` in the energy); its pull on the beam
    is the caller's to put in `N` (spinning: `N = lam^2 ((1 - x^2)/2 + mu)`).

    Rayleigh-Ritz on the energy `int v_xx^2 + N v_x^2 - s v^2` against `int v^2` with the
    polynomial basis of `_clamped_legendre_basis` (64-point Gauss-Legendre, exact for these
    polynomials); Ritz values converge from above. The natural boundary conditions at the
    free end come out of the variational form (N(l) = 0 for both loads above).
    Sources: Hodges & Rutkowski, AIAA J. 19 (1981) 1459 (rotating cantilevers, out-of-plane:
    3.5160, 3.6816, 4.1373, ... at lam = 0, 1, 2); Wright, Smith, Thresher & Wang, J. Appl.
    Mech. 49 (1982) 197; in-plane omega^2 = (out-of-plane omega)^2 - Omega^2 at the same
    speed (the `s` term)."""
    xg, wg = np.polynomial.legendre.leggauss(64)
    x, wq = 0.5 * (xg + 1.0), 0.5 * wg
    w, w1, w2 = _clamped_legendre_basis(n_basis, x)
    N = np.asarray([tension(xi) for xi in x], dtype=float)
    w_tip = _clamped_legendre_basis(n_basis, np.ones(1))[0][:, 0]
    M = (w * wq) @ w.T + tip_mass * np.outer(w_tip, w_tip)
    K = (w2 * wq) @ w2.T + (w1 * (wq * N)) @ w1.T - softening * M
    from scipy.linalg import eigh

    ev = eigh(K, M, eigvals_only=True)
    return np.sign(ev) * np.sqrt(np.abs(ev))


def spinning_beam_tip_deflection(
    ts, rate, acceleration, length: float, rho: float, EI: float, n_basis: int = 6
) -> np.ndarray:
    """Tip deflection (m) at the times `ts` of a uniform cantilever whose root is turned
    about the axis of the plane with the prescribed rate `rate(t)` (rad/s) and angular
    acceleration `acceleration(t)` (rad/s^2), starting straight and at rest: the linear
    in-plane equation of a beam in a rotating frame (Kane, Ryan & Banerjee, J. Guidance 10
    (1987) 139; its spin-up manoeuvre is the classic test of geometric stiffening),

        rho (v_tt - Omega^2 v + alpha x) + EI v_xxxx - (N v_x)_x = 0,  N = rho Omega^2 (l^2 - x^2)/2,

    discretised by Ritz with the polynomial basis of `_clamped_legendre_basis` and
    integrated by SciPy's DOP853 at rtol 1e-10. Valid while v << l. (Kane et al.'s spin-up,
    tests/flexdyn/test_chain.py: 6 polynomials are within 1.9e-6 m of 10 on a 1.58 m peak;
    more cost time only, the highest Ritz frequencies setting DOP853's step.)"""
    from scipy.integrate import solve_ivp

    xg, wg = np.polynomial.legendre.leggauss(64)
    x, wq = 0.5 * (xg + 1.0), 0.5 * wg  # x in units of l
    w, w1, w2 = _clamped_legendre_basis(n_basis, x)
    w_tip = _clamped_legendre_basis(n_basis, np.ones(1))[0][:, 0]
    M = rho * length * (w * wq) @ w.T
    K_bend = EI / length**3 * (w2 * wq) @ w2.T
    K_tension = rho * length * (w1 * (wq * 0.5 * (1.0 - x * x))) @ w1.T  # times Omega^2
    load = -rho * length**2 * (w * (wq * x)).sum(axis=1)  # times alpha
    M_inv = np.linalg.inv(M)

    def rhs(t, y):
        c, c_dot = y[:n_basis], y[n_basis:]
        omega2 = float(rate(t)) ** 2
        force = load * float(acceleration(t)) - (K_bend + omega2 * (K_tension - M)) @ c
        return np.concatenate([c_dot, M_inv @ force])

    ts = np.asarray(ts, dtype=float)
    sol = solve_ivp(rhs, (ts[0], ts[-1]), np.zeros(2 * n_basis), "DOP853", t_eval=ts, rtol=1e-10, atol=1e-12)
    if not sol.success:
        raise RuntimeError(f"spinning_beam_tip_deflection: solve_ivp failed: {sol.message}")
    return sol.y[:n_basis].T @ w_tip


def greenhill_critical_load() -> float:
    """Greenhill's self-weight buckling load of a uniform column clamped at its foot and
    free at the top: `(rho g l^3 / EI)_cr = 9/4 j^2`, `j` the first zero of the Bessel
    function `J_{-1/3}` (Greenhill 1881; Timoshenko & Gere, Theory of Elastic Stability,
    2nd ed. (1961), ch. 2, a bar under its own weight: 7.837)."""
    from scipy.special import jv

    j = brentq(lambda z: jv(-1.0 / 3.0, z), 1.0, 2.5, **_BRENT_KW)
    return 2.25 * j * j


# ---------------------------------------------------------------------------
# 5. MuJoCo rigid planar chain
# ---------------------------------------------------------------------------


def _fmt(v):
    return repr(float(v))


def _diag_inertia(izz):
    # Planar motion about z only sees Izz.  Ixx = Iyy = Izz is admissible
    # (triangle inequality) and keeps the body inertia well conditioned.
    i = float(izz)
    return f"{_fmt(i)} {_fmt(i)} {_fmt(i)}"


def mujoco_planar_chain(
    links,
    gravity=(0.0, -9.81),
    payload_mass=0.0,
    payload_inertia=0.0,
    hub_masses=None,
    hub_inertias=None,
    joint_damping=None,
    armature=None,
):
    """Build a MuJoCo model of a rigid planar serial chain (x-y plane, hinges about +z).

    Generalised coordinates are RELATIVE joint angles: theta_1 from the base +x axis
    (counter-clockwise positive), theta_i from the axis of link i-1.  Joint 1 is at
    the world origin; joint i+1 sits at distance ``length`` along link i's axis.
    ``links[i]`` = {length, mass, com, inertia}: centre of mass on the link axis at
    distance ``com`` from joint i, ``inertia`` = rotary inertia about z through the COM.
    Hub i: point mass hub_masses[i] with rotary inertia hub_inertias[i], at joint i,
    rigidly attached to link i.  Payload: point mass + rotary inertia at the far end
    of the last link.  Gravity (gx, gy) in the plane.  joint_damping[i]: viscous
    coefficient (N m s/rad, passive torque -d qdot); armature[i]: rotor inertia added
    to the diagonal of the mass matrix.  Contacts are disabled.
    The hub / payload are welded child bodies, so MuJoCo itself composes the inertias.
    """
    n = len(links)
    hub_masses = [0.0] * n if hub_masses is None else list(hub_masses)
    hub_inertias = [0.0] * n if hub_inertias is None else list(hub_inertias)
    joint_damping = [0.0] * n if joint_damping is None else list(joint_damping)
    armature = [0.0] * n if armature is None else list(armature)
    gx, gy = float(gravity[0]), float(gravity[1])

    def point_body(name, pos_x, mass, izz):
        if mass == 0.0 and izz == 0.0:
            return ""
        # MuJoCo needs a strictly positive mass on a body with inertia; a pure
        # rotary inertia gets a negligible mass at the body origin (on the axis
        # of the hub / at the payload point it changes nothing measurable).
        mass = max(float(mass), 1e-300) if izz > 0.0 else float(mass)
        return (
            f'<body name="{name}" pos="{_fmt(pos_x)} 0 0">'
            f'<inertial pos="0 0 0" mass="{_fmt(mass)}" diaginertia="{_diag_inertia(izz)}"/>'
            f"</body>"
        )

    xml_open = []
    xml_close = []
    for i, lk in enumerate(links):
        pos_x = 0.0 if i == 0 else float(links[i - 1]["length"])
        body = [f'<body name="link{i}" pos="{_fmt(pos_x)} 0 0">']
        body.append(
            f'<joint name="j{i}" type="hinge" axis="0 0 1" pos="0 0 0" '
            f'damping="{_fmt(joint_damping[i])}" armature="{_fmt(armature[i])}" '
            f'limited="false" frictionloss="0" stiffness="0"/>'
        )
        body.append(
            f'<inertial pos="{_fmt(lk["com"])} 0 0" mass="{_fmt(lk["mass"])}" '
            f'diaginertia="{_diag_inertia(lk["inertia"])}"/>'
        )
        body.append(point_body(f"hub{i}", 0.0, hub_masses[i], hub_inertias[i]))
        if i == n - 1:
            body.append(point_body("payload", lk["length"], payload_mass, payload_inertia))
        xml_open.append("".join(body))
        xml_close.append("</body>")

    xml = (
        '<mujoco model="planar_chain">'
        '<compiler angle="radian" inertiafromgeom="false" boundmass="0" boundinertia="0"/>'
        f'<option gravity="{_fmt(gx)} {_fmt(gy)} 0" integrator="RK4" timestep="0.001">'
        '<flag contact="disable" constraint="disable"/></option>'
        "<worldbody>" + "".join(xml_open) + "".join(reversed(xml_close)) + "</worldbody>"
        "</mujoco>"
    )
    return mujoco.MjModel.from_xml_string(xml)


def _full_m(model, data):
    M = np.zeros((model.nv, model.nv))
    try:
        mujoco.mj_fullM(model, data, M)  # MuJoCo >= 3.5 / 4.x signature
    except TypeError:
        mujoco.mj_fullM(model, M, data.qM)  # older signature
    return M


def mujoco_mass_matrix(model, q) -> np.ndarray:
    """Dense joint-space mass matrix M(q) (n x n) of a MuJoCo model (mj_forward + mj_fullM)."""
    data = mujoco.MjData(model)
    data.qpos[:] = np.asarray(q, dtype=float)
    mujoco.mj_forward(model, data)
    return _full_m(model, data)


def mujoco_forward_dynamics(model, q, qd, tau) -> np.ndarray:
    """Joint accelerations qdd solving M(q) qdd + c(q, qd) + g(q) + D qd = tau.

    Gravity via model.opt.gravity, viscous joint damping as passive forces,
    ``tau`` applied as qfrc_applied; computed with mj_forward.
    """
    data = mujoco.MjData(model)
    data.qpos[:] = np.asarray(q, dtype=float)
    data.qvel[:] = np.asarray(qd, dtype=float)
    data.qfrc_applied[:] = np.asarray(tau, dtype=float)
    mujoco.mj_forward(model, data)
    return data.qacc.copy()
