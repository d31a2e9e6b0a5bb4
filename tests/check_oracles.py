"""Self-check of tests/oracles.py against textbook numbers and independent models.

Run:  .venv/bin/python tests/check_oracles.py  (also run by tests/test_oracles.py)
"""

import math
import os
import sys

import numpy as np
from scipy.integrate import quad
from scipy.linalg import eigh
from scipy.optimize import brentq

sys.path.insert(0, os.path.dirname(__file__))
import oracles as O  # noqa: E402

FAIL = []


def check(name, got, want, tol):
    got = np.atleast_1d(np.asarray(got, float))
    want = np.atleast_1d(np.asarray(want, float))
    err = float(np.max(np.abs(got - want) / np.maximum(1.0, np.abs(want))))
    ok = err <= tol
    if not ok:
        FAIL.append(name)
    print(f"[{'ok ' if ok else 'BAD'}] {name}: max rel err {err:.2e} (tol {tol:g})")
    return ok


# ---------------------------------------------------------------- pendulum
I, mgl = 0.7, 2.3
T0 = O.pendulum_period_small(I, mgl)
print("pendulum T0 =", T0)
check("pendulum exact(amp->0) == small", O.pendulum_period_exact(I, mgl, 1e-8), T0, 1e-14)
# Textbook ratio T/T0 at 90 deg = 2K(1/2)/pi = 1.18034060
r90 = O.pendulum_period_exact(I, mgl, math.pi / 2) / T0
print("T/T0 at 90 deg =", r90)
check("T/T0(90deg) = 1.18034060", r90, 1.18034060, 1e-8)
# independent: T = 4 sqrt(I/mgl) * int_0^{pi/2} dphi / sqrt(1 - k^2 sin^2 phi)
for amp in (0.3, 1.0, 2.5, 3.0):
    k = math.sin(amp / 2)
    Kq = quad(
        lambda p: 1 / math.sqrt(1 - k * k * math.sin(p) ** 2), 0, math.pi / 2, epsabs=1e-15, epsrel=1e-13, limit=200
    )[0]
    check(
        f"pendulum exact amp={amp} vs quadrature",
        O.pendulum_period_exact(I, mgl, amp),
        4 * math.sqrt(I / mgl) * Kq,
        1e-12,
    )
# independent: time integration of the ODE (quarter period = time to reach th=0)
from scipy.integrate import solve_ivp  # noqa: E402

amp = 2.0
ev = lambda t, y: y[0]  # noqa: E731
ev.terminal, ev.direction = True, -1
sol = solve_ivp(
    lambda t, y: [y[1], -mgl / I * math.sin(y[0])],
    [0, 100],
    [amp, 0.0],
    events=ev,
    rtol=1e-12,
    atol=1e-12,
    method="DOP853",
)
check("pendulum exact amp=2 vs ODE quarter period", 4 * sol.t_events[0][0], O.pendulum_period_exact(I, mgl, amp), 1e-9)

# ---------------------------------------------------------------- cantilever
cr = O.cantilever_roots(6)
print("cantilever roots:", np.array2string(cr, precision=10))
check(
    "cantilever roots (Blevins)",
    cr[:5],
    [1.8751040687, 4.6940911330, 7.8547574382, 10.9955407349, 14.1371683910],
    1e-10,
)
r = O.cantilever_roots(40)
res = 1 + np.cos(r) * np.cosh(r)
# |f'| ~ 1 near the roots, so |f(root)| must be at the level of the ulp of the root
check(
    "cantilever residual |cos + sech| / (4 ulp) (40 roots)",
    np.abs(np.cos(r) + 1 / np.cosh(r)) / (4 * np.spacing(r)),
    0.0,
    1.0,
)
print("   residual of 1+cos cosh, first 5:", res[:5])
check("cantilever asymptote (2k-1)pi/2, k=40", r[-1], (2 * 40 - 1) * math.pi / 2, 1e-15)

# ---------------------------------------------------------------- clamped + tip body
check("clamped_mass_roots(mu=j=0) == cantilever", O.clamped_mass_roots(6, 0, 0), cr, 1e-14)
cm1 = O.clamped_mass_roots(3, 1.0, 0.0)
print("clamped mu=1 roots:", cm1)
check("clamped mu=1 first root 1.2479 (Blevins)", cm1[0], 1.24792, 1e-5)
for mu, j in [(0.0, 0.0), (1.0, 0.0), (0.3, 0.05), (2.0, 0.5), (0.0, 0.1)]:
    a = O.clamped_mass_roots(8, mu, j)
    b = O.hub_beam_roots(8, 1e14, mu, j)  # hub determinant, independently derived, J_h -> inf
    check(f"Ahmad eq.(23) vs hub determinant (J_h->inf) mu={mu} j={j}", a, b, 1e-8)

# ---------------------------------------------------------------- hub beam
pf = O.hub_beam_roots(4, 0.0)
print("hub beam J_h=0 (pinned-free) roots:", pf)
check(
    "pinned-free roots 3.9266 7.0686 10.2102 13.3518", pf, [3.926602312, 7.068582745, 10.210176122, 13.351768777], 1e-9
)
check("pinned-free satisfy tan x = tanh x", np.tan(pf) - np.tanh(pf), 0.0, 1e-12)
check("hub beam J_h=1e14 == cantilever", O.hub_beam_roots(6, 1e14), cr, 1e-10)

EI, rho, L = 3.1, 0.45, 0.9


def fe_hub_beam(EI, rho, L, Jh, M, J, ne=200, nmodes=8, clamp=False):
    """Hermite cubic FE, dofs (v, h v') per node, v(0)=0; hub inertia on v'(0)
    (clamp=True: v'(0)=0 instead).  Shift-invert form M x = mu (K + s M) x keeps
    the low eigenvalues accurate despite the rigid mode."""
    h = L / ne
    k = EI / h**3 * np.array([[12, 6, -12, 6], [6, 4, -6, 2], [-12, -6, 12, -6], [6, 2, -6, 4.0]])
    m = rho * h / 420 * np.array([[156, 22, 54, -13], [22, 4, 13, -3], [54, 13, 156, -22], [-13, -3, -22, 4.0]])
    nd = 2 * (ne + 1)
    K = np.zeros((nd, nd))
    Mm = np.zeros((nd, nd))
    for e in range(ne):
        s = slice(2 * e, 2 * e + 4)
        K[s, s] += k
        Mm[s, s] += m
    Mm[1, 1] += Jh / h**2
    Mm[-2, -2] += M
    Mm[-1, -1] += J / h**2
    keep = np.arange(2 if clamp else 1, nd)
    K = K[np.ix_(keep, keep)]
    Mm = Mm[np.ix_(keep, keep)]
    sig = EI / (rho * L**4)
    mu = eigh(Mm, K + sig * Mm, eigvals_only=True)[::-1]
    w = np.sqrt(np.clip(1 / mu - sig, 0, None))
    return w[:nmodes] if clamp else w[1 : nmodes + 1]  # drop the rigid mode


# FE in double precision is good to ~1e-7 here (discretisation vs round-off); a wrong
# boundary condition or a missed/spurious root would show up at the 1e-2 level.
for Jh, M, J in [
    (0.02, 0.0, 0.0),
    (0.2, 0.1, 0.003),
    (1e-4, 0.5, 0.0),
    (5.0, 0.0, 0.01),
    (50.0, 5.0, 0.3),
    (1e-6, 0.0, 0.05),
]:
    ex = O.hub_beam_frequencies(6, EI, rho, L, Jh, M, J)
    fe = fe_hub_beam(EI, rho, L, Jh, M, J, ne=150, nmodes=6)
    print(f"   J_h={Jh} M={M} J={J}: exact {np.array2string(ex, precision=6)}")
    check(f"hub_beam_frequencies vs FE(150 el) J_h={Jh} M={M} J={J}", ex, fe, 3e-7)
ex = O.hub_beam_frequencies(60, EI, rho, L, 0.37 * rho * L**3, 0.2 * rho * L, 0.01 * rho * L**3)
fe = fe_hub_beam(EI, rho, L, 0.37 * rho * L**3, 0.2 * rho * L, 0.01 * rho * L**3, ne=1000, nmodes=60)
check("hub_beam_frequencies 60 modes vs FE(1000 el) (no missed roots)", ex, fe, 1e-4)
# clamped with tip body vs FE (huge hub)
for mu, j in [(1.0, 0.0), (0.3, 0.05), (20.0, 3.0)]:
    x = O.clamped_mass_roots(4, mu, j)
    w = x**2 / L**2 * math.sqrt(EI / rho)
    fe = fe_hub_beam(EI, rho, L, 0.0, mu * rho * L, j * rho * L**3, ne=150, nmodes=4, clamp=True)
    check(f"clamped_mass_roots vs FE mu={mu} j={j}", w, fe, 3e-7)

# ---------------------------------------------------------------- MuJoCo chain
rng = np.random.default_rng(0)
g = 9.81
# 1 link, hub, payload, armature, damping
lk = dict(length=0.8, mass=1.3, com=0.35, inertia=0.07)
hm, hI, pm, pI, arm, d = 0.9, 0.011, 0.4, 0.002, 0.03, 0.17
m1 = O.mujoco_planar_chain(
    [lk],
    gravity=(0, -g),
    payload_mass=pm,
    payload_inertia=pI,
    hub_masses=[hm],
    hub_inertias=[hI],
    joint_damping=[d],
    armature=[arm],
)
Mexp = lk["inertia"] + lk["mass"] * lk["com"] ** 2 + hI + pm * lk["length"] ** 2 + pI + arm
for q in (0.0, 0.7, -2.1):
    check(f"1-link mass matrix q={q}", O.mujoco_mass_matrix(m1, [q]), Mexp, 1e-12)
    qd, tau = 1.3, 0.25
    grav = -(lk["mass"] * lk["com"] + pm * lk["length"]) * g * math.cos(q)
    check(f"1-link qacc q={q}", O.mujoco_forward_dynamics(m1, [q], [qd], [tau]), (tau - d * qd + grav) / Mexp, 1e-12)
# gravity along +x
m1x = O.mujoco_planar_chain([lk], gravity=(4.0, 0.0))
M0 = lk["inertia"] + lk["mass"] * lk["com"] ** 2
check(
    "1-link qacc, gravity (4,0)",
    O.mujoco_forward_dynamics(m1x, [0.5], [0.0], [0.0]),
    -lk["mass"] * lk["com"] * 4.0 * math.sin(0.5) / M0,
    1e-12,
)

# 2 links: textbook planar arm
L1 = dict(length=1.1, mass=2.0, com=0.45, inertia=0.21)
L2 = dict(length=0.7, mass=1.1, com=0.3, inertia=0.05)
d2 = [0.1, 0.05]
m2 = O.mujoco_planar_chain([L1, L2], gravity=(0, -g), joint_damping=d2)
I1, I2, ma, mb, c1, c2, l1 = L1["inertia"], L2["inertia"], L1["mass"], L2["mass"], L1["com"], L2["com"], L1["length"]
for _ in range(4):
    q = rng.uniform(-3, 3, 2)
    qd = rng.uniform(-2, 2, 2)
    tau = rng.uniform(-1, 1, 2)
    ct = math.cos(q[1])
    M11 = I1 + I2 + ma * c1**2 + mb * (l1**2 + c2**2 + 2 * l1 * c2 * ct)
    M12 = I2 + mb * (c2**2 + l1 * c2 * ct)
    M22 = I2 + mb * c2**2
    Mt = np.array([[M11, M12], [M12, M22]])
    check(f"2-link textbook mass matrix q={np.round(q, 3)}", O.mujoco_mass_matrix(m2, q), Mt, 1e-12)
    h = mb * l1 * c2 * math.sin(q[1])
    cor = np.array([-h * (2 * qd[0] * qd[1] + qd[1] ** 2), h * qd[0] ** 2])
    gr = np.array(
        [
            (ma * c1 + mb * l1) * g * math.cos(q[0]) + mb * c2 * g * math.cos(q[0] + q[1]),
            mb * c2 * g * math.cos(q[0] + q[1]),
        ]
    )
    qdd = np.linalg.solve(Mt, tau - cor - gr - np.array(d2) * qd)
    check("2-link textbook forward dynamics", O.mujoco_forward_dynamics(m2, q, qd, tau), qdd, 1e-12)


# n links with hubs/payload/armature: independent point-Jacobian Lagrangian model
def chain_model(links, hm, hI, pm, pI, arm, damp, gvec):
    n = len(links)
    bodies = []  # (link index, distance along link, mass, izz)
    for i, lk in enumerate(links):
        bodies.append((i, lk["com"], lk["mass"], lk["inertia"]))
        bodies.append((i, 0.0, hm[i], hI[i]))
    bodies.append((n - 1, links[-1]["length"], pm, pI))

    def pos_jac(q, i, s):
        phi = np.cumsum(q)
        joints = [np.zeros(2)]
        for k in range(n):
            joints.append(joints[-1] + links[k]["length"] * np.array([math.cos(phi[k]), math.sin(phi[k])]))
        p = joints[i] + s * np.array([math.cos(phi[i]), math.sin(phi[i])])
        Jv = np.zeros((2, n))
        for k in range(i + 1):
            r = p - joints[k]
            Jv[:, k] = [-r[1], r[0]]
        Jw = np.array([1.0 if k <= i else 0.0 for k in range(n)])
        return p, Jv, Jw

    def Mfun(q):
        M = np.diag(np.array(arm, float))
        for i, s, m, iz in bodies:
            _, Jv, Jw = pos_jac(q, i, s)
            M += m * Jv.T @ Jv + iz * np.outer(Jw, Jw)
        return M

    def V(q):
        return -sum(m * gvec @ pos_jac(q, i, s)[0] for i, s, m, iz in bodies)

    def qdd(q, qd, tau, e=1e-6):
        # Lagrange: M qdd + Mdot qd - 1/2 d/dq (qd^T M qd) + dV/dq + D qd = tau   (central differences)
        Md = sum(
            (Mfun(q + e * qd * 0 + e * np.eye(n)[k]) - Mfun(q - e * np.eye(n)[k])) / (2 * e) * qd[k] for k in range(n)
        )
        dT = (
            np.array(
                [qd @ ((Mfun(q + e * np.eye(n)[k]) - Mfun(q - e * np.eye(n)[k])) / (2 * e)) @ qd for k in range(n)]
            )
            / 2
        )
        dV = np.array([(V(q + e * np.eye(n)[k]) - V(q - e * np.eye(n)[k])) / (2 * e) for k in range(n)])
        return np.linalg.solve(Mfun(q), tau - Md @ qd + dT - dV - np.array(damp) * qd)

    return Mfun, qdd


links3 = [
    dict(length=0.9, mass=1.5, com=0.4, inertia=0.1),
    dict(length=0.6, mass=0.8, com=0.25, inertia=0.03),
    dict(length=0.5, mass=0.5, com=0.3, inertia=0.012),
]
hm3, hI3, arm3, dmp3 = [0.7, 0.4, 0.2], [0.01, 0.005, 0.0], [0.02, 0.0, 0.01], [0.1, 0.2, 0.0]
gv = np.array([1.2, -9.81])
m3 = O.mujoco_planar_chain(
    links3,
    gravity=gv,
    payload_mass=0.3,
    payload_inertia=0.004,
    hub_masses=hm3,
    hub_inertias=hI3,
    joint_damping=dmp3,
    armature=arm3,
)
Mf, qddf = chain_model(links3, hm3, hI3, 0.3, 0.004, arm3, dmp3, gv)
for _ in range(3):
    q = rng.uniform(-3, 3, 3)
    qd = rng.uniform(-2, 2, 3)
    tau = rng.uniform(-1, 1, 3)
    check("3-link (hubs, payload, armature) mass matrix vs Jacobian model", O.mujoco_mass_matrix(m3, q), Mf(q), 1e-12)
    check(
        "3-link forward dynamics vs finite-difference Lagrangian",
        O.mujoco_forward_dynamics(m3, q, qd, tau),
        qddf(q, qd, tau),
        1e-7,
    )

# hub with rotary inertia but zero mass, payload inertia only
m_i = O.mujoco_planar_chain([lk], hub_masses=[0.0], hub_inertias=[0.05], payload_mass=0.0, payload_inertia=0.02)
check("zero-mass hub/payload rotary inertia only", O.mujoco_mass_matrix(m_i, [0.3]), M0 + 0.07, 1e-12)

# ---------------------------------------------------------------- axially loaded cantilever
# Ritz with the polynomial basis: unloaded = the cantilever roots squared; rotating beam
# (out-of-plane) = the published table of Hodges & Rutkowski (1981), Table 1 (also Wright et
# al. 1982), first two modes at lam = 1, 2, 5, 10, 12; Greenhill's load from the Bessel zero =
# Timoshenko & Gere's 7.837 and = where the standing column's first Ritz frequency vanishes.
check(
    "cantilever, no load: (beta_k l)^2",
    O.axially_loaded_cantilever_frequencies(lambda x: 0.0)[:3],
    O.cantilever_roots(3) ** 2,
    1e-9,
)
PUBLISHED_ROTATING = {
    1: (3.6816, 22.1810),
    2: (4.1373, 22.6149),
    5: (6.4495, 25.4461),
    10: (11.2023, 33.6404),
    12: (13.1702, 37.6031),
}
for lam_, want in PUBLISHED_ROTATING.items():
    got = O.axially_loaded_cantilever_frequencies(lambda x, lam_=lam_: lam_**2 * (1 - x * x) / 2)[:2]
    check(f"rotating cantilever lam={lam_}: Hodges & Rutkowski", got, want, 6e-5)
    inplane = O.axially_loaded_cantilever_frequencies(lambda x, lam_=lam_: lam_**2 * (1 - x * x) / 2, lam_**2)[:2]
    check(f"rotating cantilever lam={lam_}: in-plane^2 = out-of-plane^2 - lam^2", inplane**2, got**2 - lam_**2, 1e-9)
check(
    "rotating cantilever: basis converged (14 vs 20 polynomials)",
    O.axially_loaded_cantilever_frequencies(lambda x: 50 * (1 - x * x), n_basis=14)[:2],
    O.axially_loaded_cantilever_frequencies(lambda x: 50 * (1 - x * x), n_basis=20)[:2],
    1e-9,
)
check(
    "cantilever with a tip mass, no load: clamped-mass roots squared",
    O.axially_loaded_cantilever_frequencies(lambda x: 0.0, tip_mass=0.7, n_basis=20)[:3],
    O.clamped_mass_roots(3, 0.7, 0.0) ** 2,
    1e-8,
)
gamma_cr = O.greenhill_critical_load()
check("Greenhill 9/4 j^2 = 7.837 (Timoshenko & Gere)", gamma_cr, 7.837, 1e-4)
gamma_ritz = brentq(lambda g: O.axially_loaded_cantilever_frequencies(lambda x: -g * (1 - x))[0], 5.0, 10.0, xtol=1e-13)
check("Greenhill = standing column's Ritz frequency at zero", gamma_ritz, gamma_cr, 1e-9)

print()
print("ALL OK" if not FAIL else f"FAILED: {FAIL}")
sys.exit(1 if FAIL else 0)
