"""An independent simulation of a geared servo hub carrying a flexible link, with true
stick-slip friction and a quantised strain gauge (NumPy/SciPy).

The flexible-link variant of `servo_rig.py` (issue 61): a horizontal thin aluminium strip
with a tip mass, clamped to a 70:1 geared hub whose dry friction holds it still between
moves while the link keeps ringing, driven by a digital PD + tip-feedback controller whose
torque is held over each 1 ms sample, recorded by a 4096-count motor encoder and a strain
gauge calibrated to the tip deflection (both quantised).

It shares no code with flexdyn. The link is one or two **clamped-mass assumed modes**: the
eigenfunctions of a uniform Euler-Bernoulli cantilever carrying a point mass `M` at its
tip, whose roots `lam = beta l` solve (Blevins, *Formulas for Natural Frequency and Mode
Shape*, 1979, table 8-1, case 5; divided by `cosh lam` here)

    1 + cos(lam) cosh(lam) + mu lam (cos(lam) sinh(lam) - sin(lam) cosh(lam)) = 0,
    mu = M / (rho l),

found by `scipy.optimize.brentq`, with shapes `phi(x) = cosh(beta x) - cos(beta x) -
sigma (sinh(beta x) - sin(beta x))`, `sigma = (cosh lam + cos lam) / (sinh lam + sin lam)`
(the moment-free tip), each scaled to unit mean square over the link with a positive tip
value (the modal coordinate is then the mode's RMS deflection in metres). The mass and
stiffness integrals are `scipy.integrate.quad` of these shapes.

**Equations of motion** (Lagrange, exact rigid rotation `theta` of the hub and link root,
small elastic deflection `v(x) = phi(x) . q` in the rotating frame, the tip mass at
`(l, v(l))`, no axial shortening: the kinematics of flexdyn's linear assumed-modes link).
The kinetic and potential energies are

    T = 1/2 (J + q^T Mt q) theta'^2 + theta' B . q' + 1/2 q'^T Mt q',     V = 1/2 q^T K q,

with `J = I_hub + rho l^3 / 3 + M l^2`, `Mt = rho int phi phi^T + M a a^T` (`a = phi(l)`,
the tip values), `B = rho int x phi + M l a`, `K = EI int phi'' phi''^T`; the modal damping
`D = diag(2 zeta_j sqrt(K_jj Mt_jj))`. Lagrange's equations:

    (J + q^T Mt q) theta'' + B . q'' = tau - c theta' - f - 2 theta' q^T Mt q',
    B theta'' + Mt q'' = theta'^2 Mt q - K q - D q',

`f` the joint's dry friction (Karnopp 1985): `F_c sign(theta')` while sliding; while the
hub is stuck (`theta' = theta'' = 0`) the torque it must hold,

    f_stick = tau + B^T Mt^{-1} (K q + D q'),

the held command plus the ringing link's reaction; it stays stuck while `|f_stick| <=
F_s` and breaks away towards `sign(f_stick)` the instant that fails, which is checked
continuously (a `solve_ivp` event), not only at controller updates. A sliding hub that
comes to rest (event `theta' = 0`) sticks if `|f_stick| <= F_s` there, else slides on the
other way. The `theta'^2` and `theta' q'` terms make the sliding motion nonlinear, so every
piece is integrated by DOP853 with tight tolerances (`rtol = 1e-11`); while stuck the
motion is linear (modes ringing at their clamped frequencies), which the tests check
against the closed form.

`write_flexible_servo_experiment(folder)` writes three 2.5 s logs (CSV; one held out) and
an `experiment.toml` whose baseline has no friction: the encoder declared `kind =
"encoder"` with its `resolution`, the gauge `kind = "strain_gauge"` with its
`resolution`, wired reversed and declared `sign = -1`, and `hold = "zoh"`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from pathlib import Path

import numpy as np
import scipy.integrate
import scipy.optimize
from servo_rig import min_jerk, write_logs  # tests/ is on sys.path

ALUMINIUM_E_PA = 69e9
ALUMINIUM_DENSITY_KG_M3 = 2700.0


@dataclasses.dataclass(frozen=True)
class FlexibleServoRig:
    """The rig's truth (SI, link side of the gear unless named motor).

    The link: an aluminium strip `link_length_m` x `link_width_m` x `link_thickness_m`
    bending in the horizontal plane about its thin axis, a point mass `tip_mass_kg` at its
    tip, `n_modes` clamped-mass modes with damping ratio `damping_ratio`. The hub:
    `hub_inertia_kg_m2` (the motor rotor reflected through the gear included), viscous
    `damping_n_m_s`, dry friction `sliding_friction_n_m` (`F_c`) and
    `breakaway_friction_n_m` (`F_s`). The controller, every `sample_s`:

        tau = Kp (ref - theta_enc) - Kd omega_enc + K_tip w_gauge,

    (`omega_enc` the encoder's backward difference, `w_gauge` the gauge's tip deflection),
    clipped at `torque_limit_n_m` and held. The gauge reads the tip deflection `v(l)` in
    whole counts of `gauge_resolution_m` (rounded: a bridge ADC)."""

    link_length_m: float = 0.45
    link_width_m: float = 0.02
    link_thickness_m: float = 0.0015
    tip_mass_kg: float = 0.05
    n_modes: int = 2
    damping_ratio: float = 0.01
    hub_inertia_kg_m2: float = 0.005
    damping_n_m_s: float = 0.01
    sliding_friction_n_m: float = 0.085
    breakaway_friction_n_m: float = 0.10
    gear_ratio: float = 70.0
    counts_per_turn: int = 4096
    gauge_resolution_m: float = 1e-4
    sample_s: float = 1e-3
    kp_n_m_per_rad: float = 2.0
    kd_n_m_s_per_rad: float = 0.15
    k_tip_n_m_per_m: float = 2.0
    torque_limit_n_m: float = 1.5

    @property
    def rho_kg_m(self) -> float:
        """Mass per length of the strip, kg/m."""
        return ALUMINIUM_DENSITY_KG_M3 * self.link_width_m * self.link_thickness_m

    @property
    def EI_n_m2(self) -> float:
        """Flexural rigidity `E w h^3 / 12` of the strip bending about its thin axis, N m^2."""
        return ALUMINIUM_E_PA * self.link_width_m * self.link_thickness_m**3 / 12.0

    @property
    def count_rad(self) -> float:
        """One encoder count, link side: `2 pi / (counts_per_turn G)` (a motor encoder)."""
        return 2.0 * math.pi / (self.counts_per_turn * self.gear_ratio)


def frequency_equation(lam: float, mu: float) -> float:
    """The clamped-tip-mass frequency equation divided by `cosh(lam)` (module docstring)."""
    return 1.0 / math.cosh(lam) + math.cos(lam) + mu * lam * (math.cos(lam) * math.tanh(lam) - math.sin(lam))


def clamped_mass_roots(n_modes: int, mu: float) -> np.ndarray:
    """The `n_modes` lowest roots `lam = beta l`: a sign scan (step 1e-3) then `brentq`."""
    grid = np.arange(1e-3, (n_modes + 0.5) * math.pi, 1e-3)
    values = np.array([frequency_equation(x, mu) for x in grid])
    cells = np.flatnonzero(np.sign(values[:-1]) != np.sign(values[1:]))[:n_modes]
    return np.array(
        [scipy.optimize.brentq(frequency_equation, grid[i], grid[i + 1], args=(mu,), xtol=1e-15) for i in cells]
    )


@dataclasses.dataclass(frozen=True)
class Shapes:
    """Clamped-mass mode shapes: `lam` (beta l) and `scale` (the unit-mean-square factors)."""

    length_m: float
    lam: np.ndarray
    scale: np.ndarray

    def derivative(self, j: int, x: float, k: int = 0) -> float:
        """`d^k phi_j / dx^k` at `x` [m] (units 1/m^k: the shapes are dimensionless)."""
        beta = self.lam[j] / self.length_m
        lam = self.lam[j]
        sigma = (math.cosh(lam) + math.cos(lam)) / (math.sinh(lam) + math.sin(lam))
        z = beta * x
        cosh_k = math.cosh(z) if k % 2 == 0 else math.sinh(z)
        sinh_k = math.sinh(z) if k % 2 == 0 else math.cosh(z)
        cos_k = (math.cos(z), -math.sin(z), -math.cos(z), math.sin(z))[k % 4]
        sin_k = (math.sin(z), math.cos(z), -math.sin(z), -math.cos(z))[k % 4]
        return self.scale[j] * beta**k * (cosh_k - cos_k - sigma * (sinh_k - sin_k))


def _quad(fn, length):
    """`int_0^length fn`, to 1e-12 of the integrand's size (an absolute floor, since
    the cross terms of orthogonal shapes integrate to zero)."""
    size = max(abs(fn(x)) for x in np.linspace(0.0, length, 65)) * length
    return scipy.integrate.quad(fn, 0.0, length, epsabs=1e-12 * size, epsrel=1e-12, limit=200)[0]


def mode_shapes(rig: FlexibleServoRig) -> Shapes:
    """The rig's normalised shapes: unit mean square over the link, positive tip value."""
    L = rig.link_length_m
    lam = clamped_mass_roots(rig.n_modes, rig.tip_mass_kg / (rig.rho_kg_m * L))
    raw = Shapes(L, lam, np.ones_like(lam))
    scale = []
    for j in range(rig.n_modes):
        mean_square = _quad(lambda x, j=j: raw.derivative(j, x) ** 2, L) / L
        scale.append(math.copysign(1.0, raw.derivative(j, L)) / math.sqrt(mean_square))
    return Shapes(L, lam, np.array(scale))


@dataclasses.dataclass(frozen=True)
class LinkModel:
    """The constant matrices of the equations of motion (module docstring), SI."""

    inertia: float  # J = I_hub + rho l^3 / 3 + M l^2, kg m^2
    coupling: np.ndarray  # B, kg m
    modal_mass: np.ndarray  # Mt, kg
    stiffness: np.ndarray  # K, N/m
    modal_damping: np.ndarray  # D, N s/m
    tip_shape: np.ndarray  # a = phi(l)
    clamped_frequency: np.ndarray  # lam^2 / l^2 sqrt(EI / rho), rad/s
    shapes: Shapes


@functools.cache
def link_model(rig: FlexibleServoRig) -> LinkModel:
    """The matrices of `rig`, by quadrature of the clamped-mass shapes."""
    shapes = mode_shapes(rig)
    L, rho, EI, M, n = rig.link_length_m, rig.rho_kg_m, rig.EI_n_m2, rig.tip_mass_kg, rig.n_modes
    phi = shapes.derivative
    a = np.array([phi(j, L) for j in range(n)])
    Mt = np.array([[rho * _quad(lambda x, i=i, j=j: phi(i, x) * phi(j, x), L) for j in range(n)] for i in range(n)])
    Mt += M * np.outer(a, a)
    K = np.array([[EI * _quad(lambda x, i=i, j=j: phi(i, x, 2) * phi(j, x, 2), L) for j in range(n)] for i in range(n)])
    B = np.array([rho * _quad(lambda x, j=j: x * phi(j, x), L) for j in range(n)]) + M * L * a
    D = np.diag(2.0 * rig.damping_ratio * np.sqrt(np.diag(K) * np.diag(Mt)))
    J = rig.hub_inertia_kg_m2 + rho * L**3 / 3.0 + M * L**2
    omega = shapes.lam**2 / L**2 * math.sqrt(EI / rho)
    return LinkModel(J, B, Mt, K, D, a, omega, shapes)


def accelerations(model: LinkModel, rig: FlexibleServoRig, state: np.ndarray, torque: float, friction: float):
    """`(theta'', q'')` of the sliding hub under `torque` and the dry `friction` [N m]."""
    n = rig.n_modes
    q, rate, qd = state[1 : 1 + n], state[1 + n], state[2 + n :]
    Mt, B = model.modal_mass, model.coupling
    mass = np.empty((n + 1, n + 1))
    mass[0, 0] = model.inertia + q @ Mt @ q
    mass[0, 1:] = mass[1:, 0] = B
    mass[1:, 1:] = Mt
    force = np.empty(n + 1)
    force[0] = torque - rig.damping_n_m_s * rate - friction - 2.0 * rate * (q @ Mt @ qd)
    force[1:] = rate**2 * (Mt @ q) - model.stiffness @ q - model.modal_damping @ qd
    return np.linalg.solve(mass, force)


def stick_torque(model: LinkModel, rig: FlexibleServoRig, state: np.ndarray, torque: float) -> float:
    """The friction torque [N m] that holds the hub still: `tau + B^T Mt^-1 (K q + D q')`."""
    n = rig.n_modes
    q, qd = state[1 : 1 + n], state[2 + n :]
    elastic = model.stiffness @ q + model.modal_damping @ qd
    return float(torque + model.coupling @ np.linalg.solve(model.modal_mass, elastic))


def energy(model: LinkModel, rig: FlexibleServoRig, state: np.ndarray) -> float:
    """`T + V` [J] of the state `[theta, q, theta', q']`."""
    n = rig.n_modes
    q, rate, qd = state[1 : 1 + n], state[1 + n], state[2 + n :]
    Mt = model.modal_mass
    T = 0.5 * (model.inertia + q @ Mt @ q) * rate**2 + rate * (model.coupling @ qd) + 0.5 * qd @ Mt @ qd
    return float(T + 0.5 * q @ model.stiffness @ q)


_TOLERANCES = dict(method="DOP853", rtol=1e-11, atol=1e-13)


def _slide(model, rig, state, torque, span, sign):
    """Slide with `sign` until the span ends or the hub's rate reaches zero."""
    n = rig.n_modes
    friction = sign * rig.sliding_friction_n_m

    def rhs(t, y):
        return np.concatenate([y[n + 1 :], accelerations(model, rig, y, torque, friction)])

    def stops(t, y):
        return y[n + 1]

    stops.terminal, stops.direction = True, -sign
    sol = scipy.integrate.solve_ivp(rhs, span, state, events=stops, **_TOLERANCES)
    y = sol.y[:, -1].copy()
    if sol.status == 1:
        y[n + 1] = 0.0
    return sol.t[-1], y, sol.status == 1


def _stuck(model, rig, state, torque, span):
    """Hold the hub (theta' = 0) until the span ends or `|f_stick|` reaches `F_s`."""
    n = rig.n_modes
    Fs = rig.breakaway_friction_n_m
    elastic = np.linalg.solve(model.modal_mass, np.hstack([model.stiffness, model.modal_damping]))

    def rhs(t, y):  # theta and theta' stay put; the modes ring as a clamped link's
        qdd = -elastic @ np.concatenate([y[1 : 1 + n], y[2 + n :]])
        return np.concatenate([[0.0], y[2 + n :], [0.0], qdd])

    def breaks_forward(t, y):
        return stick_torque(model, rig, y, torque) - Fs

    def breaks_backward(t, y):
        return stick_torque(model, rig, y, torque) + Fs

    breaks_forward.terminal, breaks_forward.direction = True, 1.0
    breaks_backward.terminal, breaks_backward.direction = True, -1.0

    sol = scipy.integrate.solve_ivp(rhs, span, state, events=(breaks_forward, breaks_backward), **_TOLERANCES)
    y = sol.y[:, -1].copy()
    y[n + 1] = 0.0
    return sol.t[-1], y, sol.status == 1


def advance(rig: FlexibleServoRig, state: np.ndarray, torque: float, duration: float) -> np.ndarray:
    """The state `[theta, q_1..q_n, theta', q_1'..q_n']` (rad, m, rad/s, m/s) after
    `duration` [s] under the constant link-side `torque` [N m]; `theta' == 0.0` exactly
    while the hub is stuck."""
    model = link_model(rig)
    n = rig.n_modes
    Fs = rig.breakaway_friction_n_m
    y = np.asarray(state, dtype=float).copy()
    t, end = 0.0, duration
    while t < end:
        if y[n + 1] == 0.0:
            f = stick_torque(model, rig, y, torque)
            if abs(f) <= Fs:
                t, y, _ = _stuck(model, rig, y, torque, (t, end))
                if t < end:  # broke away at the event: slide towards the unbalanced torque
                    f = stick_torque(model, rig, y, torque)
                    t, y, _ = _slide(model, rig, y, torque, (t, end), math.copysign(1.0, f))
                continue
            t, y, _ = _slide(model, rig, y, torque, (t, end), math.copysign(1.0, f))
        else:
            t, y, _ = _slide(model, rig, y, torque, (t, end), math.copysign(1.0, y[n + 1]))
    return y


def encoder(rig: FlexibleServoRig, theta: float) -> float:
    """The recorded angle [rad, link side]: whole motor counts (floor, as `servo_rig`)."""
    return rig.count_rad * math.floor(theta / rig.count_rad)


def gauge(rig: FlexibleServoRig, tip_m: float) -> float:
    """The gauge's tip deflection [m]: whole counts of `gauge_resolution_m` (rounded)."""
    return rig.gauge_resolution_m * round(tip_m / rig.gauge_resolution_m)


def reference(t: np.ndarray, rng: np.random.Generator, period_s: float = 1.0, move_s: float = 0.8) -> np.ndarray:
    """Point-to-point moves: every `period_s` a minimum-jerk move of `move_s` to a new
    target, 10-20 deg away from the last, alternating in direction (a move about two
    periods of the first mode long: a shorter one leaves the tip ringing at 20-30 mm,
    whose reaction keeps breaking the hub loose)."""
    ref = np.zeros_like(t)
    here, sign = 0.0, 1.0
    for t0 in np.arange(0.1, t[-1] - move_s, period_s):
        there = here + sign * math.radians(rng.uniform(10.0, 20.0))
        ref = np.where(t >= t0, min_jerk(t, here, there, t0, move_s), ref)
        here, sign = there, -sign
    return ref


@dataclasses.dataclass(frozen=True)
class FlexibleServoLog:
    """One closed-loop run: `t` [s], the true `state` at the samples (`(len(t), 2n + 2)`),
    the recorded `encoder` angle [rad] and `gauge` tip deflection [m], and the commanded
    link-side `torque` [N m] held over `[t_k, t_k+1)`."""

    t: np.ndarray
    state: np.ndarray
    encoder: np.ndarray
    gauge: np.ndarray
    torque: np.ndarray
    tip: np.ndarray

    @property
    def still_fraction(self) -> float:
        """Fraction of the sample intervals over which the hub is exactly still."""
        n = (self.state.shape[1] - 2) // 2
        theta, rate = self.state[:, 0], self.state[:, n + 1]
        return float(np.mean((rate[:-1] == 0.0) & (theta[1:] == theta[:-1])))


def closed_loop(rig: FlexibleServoRig, duration_s: float, rng: np.random.Generator) -> FlexibleServoLog:
    """The digital controller tracking `reference` moves for `duration_s`, from rest."""
    model = link_model(rig)
    n = int(round(duration_s / rig.sample_s)) + 1
    t = np.arange(n) * rig.sample_s
    ref = reference(t, rng)
    states = np.zeros((n, 2 * rig.n_modes + 2))
    enc, gau, torque, tip = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    previous = 0.0
    for k in range(n):
        y = states[k]
        tip[k] = float(model.tip_shape @ y[1 : 1 + rig.n_modes])
        enc[k], gau[k] = encoder(rig, y[0]), gauge(rig, tip[k])
        omega = (enc[k] - previous) / rig.sample_s if k else 0.0
        previous = enc[k]
        u = rig.kp_n_m_per_rad * (ref[k] - enc[k]) - rig.kd_n_m_s_per_rad * omega + rig.k_tip_n_m_per_m * gau[k]
        torque[k] = float(np.clip(u, -rig.torque_limit_n_m, rig.torque_limit_n_m))
        if k + 1 < n:
            states[k + 1] = advance(rig, y, torque[k], rig.sample_s)
    return FlexibleServoLog(t, states, enc, gau, torque, tip)


#: log name -> (seed, role)
LOGS = {"flex_a": (621, "fit"), "flex_b": (622, "fit"), "flex_c": (623, "validation")}
DURATION_S = 2.5


def write_log(rig: FlexibleServoRig, log: FlexibleServoLog, path: Path) -> None:
    """CSV as the drive records it: the motor encoder in counts-exact degrees and the motor
    torque command (link torque / G) in N m, both motor side, and the strain gauge's tip
    deflection in mm, its bridge wired the other way round (the column is `-v(l)`)."""
    motor_deg = np.degrees(log.encoder * rig.gear_ratio)
    motor_torque = log.torque / rig.gear_ratio
    gauge_mm = -1e3 * log.gauge
    lines = [
        "# synthetic flexible-link servo rig (tests/servo_rig_flexible.py): motor side, 4096-count encoder,",
        "# tip gauge bridge wired reversed",
        "time [s],motor [deg],gauge [mm],torque [N m]",
    ]
    rows = zip(log.t.tolist(), motor_deg.tolist(), gauge_mm.tolist(), motor_torque.tolist())
    lines += [f"{tk!r},{a!r},{g!r},{q!r}" for tk, a, g, q in rows]
    path.write_text("\n".join(lines) + "\n")


def write_flexible_servo_experiment(
    folder: Path, rig: FlexibleServoRig = FlexibleServoRig(), hold: str = "zoh"
) -> tuple[Path, dict]:
    """Write the logs and `experiment.toml` into `folder`; returns its path and the logs
    (`name -> FlexibleServoLog`). The baseline: the flexible link with its length, mass per
    length, tip mass and modal damping known (weighed, measured, a ring-down), the hub
    inertia, the joint's viscous damping and `EI` free, no friction; each channel's noise is
    its quantisation, `q / sqrt(12)`."""
    entry = """
[[logs]]
name = "{name}"
file = "{name}.csv"
columns = {{ time = "time [s]", theta1 = "motor [deg]", tip1 = "gauge [mm]", torque1 = "torque [N m]" }}
initial = {{ theta1 = "measured" }}
fit_initial = ["theta1"]
hold = "{hold}"
role = "{role}"

[logs.calibration]
theta1 = {{ gear_ratio = {gear_ratio!r} }}
torque1 = {{ gear_ratio = {gear_ratio!r} }}
tip1 = {{ sign = -1 }}
"""
    logs, entries = write_logs(folder, rig, LOGS, DURATION_S, closed_loop, write_log, entry, hold)
    q, g = rig.count_rad, rig.gauge_resolution_m
    text = f"""# synthetic flexible-link servo rig with stick-slip friction (tests/servo_rig_flexible.py)
[experiment]
name = "flexible servo rig"

[rig]

[[rig.links]]
type = "flexible"
length = {rig.link_length_m!r}
rho = {rig.rho_kg_m!r}
EI = {1.15 * rig.EI_n_m2!r}
n_modes = {rig.n_modes}
damping_ratio = {rig.damping_ratio!r}

[[rig.joints]]
type = "rigid"
damping = 0.02

[[rig.hubs]]
inertia = 0.004

[rig.payload]
mass = {rig.tip_mass_kg!r}

[parameters]
"hub1.inertia" = {{ guess = 0.004, lower = 1e-4, upper = 1.0 }}
"joint1.damping" = {{ guess = 0.02, lower = 1e-5, upper = 1.0 }}
"link1.EI" = {{ guess = {1.15 * rig.EI_n_m2!r}, lower = 0.01, upper = 10.0 }}

[sensors.theta1]
kind = "encoder"
resolution = {q!r}

[sensors.tip1]
kind = "strain_gauge"
resolution = {g!r}

[noise]
theta1 = {q / math.sqrt(12.0)!r}
tip1 = {g / math.sqrt(12.0)!r}
""" + "".join(entries)
    path = folder / "experiment.toml"
    path.write_text(text)
    return path, logs
