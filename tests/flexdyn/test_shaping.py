"""ZV / ZVD input shapers (flexdyn.shaping) against closed forms: the analytic step response of a damped
second-order mode, Singer & Seering's residual-vibration expression, and the shapers' defining properties."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import flexdyn as fd  # noqa: F401  (float64)
from flexdyn import shaping

DESIGN_HZ = 2.0


def step_response(t, natural_frequency, damping_ratio):
    """Position and rate of `x'' + 2 zeta w x' + w^2 x = w^2 u` for a unit step at t = 0 from rest (0 for t < 0)."""
    w = 2 * jnp.pi * natural_frequency
    root = jnp.sqrt(1 - damping_ratio**2)
    wd = w * root
    tau = jnp.maximum(t, 0.0)
    decay = jnp.exp(-damping_ratio * w * tau)
    x = 1 - decay * (jnp.cos(wd * tau) + damping_ratio / root * jnp.sin(wd * tau))
    x_dot = w / root * decay * jnp.sin(wd * tau)
    return jnp.where(t >= 0, x, 0.0), jnp.where(t >= 0, x_dot, 0.0)


def shaped_step_residual(shaper, t, natural_frequency, damping_ratio):
    """(x - 1, x_dot) of the mode driven by the shaped unit step, at time t."""
    x, x_dot = 0.0, 0.0
    for a, ti in zip(shaper.amplitudes, shaper.times):
        xi, vi = step_response(t - ti, natural_frequency, damping_ratio)
        x, x_dot = x + a * xi, x_dot + a * vi
    return jnp.stack([x - 1, x_dot])


def envelope(residual, natural_frequency, damping_ratio):
    """Amplitude R e^{-zeta w t} of a free damped oscillation e(t) from its state (e, e_dot)."""
    w = 2 * jnp.pi * natural_frequency
    wd = w * jnp.sqrt(1 - damping_ratio**2)
    e, e_dot = residual
    return jnp.sqrt(e**2 + ((e_dot + damping_ratio * w * e) / wd) ** 2)


SHAPERS = {"zv": shaping.zv_shaper, "zvd": shaping.zvd_shaper}


@pytest.mark.parametrize("kind", ["zv", "zvd"])
@pytest.mark.parametrize("zeta", [0.0, 0.05, 0.3])
def test_impulses_sum_to_one_and_times(kind, zeta):
    sh = SHAPERS[kind](DESIGN_HZ, zeta)
    assert float(jnp.sum(sh.amplitudes)) == pytest.approx(1.0, abs=1e-15)
    assert np.all(np.asarray(sh.amplitudes) > 0)
    half = 0.5 / (DESIGN_HZ * np.sqrt(1 - zeta**2))  # half damped period, s
    expected = [0.0, half] if kind == "zv" else [0.0, half, 2 * half]
    np.testing.assert_allclose(np.asarray(sh.times), expected, rtol=1e-14, atol=0)


@pytest.mark.parametrize("kind", ["zv", "zvd"])
@pytest.mark.parametrize("zeta", [0.0, 0.05, 0.3])
def test_shaped_step_leaves_no_residual_vibration_at_design_frequency(kind, zeta):
    sh = SHAPERS[kind](DESIGN_HZ, zeta)
    ts = float(sh.duration) + jnp.linspace(0.0, 2.0, 41)
    residual = jax.vmap(lambda t: shaped_step_residual(sh, t, DESIGN_HZ, zeta))(ts)
    assert float(jnp.max(jnp.abs(residual[:, 0]))) < 1e-13  # m per unit step
    assert float(jnp.max(jnp.abs(residual[:, 1]))) < 1e-12 * 2 * np.pi * DESIGN_HZ
    # the unshaped step rings: the check above can fail
    raw = jax.vmap(lambda t: jnp.stack(step_response(t, DESIGN_HZ, zeta)))(ts)
    assert float(jnp.max(jnp.abs(raw[:, 0] - 1))) > 1e-2


@pytest.mark.parametrize("kind", ["zv", "zvd"])
@pytest.mark.parametrize("ratio", [0.7, 0.9, 1.15, 1.5])
def test_residual_vibration_formula_matches_analytic_response(kind, ratio):
    # off the design frequency the shaped residual is Singer & Seering's V times that of an unshaped step applied at
    # the last impulse's time (V's factor exp(-zeta w t_N))
    zeta = 0.05
    sh = SHAPERS[kind](DESIGN_HZ, zeta)
    f = ratio * DESIGN_HZ
    t = float(sh.duration) + 0.37
    shaped = envelope(shaped_step_residual(sh, t, f, zeta), f, zeta)
    x, x_dot = step_response(jnp.asarray(t) - sh.duration, f, zeta)
    unshaped = envelope(jnp.stack([x - 1, x_dot]), f, zeta)
    V = sh.residual_vibration(f, zeta)
    assert float(V) > 1e-3
    assert float(shaped / unshaped) == pytest.approx(float(V), rel=1e-11)


@pytest.mark.parametrize("zeta", [0.0, 0.05])
def test_zvd_is_insensitive_to_frequency_error(zeta):
    t = 1.7  # s, after both shapers' last impulse

    def residual_state(kind, f):
        return shaped_step_residual(SHAPERS[kind](DESIGN_HZ, zeta), t, f, zeta)

    d_zvd = jax.jacfwd(lambda f: residual_state("zvd", f))(jnp.asarray(DESIGN_HZ))
    d_zv = jax.jacfwd(lambda f: residual_state("zv", f))(jnp.asarray(DESIGN_HZ))
    # derivative of the residual (m per unit step per Hz, and its rate) w.r.t. the plant's frequency
    assert float(jnp.max(jnp.abs(d_zvd))) < 1e-12
    assert float(jnp.max(jnp.abs(d_zv))) > 0.1
    # so V grows quadratically in the frequency error for ZVD, linearly for ZV
    zvd, zv = shaping.zvd_shaper(DESIGN_HZ, zeta), shaping.zv_shaper(DESIGN_HZ, zeta)
    small, big = DESIGN_HZ * 1.005, DESIGN_HZ * 1.01
    assert float(zvd.residual_vibration(big, zeta) / zvd.residual_vibration(small, zeta)) == pytest.approx(4, rel=0.02)
    assert float(zv.residual_vibration(big, zeta) / zv.residual_vibration(small, zeta)) == pytest.approx(2, rel=0.02)
    assert float(zvd.residual_vibration(DESIGN_HZ, zeta)) < 1e-14


def test_shaped_torque_convolves_and_lists_jumps():
    base = fd.BangBang([0.2, -0.1], 0.5)
    zv, zvd = shaping.zv_shaper(DESIGN_HZ, 0.02), shaping.zvd_shaper(3.0, 0.0)
    shaped = shaping.ShapedTorque(base, (zv, zvd))
    ts = jnp.linspace(-0.1, 2.0, 97)
    got = jax.vmap(lambda t: shaped(t, None))(ts)
    expect0 = sum(a * jax.vmap(lambda t: base(t - ti)[0])(ts) for a, ti in zip(zv.amplitudes, zv.times))
    expect1 = sum(a * jax.vmap(lambda t: base(t - ti)[1])(ts) for a, ti in zip(zvd.amplitudes, zvd.times))
    np.testing.assert_allclose(np.asarray(got[:, 0]), np.asarray(expect0), rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(got[:, 1]), np.asarray(expect1), rtol=0, atol=1e-15)
    assert shaped.jump_times().shape == (3 * 2 + 3 * 3,)
    # one shaper shared by all joints; a shaped bang-bang never exceeds the base amplitude
    shared = shaping.ShapedTorque(base, zvd)
    vals = jax.vmap(lambda t: shared(t, None))(ts)
    assert float(jnp.max(jnp.abs(vals[:, 0]))) <= 0.2 + 1e-15


def test_shaped_reference_reaches_the_same_goal():
    ref = fd.QuinticReference([0.0, 0.0], [np.pi / 2, np.pi / 6], 2.0)
    sh = shaping.zvd_shaper(DESIGN_HZ, 0.05)
    shaped = shaping.ShapedReference(ref, sh)
    t_end = 2.0 + float(sh.duration)
    np.testing.assert_allclose(np.asarray(shaped.position(t_end)), [np.pi / 2, np.pi / 6], rtol=1e-14)
    np.testing.assert_allclose(np.asarray(shaped.velocity(t_end + 0.1)), 0.0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(shaped.position(0.0)), 0.0, atol=1e-15)
    # velocity is the derivative of position
    dpos = jax.jacfwd(shaped.position)(jnp.asarray(1.3))
    np.testing.assert_allclose(np.asarray(dpos), np.asarray(shaped.velocity(1.3)), rtol=1e-12)


@pytest.mark.parametrize("make", [shaping.zv_shaper, shaping.zvd_shaper])
def test_shaper_arguments_checked(make):
    # Review: NaN / zero / negative frequencies gave NaN or inf or negative impulse times
    # (a negative one broke "ascending, first 0" and applied the full step at t = 0), and a
    # damping ratio outside [0, 1) NaN amplitudes or was accepted.
    for f in (np.nan, 0.0, -5.8):
        with pytest.raises(ValueError, match="natural_frequency"):
            make(f)
    for zeta in (np.nan, -0.1, 1.0, 1.5):
        with pytest.raises(ValueError, match=r"damping_ratio: expected 0 <= zeta < 1"):
            make(3.0, zeta)
    # traced values pass through (jit/vmap/grad over the design frequency)
    times = jax.vmap(lambda f: make(f).times)(jnp.asarray([2.0, 4.0]))
    np.testing.assert_allclose(np.asarray(times)[:, 1], [0.25, 0.125])
