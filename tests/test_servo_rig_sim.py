"""The servo rig simulator (tests/servo_rig.py) against closed forms and an independent
integrator: an error there would make the servo diagnosis test (tests/identify/
test_servo_rig.py) check the wrong truth."""

import dataclasses
import math

import numpy as np
import pytest
import scipy.integrate
from servo_rig import LOGS, ServoRig, advance, closed_loop, encoder, open_loop  # tests/ is on sys.path

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
