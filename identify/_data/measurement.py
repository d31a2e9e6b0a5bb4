r"""The measurement model: what lies between the rig's physics and the numbers in a log.

A sensor does not record the model's output `y_c(t)` exactly, and a drive does not
apply the commanded torque exactly. Each effect below is an optional physical
parameter (`None`: absent, the computation is skipped; a value: present, and
`fit`-able by name like the chain's parameters):

| name                    | effect                                        | unit | neutral |
| ----------------------- | --------------------------------------------- | ---- | ------- |
| `sensor.<ch>.gain`      | calibration gain, `m = g y`                   | 1    | 1       |
| `sensor.<ch>.offset`    | calibration offset, `m = y + o` (all logs)    | SI   | 0       |
| `sensor.<ch>.delay`     | transport/filter delay, `m(t) = y(t - d)`     | s    | 0       |
| `sensor.<ch>.highpass`  | AC coupling (first-order high-pass), cut-off  | Hz   | 0       |
| `actuator<i>.lag`       | first-order lag of joint i's applied torque   | s    | 0       |

The recorded value of channel `c` is

    m_c(t) = g_c HP_{f_c}[ y_c(. - d_c) ](t) + o_c      (+ the per-log offsets of a fit)

**Delay.** `y_c(t - d)` is evaluated by cubic Hermite interpolation between the
simulated samples, using the outputs and their exact time derivatives (`dy_c/dt =
dy_c/dy . f(t, y)`, the vector field), so it is fourth-order accurate in the sample
interval and smooth in `d`; before the log's first sample the first value is held
(the rig is at rest before the log starts).

**High-pass** (an AC-coupled channel, e.g. paper 000's charge amplifier with its
~2 Hz cut-off): `m = y - l`, `l' = 2 pi f_c (y - l)`, `l(t_0) = 0` (the coupling
starts discharged, so `f_c = 0` is the identity). Integrated exactly for a signal
that is linear between samples:

    l_{k+1} = y_{k+1} + (l_k - y_k) e^{-x} - (y_{k+1} - y_k) (1 - e^{-x}) / x,   x = 2 pi f_c h_k.

**Actuator lag**: the applied torque `u_a` follows the commanded (logged) torque `u`
through `T u_a' = u - u_a`, `u_a(t_0) = u(t_0)`, solved exactly between samples for the
command as the log's `hold` reads it (`flexdyn.LaggedTorque`; `T = 0` is the identity).
On held commands the derivative in `T` vanishes at `T = 0` (see `flexdyn.LaggedTorque`),
so a fit of the lag on held commands starts from `T > 0`.

**Sensor kinds** (`Sensor.kind`, `KINDS`): what the sensor is, when it is known. A kind
measures some channels only and cannot have some of the effects above; `identify.diagnose`
then does not offer them (`identify.catalogue.kind_left_out`):

| kind            | channels                   | delay | gain | offset | highpass |
| --------------- | -------------------------- | ----- | ---- | ------ | -------- |
| `encoder`       | `theta`, `phi`, `alpha`    | yes   | no   | yes    | no       |
| `potentiometer` | `theta`, `phi`, `alpha`    | yes   | yes  | yes    | no       |
| `strain_gauge`  | `curvature`, `tip`         | yes   | yes  | yes    | yes      |
| `accelerometer` | `accel_x`, `accel_y`       | yes   | yes  | yes    | yes      |
| `optical`       | `end_x`, `end_y`, `tip`    | yes   | yes  | yes    | no       |

**Resolution** (`Sensor.resolution`, SI): the quantisation step of the channel's values.
Uniform quantisation of a signal that crosses many steps adds an error uniform on
`[-q/2, q/2]`, of standard deviation `q / sqrt(12)` (Widrow & Kollar 2008, *Quantization
Noise*, ch. 4), which the model cannot explain; the model-free noise floor of a slow
signal misses most of it (`identify.noise_floor.series_floor` is kept at least at it).
Neither is a parameter: both are static metadata of the sensor.
"""

from __future__ import annotations

import dataclasses
import math
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import flexdyn as fd
from flexdyn._checks import as_float_array

FIELDS = {"gain": "1", "offset": None, "delay": "s", "highpass": "Hz"}
NEUTRAL = {"gain": 1.0, "offset": 0.0, "delay": 0.0, "highpass": 0.0, "lag": 0.0}

_NAME = re.compile(r"^sensor\.(?P<ch>[A-Za-z_]\w*)\.(?P<field>gain|offset|delay|highpass)$|^actuator(?P<j>\d+)\.lag$")


@dataclasses.dataclass(frozen=True)
class SensorKind:
    """A kind of sensor (`KINDS`): `what` it is and what it `measures`, in words; the
    channel families it can measure (`channel_family`: `theta`, `tip`, `end`, `accel`, ...);
    the `Sensor` fields it cannot have, each with the reason in one sentence (`lacks`)."""

    what: str
    measures: str
    channels: tuple[str, ...]
    lacks: dict = dataclasses.field(default_factory=dict)


_ANGLES = ("theta", "phi", "alpha")

#: The sensor kinds a channel may declare (`[sensors.<channel>] kind`); the module
#: docstring's table. Every kind can have a delay (a filter, a bus cycle, a frame) and an
#: offset (an encoder's zero, a bridge's balance, a bias).
KINDS = {
    "encoder": SensorKind(
        "an incremental or absolute quadrature encoder",
        "angles (theta<i>, phi<i>, alpha<i>)",
        _ANGLES,
        {
            "gain": "an encoder's gain is fixed by its counts per revolution",
            "highpass": "an encoder is DC-coupled (it counts position: a constant angle reads constant)",
        },
    ),
    "potentiometer": SensorKind(
        "a rotary potentiometer",
        "angles (theta<i>, phi<i>, alpha<i>)",
        _ANGLES,
        {"highpass": "a potentiometer is DC-coupled (a voltage divider: a constant angle reads constant)"},
    ),
    "strain_gauge": SensorKind(
        "a strain gauge bridge",
        "a root curvature (curvature<i>) or a tip deflection calibrated from it (tip<i>)",
        ("curvature", "tip"),
    ),
    "accelerometer": SensorKind(
        "a MEMS or piezoelectric accelerometer",
        "the end point's acceleration (accel_x, accel_y)",
        ("accel",),
    ),
    "optical": SensorKind(
        "a camera, laser tracker or laser displacement sensor",
        "positions: the end point's (end_x, end_y) or a tip deflection (tip<i>)",
        ("end", "tip"),
        {"highpass": "an optical position measurement is DC-coupled (a still target reads constant)"},
    ),
}


def channel_family(channel: str) -> str:
    """`'theta2'` -> `'theta'`, `'end_x'` -> `'end'`, `'accel_y'` -> `'accel'`."""
    return re.match(r"[a-z]+", channel)[0]


def kind_problem(kind, channel: str) -> str | None:
    """None if `kind` is a known sensor kind that can measure the output `channel`, else
    why not (listing the kinds, or those that fit the channel)."""
    if kind not in KINDS:
        return f"unknown sensor kind {kind!r}; expected one of {', '.join(KINDS)}"
    if channel_family(channel) not in KINDS[kind].channels:
        fits = [k for k, v in KINDS.items() if channel_family(channel) in v.channels]
        return f"{kind} ({KINDS[kind].what}) measures {KINDS[kind].measures}, not {channel}; expected " + (
            f"{' or '.join(fits)} for {channel}, or no kind" if fits else f"no kind for {channel}"
        )
    return None


def lacks(kind: str | None) -> dict:
    """The `Sensor` fields a sensor of `kind` cannot have, field -> why (empty for None)."""
    return {} if kind is None else KINDS[kind].lacks


class Sensor(eqx.Module):
    """Calibration and dynamics of one output channel's sensor (see the module docstring).
    Every field is optional (`None`: absent). `kind` (a `KINDS` name) and `resolution`
    (the quantisation step, SI, > 0) describe the sensor; they are static, not parameters."""

    gain: jax.Array | None = None
    offset: jax.Array | None = None
    delay: jax.Array | None = None
    highpass: jax.Array | None = None
    kind: str | None = eqx.field(static=True, default=None)
    resolution: float | None = eqx.field(static=True, default=None)

    def __init__(self, gain=None, offset=None, delay=None, highpass=None, *, kind=None, resolution=None):
        for name, value in (("gain", gain), ("offset", offset), ("delay", delay), ("highpass", highpass)):
            value = None if value is None else as_float_array(value)
            if value is not None and not isinstance(value, jax.core.Tracer):
                v = np.asarray(value)
                if v.shape != () or not np.isfinite(v) or (name != "offset" and v < 0) or (name == "gain" and v == 0):
                    raise ValueError(f"Sensor.{name}: expected a finite scalar{'' if name == 'offset' else ' >= 0'}")
            setattr(self, name, value)
        if kind is not None and kind not in KINDS:
            raise ValueError(f"Sensor.kind: unknown sensor kind {kind!r}; expected one of {', '.join(KINDS)}")
        for name, why in lacks(kind).items():
            if getattr(self, name) is not None:
                raise ValueError(f"Sensor.{name}: a sensor of kind {kind!r} has none: {why}")
        self.kind = kind
        if resolution is not None and not (
            isinstance(resolution, int | float) and not isinstance(resolution, bool) and 0 < resolution < math.inf
        ):
            raise ValueError(f"Sensor.resolution: expected a quantisation step > 0 (SI), got {resolution!r}")
        self.resolution = None if resolution is None else float(resolution)

    @property
    def described(self) -> dict:
        """The static description as keywords (`kind`, `resolution`), to build a copy."""
        return {"kind": self.kind, "resolution": self.resolution}


class Measurement(eqx.Module):
    """Sensors of the output channels (`{channel: Sensor}`) and the first-order lag of
    each joint's drive (`actuator_lag[i]`, s, or None)."""

    sensors: dict
    actuator_lag: tuple

    def __init__(self, sensors=None, actuator_lag=()):
        self.sensors = dict(sensors or {})
        for c, s in self.sensors.items():
            if not isinstance(s, Sensor):
                raise ValueError(f"Measurement.sensors[{c!r}]: expected a Sensor, got {type(s).__name__}")
        self.actuator_lag = tuple(None if v is None else as_float_array(v) for v in actuator_lag)

    def lag(self, joint: int):
        return self.actuator_lag[joint] if joint < len(self.actuator_lag) else None


def parameter_names(m: Measurement) -> list[str]:
    names = []
    for c in sorted(m.sensors):
        for f in FIELDS:
            if getattr(m.sensors[c], f) is not None:
                names.append(f"sensor.{c}.{f}")
    names.extend(f"actuator{i + 1}.lag" for i, v in enumerate(m.actuator_lag) if v is not None)
    return names


def is_measurement_parameter(name: str) -> bool:
    return _NAME.match(name) is not None


def target(name: str) -> tuple[str | None, int | None]:
    """What a measurement parameter acts on: `(channel, None)` for `sensor.<channel>.<field>`,
    `(None, joint)` (1-based) for `actuator<joint>.lag`."""
    match = _NAME.match(name)
    if match is None:
        raise KeyError(f"{name!r} is not a measurement parameter (sensor.<channel>.<field> or actuator<i>.lag)")
    return (None, int(match["j"])) if match["j"] is not None else (match["ch"], None)


def split_values(values: dict) -> tuple[dict, dict]:
    """`(chain_values, measurement_values)`: named values split into the chain's
    parameters and the measurement's."""
    chain = {n: v for n, v in values.items() if not is_measurement_parameter(n)}
    return chain, {n: v for n, v in values.items() if is_measurement_parameter(n)}


def is_signed(name: str) -> bool:
    return name.endswith(".offset")


def unit(name: str, channel_unit) -> str:
    m = _NAME.match(name)
    if m is None:
        raise KeyError(name)
    if m["j"] is not None:
        return "s"
    return FIELDS[m["field"]] or channel_unit(m["ch"])


def get_parameter(m: Measurement, name: str):
    match = _NAME.match(name)
    if match is None:
        raise KeyError(f"unknown measurement parameter {name!r}")
    if match["j"] is not None:
        value = m.lag(int(match["j"]) - 1)
    else:
        sensor = m.sensors.get(match["ch"])
        value = None if sensor is None else getattr(sensor, match["field"])
    if value is None:
        raise KeyError(f"measurement parameter {name!r} is not in this model; it has: {parameter_names(m)}")
    return value


def with_parameters(m: Measurement, values: dict) -> Measurement:
    """A copy with named parameters replaced (traced values are fine)."""
    for name, value in values.items():
        get_parameter(m, name)  # raises for unknown names
        match = _NAME.match(name)
        value = jnp.asarray(value, dtype=float)
        if match["j"] is not None:
            j = int(match["j"]) - 1
            m = eqx.tree_at(lambda mm: mm.actuator_lag[j], m, value)
        else:
            c, f = match["ch"], match["field"]
            m = eqx.tree_at(lambda mm: getattr(mm.sensors[c], f), m, value)
    return m


def with_effect(m: Measurement, name: str, value=None) -> Measurement:
    """Add the (absent) parameter `name` at `value` (default: its neutral value)."""
    match = _NAME.match(name)
    if match is None:
        raise KeyError(f"{name!r} is not a measurement parameter (sensor.<channel>.<field> or actuator<i>.lag)")
    if match["j"] is not None:
        j = int(match["j"]) - 1
        lags = list(m.actuator_lag) + [None] * max(0, j + 1 - len(m.actuator_lag))
        lags[j] = NEUTRAL["lag"] if value is None else value
        return Measurement(m.sensors, lags)
    c, f = match["ch"], match["field"]
    sensors = dict(m.sensors)
    old = sensors.get(c, Sensor())
    kw = {k: getattr(old, k) for k in FIELDS}
    kw[f] = NEUTRAL[f] if value is None else value
    sensors[c] = Sensor(**kw, **old.described)
    return Measurement(sensors, m.actuator_lag)


def kinds(m: Measurement) -> dict[str, str]:
    """Channel -> sensor kind, for the channels whose sensor declares one."""
    return {c: s.kind for c, s in m.sensors.items() if s.kind is not None}


def resolutions(m: Measurement, channels) -> np.ndarray:
    """Each of `channels`' declared quantisation step (SI; `Sensor.resolution`), 0 where
    none is declared."""
    return np.asarray([(m.sensors[c].resolution or 0.0) if c in m.sensors else 0.0 for c in channels], float)


# ---------------------------------------------------------------------------
# The filters (pure, jit/vmap/grad-safe at the neutral values)
# ---------------------------------------------------------------------------


def _phi(x):
    """(1 - e^{-x}) / x, smooth through x = 0."""
    small = x < 1e-6
    xs = jnp.where(small, 1.0, x)
    return jnp.where(small, 1.0 - 0.5 * x, -jnp.expm1(-xs) / xs)


def first_order_step(l, u0, u1, h, rate):
    """One sample interval `h` (s) of `l' = rate (u - l)` from `l`, `u` linear from `u0`
    to `u1`: exact (`rate` >= 0, 1/s)."""
    x = rate * h
    return u1 + (l - u0) * jnp.exp(-x) - (u1 - u0) * _phi(x)


def _first_order(t, u, rate, start):
    """Exact response `l` of `l' = rate (u - l)`, `l(t_0) = start`, to `u` linear between
    samples `t` (shape (T,) and (T, ...)). `rate` >= 0 (1/s), may be traced."""
    h = jnp.diff(t)

    def step(l, k):
        l1 = first_order_step(l, u[k], u[k + 1], h[k], rate)
        return l1, l1

    _, rest = jax.lax.scan(step, start, jnp.arange(t.shape[0] - 1))
    return jnp.concatenate([start[None], rest], axis=0)


def highpass(t, y, cutoff_hz):
    """First-order high-pass of samples `y` (T,) at times `t`, cut-off `cutoff_hz` (Hz),
    filter state starting at zero (so `cutoff_hz = 0` returns `y`)."""
    return y - _first_order(t, y, 2.0 * jnp.pi * cutoff_hz, jnp.zeros_like(y[0]))


def delayed(t, y, ydot, delay):
    """`y(t - delay)` by cubic Hermite interpolation of samples `y` with derivatives
    `ydot` (both (T,)) at increasing times `t`; the first value is held before `t_0`."""
    s = t - delay
    j = jnp.clip(jnp.searchsorted(t, s, side="right") - 1, 0, t.shape[0] - 2)
    t0, t1 = t[j], t[j + 1]
    h = t1 - t0
    ok = h > 0
    hs = jnp.where(ok, h, 1.0)
    u = jnp.clip(jnp.where(ok, (s - t0) / hs, 0.0), 0.0, 1.0)
    h00 = 2 * u**3 - 3 * u**2 + 1
    h10 = u**3 - 2 * u**2 + u
    h01 = -2 * u**3 + 3 * u**2
    h11 = u**3 - u**2
    value = h00 * y[j] + h10 * hs * ydot[j] + h01 * y[j + 1] + h11 * hs * ydot[j + 1]
    return jnp.where(s <= t[0], y[0], value)


def apply_sensors(m: Measurement, channels, t, out, dout):
    """Recorded values `(T, C)` from model outputs `out` `(T, C)` (and their time
    derivatives `dout`, used only for delayed channels)."""
    cols = []
    for k, c in enumerate(channels):
        y = out[:, k]
        s = m.sensors.get(c)
        if s is not None:
            if s.delay is not None:
                y = delayed(t, y, dout[:, k], s.delay)
            if s.highpass is not None:
                y = highpass(t, y, s.highpass)
            if s.gain is not None:
                y = s.gain * y
            if s.offset is not None:
                y = y + s.offset
        cols.append(y)
    return jnp.stack(cols, axis=1)


def needs_rates(m: Measurement, channels) -> bool:
    return any(c in m.sensors and m.sensors[c].delay is not None for c in channels)


def lag_vector(m: Measurement, n_joints: int):
    """`(n_joints,)` each joint's actuator lag (s, 0 for none), or None if none has one."""
    if not any(v is not None for v in m.actuator_lag):
        return None
    zero = jnp.zeros((), jnp.result_type(float))
    return jnp.stack([zero if m.lag(j) is None else m.lag(j) for j in range(n_joints)])


def actuated_torque(m: Measurement, t, torque, hold):
    """The torque the rig is driven by, as a `flexdyn` input: the commanded (logged)
    samples `torque` `(T, n_joints)` at times `t`, read as `hold` says, through each
    joint's actuator lag where `m` has one (`flexdyn.LaggedTorque`, exact between
    samples; a joint without a lag gets time constant 0, the identity)."""
    command = fd.SampledTorque(t, torque, hold=hold)
    lags = lag_vector(m, torque.shape[1])
    return command if lags is None else fd.LaggedTorque(command, lags)
