"""The measurement model (identify.measurement) against closed forms: first-order
high-pass and lag responses, Hermite-interpolated delay, neutral values, derivatives."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import flexdyn as fd
from identify._data import measurement as meas


def test_highpass_of_a_ramp_is_the_closed_form():
    # l' = wc (y - l), l(0) = 0, y = t  ->  m = y - l = (1 - e^{-wc t}) / wc
    fc = 0.7
    wc = 2 * math.pi * fc
    t = np.linspace(0.0, 3.0, 301)
    m = np.asarray(meas.highpass(jnp.asarray(t), jnp.asarray(t), fc))
    np.testing.assert_allclose(m, (1 - np.exp(-wc * t)) / wc, rtol=1e-12, atol=1e-14)


def test_highpass_of_a_sine_has_the_first_order_gain_in_steady_state():
    fc, f = 2.0, 5.0
    t = np.linspace(0.0, 4.0, 40001)
    y = np.sin(2 * math.pi * f * t)
    m = np.asarray(meas.highpass(jnp.asarray(t), jnp.asarray(y), fc))
    tail = t > 2.0
    gain = np.sqrt(2 * np.mean(m[tail] ** 2))
    assert gain == pytest.approx(f / math.hypot(f, fc), rel=1e-4)


def test_delay_by_hermite_interpolation():
    f, d = 1.3, 0.0137
    t = np.linspace(0.0, 2.0, 201)  # 77 samples per period
    w = 2 * math.pi * f
    y, ydot = np.sin(w * t), w * np.cos(w * t)
    out = np.asarray(meas.delayed(jnp.asarray(t), jnp.asarray(y), jnp.asarray(ydot), d))
    late = t >= d
    # cubic Hermite error <= h^4 max|y''''| / 384
    bound = (t[1] - t[0]) ** 4 * w**4 / 384
    np.testing.assert_allclose(out[late], np.sin(w * (t[late] - d)), atol=1.01 * bound)
    np.testing.assert_array_equal(out[~late], y[0])
    np.testing.assert_allclose(
        np.asarray(meas.delayed(jnp.asarray(t), jnp.asarray(y), jnp.asarray(ydot), 0.0)), y, atol=1e-15
    )


@pytest.mark.parametrize(
    "fn, neutral",
    [
        (lambda p, t, y: meas.highpass(t, y, p), 0.0),
        (lambda p, t, y: jax.vmap(fd.LaggedTorque(fd.SampledTorque(t, y), p))(t)[:, 0], 0.0),
        (lambda p, t, y: meas.delayed(t, y, jnp.cos(t), p), 0.0),
    ],
)
def test_derivative_at_the_neutral_value_is_finite_and_nonzero(fn, neutral):
    t = jnp.linspace(0.0, 2.0, 201)
    y = jnp.sin(t)
    d = np.asarray(jax.jacfwd(lambda p: fn(p, t, y))(jnp.asarray(neutral)))
    assert np.all(np.isfinite(d)) and np.max(np.abs(d)) > 0


def test_apply_sensors_gain_offset_and_names():
    m = meas.Measurement({"theta1": meas.Sensor(gain=1.0, offset=0.0)}, actuator_lag=[0.0])
    assert meas.parameter_names(m) == ["sensor.theta1.gain", "sensor.theta1.offset", "actuator1.lag"]
    m = meas.with_parameters(m, {"sensor.theta1.gain": 1.1, "sensor.theta1.offset": 0.02})
    t = jnp.linspace(0.0, 1.0, 11)
    out = jnp.stack([jnp.sin(t), jnp.cos(t)], axis=1)
    rec = np.asarray(meas.apply_sensors(m, ("theta1", "tip1"), t, out, out))
    np.testing.assert_allclose(rec[:, 0], 1.1 * np.sin(t) + 0.02, rtol=1e-14)
    np.testing.assert_array_equal(rec[:, 1], np.cos(t))
    with pytest.raises(KeyError, match="not in this model"):
        meas.get_parameter(m, "sensor.tip1.delay")
    with pytest.raises(ValueError, match="Sensor.delay"):
        meas.Sensor(delay=-1.0)


def test_a_sensors_kind_and_resolution_are_static_and_survive_copies():
    """`kind` and `resolution` describe the sensor (not parameters): no leaves of the
    pytree, kept by `with_effect` and `with_parameters`, checked when a Sensor is built."""
    m = meas.Measurement({"theta1": meas.Sensor(offset=0.01, kind="encoder", resolution=1.5e-3)})
    assert [float(x) for x in jax.tree_util.tree_leaves(m)] == [0.01]
    m = meas.with_parameters(meas.with_effect(m, "sensor.theta1.delay"), {"sensor.theta1.offset": 0.02})
    s = m.sensors["theta1"]
    assert (s.kind, s.resolution, float(s.offset), float(s.delay)) == ("encoder", 1.5e-3, 0.02, 0.0)
    assert meas.kinds(m) == {"theta1": "encoder"}
    np.testing.assert_array_equal(meas.resolutions(m, ("tip1", "theta1")), [0.0, 1.5e-3])
    with pytest.raises(ValueError, match="Sensor.gain: a sensor of kind 'encoder' has none: .*counts per revolution"):
        meas.with_effect(m, "sensor.theta1.gain")
    with pytest.raises(ValueError, match="Sensor.highpass: .*'potentiometer'.*DC-coupled"):
        meas.Sensor(highpass=1.0, kind="potentiometer")
    with pytest.raises(ValueError, match="Sensor.kind: unknown sensor kind 'lvdt'; expected one of encoder"):
        meas.Sensor(kind="lvdt")
    for bad in (0.0, -1e-3, float("inf"), True):
        with pytest.raises(ValueError, match="Sensor.resolution: expected a quantisation step > 0"):
            meas.Sensor(resolution=bad)


@pytest.mark.parametrize(
    ("kind", "channel", "fits"),
    [
        ("encoder", "theta2", True),
        ("encoder", "phi1", True),
        ("encoder", "alpha1", True),
        ("encoder", "tip1", False),
        ("potentiometer", "alpha2", True),
        ("potentiometer", "curvature1", False),
        ("strain_gauge", "curvature1", True),
        ("strain_gauge", "tip1", True),
        ("strain_gauge", "end_x", False),
        ("accelerometer", "accel_y", True),
        ("accelerometer", "theta1", False),
        ("optical", "end_y", True),
        ("optical", "tip2", True),
        ("optical", "curvature1", False),
    ],
)
def test_each_kind_measures_its_quantities_only(kind, channel, fits):
    why = meas.kind_problem(kind, channel)
    assert (why is None) is fits
    if not fits:
        assert f"not {channel}" in why and why.endswith("or no kind")


def test_a_synthetic_log_of_a_quantised_sensor_records_whole_steps():
    """`simulate_log` with a `Sensor.resolution`: the channel holds whole steps (an
    encoder's counts), within half a step of the noise-free record; others unchanged."""
    import flexdyn as fd
    from identify._model.synthetic import simulate_log

    q = 2 * np.pi / 4096  # a 4096-count encoder, rad
    chain = fd.rigs.rigid_pendulum()
    t = np.arange(0.0, 2.0, 0.01)
    common = dict(initial={"theta1": 0.3}, channels=("theta1",))
    exact = simulate_log(chain, t, **common).outputs["theta1"]
    m = meas.Measurement(sensors={"theta1": meas.Sensor(kind="encoder", resolution=q)})
    counted = simulate_log(chain, t, measurement=m, **common).outputs["theta1"]
    np.testing.assert_allclose(counted / q, np.round(counted / q), atol=1e-9)
    assert np.max(np.abs(counted - exact)) <= 0.5 * q + 1e-12
    assert len(np.unique(counted)) > 20  # (it moves across many counts)
    plain = simulate_log(chain, t, measurement=meas.Measurement(), **common).outputs["theta1"]
    np.testing.assert_array_equal(plain, exact)
