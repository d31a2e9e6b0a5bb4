"""A NumPy implementation of flexdyn's planar-chain equations, written for the benchmarks.

This is the *peer* the benchmarks race against (`scipy.integrate.solve_ivp` on these
equations). It is written to be fair to NumPy: the constant shape integrals of each link
(flexdyn's `LinkMatrices`: `mass`, `c1`, `c2`, `a`, `b`, `modal_mass`, `stiffness`,
`damping`, `tip_shape`, `tip_slope`) are taken as constants, as any hand-written model
would precompute them, and everything that depends on the state is formed here, by hand,
with small dense NumPy operations (no loops over quadrature points; one Python loop over
the links, as the recursion needs). It imports neither jax nor flexdyn.

**Equations** (the kinematics and kinetic energy of `flexdyn/chain.py`'s docstring).
Link i has its root at `o_i`, absolute angle `phi_i`, modal coordinates `q_i`; a point at
`x` is at `r = o_i + R(phi_i) P(x)`, `P = [x, v(x)]`, `v = phi(x).q_i`. Angles are linear
in `Q` (`phi_i = e_i.Q`, `psi_i = phi_i + tip_slope.q_i`), so their Jacobians `e_i` are
constant. By Kane's method (equal to Lagrange's equations for these holonomic
coordinates) the generalised inertia force is `sum_i int rho (dr/dQ)^T r_ddot dx`; with the
body-frame quasi-velocities `w_i = [u, omega, q_dot_i] = D_i(Q) Q_dot` (`u = R^T o_dot`,
`D_i = [R^T J_o; e_i; E_i]`) it is

    M(Q) = sum_i D_i^T G_i(q_i) D_i,      h(Q, Q_dot) = sum_i D_i^T beta_i,

with the link's mass matrix in its own frame (the kinetic-energy formula of the docstring)

    G_i = [[m, 0, -a.q, 0], [0, m, c1, a^T], [-a.q, c1, c2 + q^T Mq q, b^T], [0, a, b, Mq]]

and the velocity-product ("bias") generalised force, `a_b = R^T o_ddot_bias`:

    beta_u     = m a_b - omega^2 [c1, a.q] + 2 omega [-a.q_dot, 0]
    beta_omega = [-a.q, c1].a_b + 2 omega q^T Mq q_dot
    beta_q     = a a_b_y - omega^2 Mq q

The root Jacobian and bias acceleration propagate tip-wards,
`J_o,i+1 = J_o,i + S R p e_i^T + R[:,1] tip^T E_i` and
`o_ddot_bias,i+1 = o_ddot_bias,i - omega^2 R p + 2 omega S R[:,1] (tip.q_dot)` with
`p = [l, tip.q]`, `S` the 90-degree rotation. Hubs (point mass + inertia on `phi_i`),
rotors (inertia on the constant-Jacobian angle `psi_{i-1} + G s_i`, or `G s_i` with
Spong's approximation) and the payload (point mass at the tip + inertia on `psi_n`) add
`m J^T J` / `I g g^T` to `M` and `m J^T o_ddot_bias` to `h`. Forces: joint torques on the
actuated coordinates, bending `-K q`, joint springs, viscous joint/spring/modal damping, and
gravity `J_w^T g` (J_w: Jacobian of the mass-weighted positions).
"""

from __future__ import annotations

import numpy as np

_S = np.array([[0.0, -1.0], [1.0, 0.0]])


class NumpyChain:
    """The equations of motion of one planar chain, in NumPy.

    Build it with `from_flexdyn(chain)` (reads the parameters and the assembled shape
    integrals once) or directly from plain dicts. `accelerations(Q, Qd, tau)` is the
    forward dynamics; `rhs(t, y, tau)` the first-order field."""

    def __init__(self, links, joints, hubs, payload, gravity, layout):
        # links: list of dicts (length, mass, c1, c2, a, b, modal_mass, stiffness, damping,
        # tip_shape, tip_slope); joints: list of dicts (elastic, stiffness, damping,
        # spring_damping, rotor_inertia, gear_ratio, spong); hubs: list of (mass, inertia);
        # payload: (mass, inertia); layout: (rotor, theta, modal, actuated) index tuples.
        self.links, self.joints, self.hubs = links, joints, hubs
        self.payload_mass, self.payload_inertia = payload
        self.gravity = np.asarray(gravity, float)
        self.rotor, self.theta, self.modal, self.actuated = layout
        n = self.n = sum(len(m) for m in self.modal) + len(self.theta) + sum(r is not None for r in self.rotor)
        # Constant Jacobians of the angles and modal selectors.
        self.e, self.E, self.e_psi, self.g_rotor = [], [], [], []
        psi = np.zeros(n)
        self.M_const = np.zeros((n, n))  # rotors: constant inertia terms
        for i, lk in enumerate(links):
            e = psi.copy()
            e[self.theta[i]] += 1.0
            E = np.zeros((len(self.modal[i]), n))
            E[np.arange(len(self.modal[i])), list(self.modal[i])] = 1.0
            j = joints[i]
            g = np.zeros(n)
            g[self.actuated[i]] = j["gear_ratio"]
            if not j["spong"]:
                g = g + psi
            self.M_const += j["rotor_inertia"] * np.outer(g, g)
            self.M_const += hubs[i][1] * np.outer(e, e)
            psi = e + lk["tip_slope"] @ E
            self.e.append(e)
            self.E.append(E)
            self.e_psi.append(psi)
        self.M_const += self.payload_inertia * np.outer(psi, psi)
        # Constant generalised stiffness and damping (bending, joint springs, viscous).
        K = np.zeros((n, n))
        C = np.zeros((n, n))
        for i, lk in enumerate(links):
            idx = np.ix_(self.modal[i], self.modal[i])
            K[idx] += lk["stiffness"]
            C[idx] += lk["damping"]
            j = joints[i]
            C[self.actuated[i], self.actuated[i]] += j["damping"]
            if j["elastic"]:
                r, t = self.rotor[i], self.theta[i]
                d = np.zeros(n)
                d[r], d[t] = 1.0, -1.0
                K += j["stiffness"] * np.outer(d, d)
                C += j["spring_damping"] * np.outer(d, d)
        self.K, self.C = K, C
        self.B = np.zeros((n, len(links)))
        self.B[list(self.actuated), np.arange(len(links))] = 1.0

    @classmethod
    def from_flexdyn(cls, chain, assembled=None):
        """Read a flexdyn `Chain`'s parameters and assembled shape integrals (the only
        use of flexdyn: the constants). `assembled`: `fd.assemble(chain)` if already at hand
        (e.g. from a jitted call: the clamped-mass mode shapes depend on the payload)."""
        import flexdyn as fd

        asm = fd.assemble(chain) if assembled is None else assembled
        lay = chain.layout
        f = lambda x: np.asarray(x, float)  # noqa: E731
        links = [
            dict(
                length=float(lm.length),
                mass=float(lm.mass),
                c1=float(lm.c1),
                c2=float(lm.c2),
                a=f(lm.a),
                b=f(lm.b),
                modal_mass=f(lm.modal_mass),
                stiffness=f(lm.stiffness),
                damping=f(lm.damping),
                tip_shape=f(lm.tip_shape),
                tip_slope=f(lm.tip_slope),
            )
            for lm in asm.links
        ]
        joints = [
            dict(
                elastic=j.elastic,
                stiffness=float(j.stiffness) if j.elastic else 0.0,
                damping=float(j.damping),
                spring_damping=float(j.spring_damping) if j.elastic else 0.0,
                rotor_inertia=float(j.rotor_inertia),
                gear_ratio=float(j.gear_ratio),
                spong=j.spong_approximation,
            )
            for j in chain.joints
        ]
        hubs = [(float(h.mass), float(h.inertia)) for h in chain.hubs]
        payload = (float(chain.payload.mass), float(chain.payload.inertia))
        return cls(links, joints, hubs, payload, f(chain.gravity), (lay.rotor, lay.theta, lay.modal, lay.actuated))

    def mass_and_bias(self, Q, Qd):
        """`(M(Q), h(Q, Q_dot), f_gravity(Q))`: mass matrix, velocity terms, gravity force."""
        n = self.n
        M = self.M_const.copy()
        h = np.zeros(n)
        Jo = np.zeros((2, n))  # Jacobian of the link root o_i (base frame)
        ob = np.zeros(2)  # velocity-product part of o_ddot_i
        Jw = np.zeros((2, n))  # Jacobian of the mass-weighted positions (gravity)
        for i, lk in enumerate(self.links):
            e, E, idx = self.e[i], self.E[i], self.modal[i]
            phi, omega = e @ Q, e @ Qd
            q, qd = Q[list(idx)], Qd[list(idx)]
            c, s = np.cos(phi), np.sin(phi)
            R = np.array([[c, -s], [s, c]])
            m, c1, c2, a, b, Mq = lk["mass"], lk["c1"], lk["c2"], lk["a"], lk["b"], lk["modal_mass"]
            aq, aqd, Mqq = a @ q, a @ qd, Mq @ q
            nm = len(idx)
            G = np.empty((3 + nm, 3 + nm))
            G[:3, :3] = [[m, 0.0, -aq], [0.0, m, c1], [-aq, c1, c2 + q @ Mqq]]
            G[0, 3:] = G[3:, 0] = 0.0
            G[1, 3:] = G[3:, 1] = a
            G[2, 3:] = G[3:, 2] = b
            G[3:, 3:] = Mq
            D = np.vstack([R.T @ Jo, e, E])
            ab = R.T @ ob
            beta = np.concatenate(
                [
                    [m * ab[0] - omega**2 * c1 - 2.0 * omega * aqd, m * ab[1] - omega**2 * aq],
                    [-aq * ab[0] + c1 * ab[1] + 2.0 * omega * (qd @ Mqq)],
                    a * ab[1] - omega**2 * Mqq,
                ]
            )
            M += D.T @ G @ D
            h += D.T @ beta
            hub_mass = self.hubs[i][0]
            if hub_mass:
                M += hub_mass * (Jo.T @ Jo)
                h += hub_mass * (Jo.T @ ob)
            Jw += (m + hub_mass) * Jo + np.outer(_S @ R @ np.array([c1, aq]), e) + np.outer(R[:, 1], a) @ E
            p = np.array([lk["length"], lk["tip_shape"] @ q])
            arm = R @ p
            Sarm = _S @ arm
            Jo = Jo + np.outer(Sarm, e) + np.outer(R[:, 1], lk["tip_shape"]) @ E
            ob = ob + omega * (omega * -arm + 2.0 * (lk["tip_shape"] @ qd) * (_S @ R[:, 1]))
        mp = self.payload_mass
        if mp:
            M += mp * (Jo.T @ Jo)
            h += mp * (Jo.T @ ob)
            Jw += mp * Jo
        return M, h, Jw.T @ self.gravity

    def accelerations(self, Q, Qd, tau):
        """Q_ddot = M^-1 (B tau - K Q - C Q_dot + f_gravity - h)."""
        M, h, fg = self.mass_and_bias(Q, Qd)
        rhs = self.B @ tau - self.K @ Q - self.C @ Qd + fg - h
        return np.linalg.solve(M, rhs)

    def rhs(self, t, y, tau):
        n = self.n
        return np.concatenate([y[n:], self.accelerations(y[:n], y[n:], tau)])
