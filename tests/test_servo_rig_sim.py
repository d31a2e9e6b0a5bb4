"""The servo rig simulator (tests/servo_rig.py) against closed forms and an independent
integrator: an error there would make the servo diagnosis test (tests/identify/
test_servo_rig.py) check the wrong truth."""

import dataclasses
import math

import numpy as np
import pytest
import scipy.integrate
import scipy.linalg
import scipy.optimize
import servo_rig_flexible  # tests/ is on sys.path
from servo_rig import LOGS, ServoRig, advance, closed_loop, encoder, open_loop

RIG = ServoRig()


def test_stuck_until_the_held_torque_exceeds_breakaway():
    """A torque ramp held sample by sample: the hub stays exactly where it is through every
    sample whose torque is at most F_s = 0.10 N m, and moves in the first one above it."""
    torques = np.linspace(0.0, 0.12, 121)  # 0.001 N m per sample; sample 100 is 0.100 exactly
    theta, rate = open_loop(RIG, torques, theta0=0.3)
    first = int(np.flatnonzero(torques > RIG.breakaway_friction_n_m)[0])
    assert first == 101
    assert np.all(theta[: first + 1] == 0.3) and np.all(rate[: first + 1] == 0.0)
    assert theta[first + 1] > 0.3 and rate[first + 1] > 0.0


def test_coasting_stop_time_and_angle_closed_form():
    """No torque from `v0`: `J v' = -c v - F_c` stops at `t* = (J/c) ln(1 + c v0 / F_c)`,
    at `theta* = (J/c) (v0 - (F_c/c) ln(1 + c v0 / F_c))`, and stays there (F_s > 0)."""
    J, c, Fc, v0 = RIG.inertia_kg_m2, RIG.damping_n_m_s, RIG.sliding_friction_n_m, 2.0
    t_stop = J / c * math.log1p(c * v0 / Fc)
    theta_stop = J / c * (v0 - Fc / c * math.log1p(c * v0 / Fc))
    th, v = advance(RIG, 0.0, v0, 0.0, 0.999 * t_stop)
    assert v > 0.0
    th, v = advance(RIG, 0.0, v0, 0.0, t_stop * (1 + 1e-9))
    assert v == 0.0
    assert th == pytest.approx(theta_stop, rel=1e-9)
    th2, v2 = advance(RIG, 0.0, v0, 0.0, 3 * t_stop)
    assert (th2, v2) == (th, 0.0)


def test_sliding_under_held_torques_matches_an_independent_integrator():
    """Held torques that keep the hub sliding (|tau| > F_s, one sign) and one stop-and-reverse:
    the exact update agrees with DOP853 on `J v' = tau - c v - F_c sign(v)`, integrated
    sample by sample with an event at v = 0."""
    J, c, Fc = RIG.inertia_kg_m2, RIG.damping_n_m_s, RIG.sliding_friction_n_m
    torques = np.r_[np.full(40, 0.4), np.full(60, -0.3)]  # accelerates, then brakes and reverses
    theta, rate = open_loop(RIG, torques)
    y = np.array([0.0, 0.0])
    for k, tau in enumerate(torques):
        t0, t1 = 0.0, RIG.sample_s
        while t1 - t0 > 0:
            s = math.copysign(1.0, y[1]) if y[1] != 0 else math.copysign(1.0, tau)

            def stop(t, z):
                return z[1]

            stop.terminal, stop.direction = True, -s
            sol = scipy.integrate.solve_ivp(
                lambda t, z, s=s, tau=tau: [z[1], (tau - c * z[1] - s * Fc) / J],
                (t0, t1),
                y,
                method="DOP853",
                rtol=1e-12,
                atol=1e-14,
                events=stop if y[1] != 0 else None,
            )
            y = sol.y[:, -1].copy()
            if sol.status == 1:
                y[1] = 0.0
            t0 = sol.t[-1]
        assert theta[k + 1] == pytest.approx(y[0], rel=1e-8, abs=1e-12)
        assert rate[k + 1] == pytest.approx(y[1], rel=1e-8, abs=1e-10)
    assert rate[40] > 0 and rate[-1] < 0  # it did reverse


def test_energy_balance_while_sliding():
    """Work-energy over a sliding stretch: `J (v1^2 - v0^2) / 2 = (tau - F_c) dtheta -
    c int v^2 dt` (the last term by quadrature of the closed-form velocity)."""
    J, c, Fc = RIG.inertia_kg_m2, RIG.damping_n_m_s, RIG.sliding_friction_n_m
    tau, v0, T = 0.3, 0.5, 0.05
    th, v1 = advance(RIG, 0.0, v0, tau, T)
    v_inf = (tau - Fc) / c
    ts = np.linspace(0.0, T, 20001)
    v = v_inf + (v0 - v_inf) * np.exp(-c / J * ts)
    dissipated = c * scipy.integrate.simpson(v**2, x=ts)
    assert 0.5 * J * (v1**2 - v0**2) == pytest.approx((tau - Fc) * th - dissipated, rel=1e-9)


def test_closed_loop_logs_have_the_real_logs_traits():
    """Whole encoder counts; the commanded torque held (one value per sample); the hub
    exactly still 63-73 % of each log, held by stiction between moves (|tau| <= F_s there)."""
    for name, (seed, _) in LOGS.items():
        log = closed_loop(RIG, 3.0, np.random.default_rng(seed))
        counts = log.encoder / RIG.count_rad
        assert np.max(np.abs(counts - np.round(counts))) < 1e-9, name  # (roundoff of n q / q)
        assert np.all(log.encoder <= log.theta) and np.all(log.theta - log.encoder < RIG.count_rad)
        assert 0.63 <= log.still_fraction <= 0.73, (name, log.still_fraction)
        still = (log.rate[:-1] == 0.0) & (log.theta[1:] == log.theta[:-1])
        assert np.all(np.abs(log.torque[:-1][still]) <= RIG.breakaway_friction_n_m)
        assert np.degrees(np.ptp(log.theta)) > 30.0  # it moves: several 15-40 deg moves


def test_encoder_counts_by_floor():
    rig = dataclasses.replace(RIG, counts_per_turn=4, gear_ratio=1.0)  # one count = pi/2
    assert encoder(rig, 1.5) == 0.0 and encoder(rig, 1.6) == pytest.approx(math.pi / 2)
    assert encoder(rig, -0.1) == pytest.approx(-math.pi / 2)


# -- the flexible-link rig (tests/servo_rig_flexible.py) --------------------------------

FLEX = servo_rig_flexible.FlexibleServoRig()


def test_cantilever_roots_without_tip_mass():
    """`mu = 0`: the clamped-free roots of `1 + cos(lam) cosh(lam) = 0`, 1.8751040687 and
    4.6940911330 (Blevins 1979, table 8-1)."""
    lam = servo_rig_flexible.clamped_mass_roots(2, 0.0)
    assert lam == pytest.approx([1.8751040687, 4.6940911330], abs=1e-9)


def test_mode_shapes_meet_the_clamped_tip_mass_boundary_conditions():
    """Each shape is clamped at the root (`phi(0) = phi'(0) = 0`), moment-free at the tip
    (`phi''(l) = 0`) and carries the tip mass's inertia in its shear
    (`EI phi'''(l) = -omega^2 M phi(l)`); unit mean square; positive tip value."""
    model = servo_rig_flexible.link_model(FLEX)
    shapes, L = model.shapes, FLEX.link_length_m
    for j, omega in enumerate(model.clamped_frequency):
        scale = (shapes.lam[j] / L) ** 3  # phi''' ~ beta^3
        assert abs(shapes.derivative(j, 0.0)) < 1e-12 and abs(shapes.derivative(j, 0.0, 1)) < 1e-12 * scale
        assert abs(shapes.derivative(j, L, 2)) < 1e-9 * scale * L
        shear = FLEX.EI_n_m2 * shapes.derivative(j, L, 3)
        assert shear == pytest.approx(-(omega**2) * FLEX.tip_mass_kg * shapes.derivative(j, L), rel=1e-9)
        mean_square = scipy.integrate.quad(lambda x, j=j: shapes.derivative(j, x) ** 2, 0.0, L)[0] / L
        assert mean_square == pytest.approx(1.0, rel=1e-10) and shapes.derivative(j, L) > 0


def test_mass_and_stiffness_integrals_are_the_frequency_equations():
    """The quadrature matrices against the frequency equation's roots: the Rayleigh quotient
    of each exact mode, `K_jj / Mt_jj`, is `omega_j^2 = lam_j^4 / l^4 EI / rho`; the modes
    are orthogonal in the mass with the tip mass (`Mt`) and in the stiffness (`K`); the
    first mode lies at 1.5-3 Hz (a lab's floppy link)."""
    model = servo_rig_flexible.link_model(FLEX)
    omega = model.clamped_frequency
    assert np.diag(model.stiffness) / np.diag(model.modal_mass) == pytest.approx(omega**2, rel=1e-10)
    assert abs(model.modal_mass[0, 1]) < 1e-12 * model.modal_mass[0, 0]
    assert abs(model.stiffness[0, 1]) < 1e-12 * model.stiffness[1, 1]
    assert 1.5 <= omega[0] / (2 * math.pi) <= 3.0


def _pinned_frequency_equation(lam, rig):
    """The exact frequency equation of the free (frictionless, undamped) hub-beam-tip-mass
    system, linearised: `W(x) = A cos + B sin + C cosh + D sinh (beta x)` of the absolute
    deflection with `W(0) = 0`, `EI W''(0) = -omega^2 I_hub W'(0)` (the hub's inertia
    turns with the root slope), `W''(l) = 0`, `EI W'''(l) = -omega^2 M W(l)`; the
    determinant of the rows scaled to unit size."""
    L, EI, rho = rig.link_length_m, rig.EI_n_m2, rig.rho_kg_m
    b = lam / L
    w2 = b**4 * EI / rho
    c, s, ch, sh = math.cos(lam), math.sin(lam), math.cosh(lam), math.sinh(lam)
    Jh, M = rig.hub_inertia_kg_m2, rig.tip_mass_kg
    shear = EI * b**3
    rows = np.array(
        [
            [1.0, 0.0, 1.0, 0.0],
            [-EI * b * b, w2 * Jh * b, EI * b * b, w2 * Jh * b],
            [-c, -s, ch, sh],
            [shear * s + w2 * M * c, -shear * c + w2 * M * s, shear * sh + w2 * M * ch, shear * ch + w2 * M * sh],
        ]
    )
    return np.linalg.det(rows / np.abs(rows).max(axis=1, keepdims=True))


def test_free_hub_frequencies_converge_to_the_pinned_frequency_equation():
    """The frictionless, undamped rig linearised about rest (`[[J, B^T], [B, Mt]]`,
    `diag(0, K)`): a rigid-body mode at 0 and flexible ones that approach the exact roots
    of the free-hub frequency equation from above (Rayleigh-Ritz) as modes are added; with
    the rig's two clamped-mass modes the first is within 1e-5 of the exact 4.35 Hz. Checks
    the hub-link coupling `B` and the inertia `J`, which the clamped modes do not."""
    grid = np.linspace(0.3, 6.0, 2000)
    values = np.array([_pinned_frequency_equation(x, FLEX) for x in grid])
    cells = np.flatnonzero(np.sign(values[:-1]) != np.sign(values[1:]))
    equation = _pinned_frequency_equation
    lam = [scipy.optimize.brentq(equation, grid[i], grid[i + 1], args=(FLEX,), xtol=1e-14) for i in cells]
    exact = np.array(lam[:2]) ** 2 / FLEX.link_length_m**2 * math.sqrt(FLEX.EI_n_m2 / FLEX.rho_kg_m)
    errors = []
    for n in (1, 2, 3):
        model = servo_rig_flexible.link_model(dataclasses.replace(FLEX, n_modes=n))
        mass = np.zeros((n + 1, n + 1))
        mass[0, 0], mass[0, 1:], mass[1:, 0], mass[1:, 1:] = (
            model.inertia,
            model.coupling,
            model.coupling,
            model.modal_mass,
        )
        stiffness = np.zeros((n + 1, n + 1))
        stiffness[1:, 1:] = model.stiffness
        omega = np.sqrt(np.abs(scipy.linalg.eigh(stiffness, mass, eigvals_only=True)))
        assert omega[0] < 1e-6 * omega[1]  # the hub turning the straight link
        assert omega[1] >= exact[0] * (1 - 1e-12)
        errors.append(omega[1] / exact[0] - 1)
    assert errors[0] > errors[1] > errors[2] >= -1e-12
    assert errors[1] < 1e-5
    assert exact[0] / (2 * math.pi) == pytest.approx(4.35, abs=0.01)


def _rest_with_deflection(q0):
    n = FLEX.n_modes
    y = np.zeros(2 * n + 2)
    y[1 : 1 + n] = q0
    return y


def test_stuck_hub_holds_a_ringing_link_at_the_clamped_frequencies():
    """A held hub (|held torque + the link's reaction| <= F_s throughout) stays exactly
    where it is while each mode rings as a damped clamped oscillator:
    `q(t) = e^{-zeta w t} (q0 cos(w_d t) + zeta w q0 / w_d sin(w_d t))`."""
    model = servo_rig_flexible.link_model(FLEX)
    n, zeta = FLEX.n_modes, FLEX.damping_ratio
    q0 = np.array([2e-3, 1e-4])  # ~4 mm at the tip: a reaction of ~0.05 N m < F_s
    y = _rest_with_deflection(q0)
    y[0] = 0.2
    for k in range(1, 201):
        y = servo_rig_flexible.advance(FLEX, y, 0.02, 2e-3)
        assert y[0] == 0.2 and y[n + 1] == 0.0, k
        t = 2e-3 * k
        w = model.clamped_frequency
        wd = w * math.sqrt(1 - zeta**2)
        q = np.exp(-zeta * w * t) * (q0 * np.cos(wd * t) + zeta * w * q0 / wd * np.sin(wd * t))
        assert y[1 : 1 + n] == pytest.approx(q, rel=1e-7, abs=1e-12), k


def test_the_ringing_link_breaks_the_hub_loose_between_controller_updates():
    """Under a held torque just below F_s, the ringing link's reaction adds to it; the hub
    breaks away at the instant `tau + B^T Mt^-1 K q(t)` (closed-form ringing) reaches F_s,
    not at the next controller update."""
    model = servo_rig_flexible.link_model(FLEX)
    n, zeta = FLEX.n_modes, FLEX.damping_ratio
    tau, q0 = 0.09, np.array([-1.5e-3, 0.0])  # the reaction starts at -0.018 N m, swings to +0.018
    w = model.clamped_frequency
    wd = w * math.sqrt(1 - zeta**2)
    reaction_gain = model.coupling @ np.linalg.solve(model.modal_mass, np.eye(n))

    def held(t):
        decay = np.exp(-zeta * w * t)
        q = decay * (q0 * np.cos(wd * t) + zeta * w * q0 / wd * np.sin(wd * t))
        qd = -decay * q0 * w**2 / wd * np.sin(wd * t)
        return tau + reaction_gain @ (model.stiffness @ q + model.modal_damping @ qd) - FLEX.breakaway_friction_n_m

    t_break = scipy.optimize.brentq(held, 0.0, math.pi / wd[0], xtol=1e-14)  # before the reaction's peak
    y0 = _rest_with_deflection(q0)
    before = servo_rig_flexible.advance(FLEX, y0, tau, t_break - 1e-6)
    after = servo_rig_flexible.advance(FLEX, y0, tau, t_break + 1e-4)
    assert before[n + 1] == 0.0 and before[0] == 0.0
    assert after[n + 1] > 0.0 and after[0] > 0.0
    assert t_break % FLEX.sample_s > 1e-5  # (not a sample instant)


def test_energy_balance_while_sliding_with_the_link_bending():
    """Without viscous and modal damping, work-energy is exact over a sliding stretch:
    `E1 - E0 = (tau - F_c) (theta1 - theta0)`, whatever the link does (the velocity terms
    of the equations, `2 theta' q^T Mt q'` and `theta'^2 Mt q`, do no work)."""
    rig = dataclasses.replace(FLEX, damping_n_m_s=0.0, damping_ratio=0.0)
    model = servo_rig_flexible.link_model(rig)
    n, tau = rig.n_modes, 0.4
    y0 = _rest_with_deflection([3e-3, -2e-4])
    y0[n + 1] = 2.0  # fast enough that theta'^2 matters: 2 rad/s against w1 = 14.8 rad/s
    y1 = servo_rig_flexible.advance(rig, y0, tau, 0.3)
    assert y1[n + 1] > 0.0  # slid throughout
    work = (tau - rig.sliding_friction_n_m) * (y1[0] - y0[0])
    e0, e1 = servo_rig_flexible.energy(model, rig, y0), servo_rig_flexible.energy(model, rig, y1)
    assert e1 - e0 == pytest.approx(work, rel=1e-8)


@pytest.mark.slow  # ~20 s on 2 loaded cores, nearly all of it flexdyn's compilation
def test_frictionless_flexible_rig_is_flexdyns_model():
    """With no dry friction, the simulation under held torques is flexdyn's simulation of
    the same rig (a `FlexibleLink` with the payload, 2 modes) to 1e-9: the diagnosis's
    baseline plus `joint1.coulomb` can represent the rig, up to the stiction and the
    smoothed friction law."""
    import jax.numpy as jnp

    import flexdyn as fd

    rig = dataclasses.replace(FLEX, sliding_friction_n_m=0.0, breakaway_friction_n_m=0.0)
    link = fd.FlexibleLink(rig.link_length_m, rig.rho_kg_m, rig.EI_n_m2, n_modes=2, damping_ratio=rig.damping_ratio)
    chain = fd.Chain(
        [link], [fd.RigidJoint(damping=rig.damping_n_m_s)], [fd.Hub(inertia=rig.hub_inertia_kg_m2)], fd.Payload(0.05)
    )
    torques = np.r_[np.full(80, 0.3), np.full(100, -0.25), np.full(60, 0.05)]
    ts = np.arange(len(torques) + 1) * rig.sample_s
    y = np.array([0.1, 1e-3, 0.0, 0.5, 0.0, 0.0])
    ours = [y]
    for tau in torques:
        ours.append(servo_rig_flexible.advance(rig, ours[-1], tau, rig.sample_s))
    ours = np.array(ours)
    held = fd.SampledTorque(jnp.asarray(ts[:-1]), jnp.asarray(torques[:, None]), hold="zoh")
    theirs = fd.simulate(chain, jnp.asarray(y), jnp.asarray(ts), held, rtol=1e-10, atol=1e-12)
    assert np.max(np.abs(np.asarray(theirs.Q) - ours[:, :3])) < 1e-9
    assert np.max(np.abs(ours[:, 1])) > 5e-3  # the link did bend


def test_flexible_closed_loop_logs_have_the_real_logs_traits():
    """Whole encoder counts (floor) and whole gauge counts (nearest); the hub exactly
    still for 45-60 % of each log, held by stiction (|held torque + the link's reaction|
    <= F_s at every still sample) while the tip still moves; several-degree moves and a
    tip deflection of millimetres (small against the 0.45 m link)."""
    model = servo_rig_flexible.link_model(FLEX)
    n = FLEX.n_modes
    for name, (seed, _) in servo_rig_flexible.LOGS.items():
        log = servo_rig_flexible.closed_loop(FLEX, servo_rig_flexible.DURATION_S, np.random.default_rng(seed))
        theta = log.state[:, 0]
        counts = log.encoder / FLEX.count_rad
        assert np.max(np.abs(counts - np.round(counts))) < 1e-9, name
        assert np.all(log.encoder <= theta) and np.all(theta - log.encoder < FLEX.count_rad)
        assert np.all(np.abs(log.gauge - log.tip) <= FLEX.gauge_resolution_m / 2 + 1e-15)
        assert 0.45 <= log.still_fraction <= 0.60, (name, log.still_fraction)
        still = (log.state[:-1, n + 1] == 0.0) & (theta[1:] == theta[:-1])
        reaction = [servo_rig_flexible.stick_torque(model, FLEX, y, u) for y, u in zip(log.state[:-1], log.torque[:-1])]
        assert np.all(np.abs(np.array(reaction)[still]) <= FLEX.breakaway_friction_n_m), name
        assert np.ptp(log.tip[:-1][still]) > 1e-3  # the link rings while the hub is held
        assert np.degrees(np.ptp(theta)) > 8.0
        assert 3e-3 < np.max(np.abs(log.tip)) < 0.02
