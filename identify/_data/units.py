"""Units of measured logs and the channel vocabulary of the model.

A log column is named `name [unit]` (e.g. `tip1 [mm]`). `UNITS` lists every unit a
log may use, with its physical dimension and its factor to SI; volts (`V`, `mV`)
are a dimension of their own and are converted with a per-channel calibration
`SI = scale * volts + offset` given in the experiment file.

Channels are what the model predicts or is driven by (the experiment file's
vocabulary), each with a dimension used to check a log's units:

| channel        | meaning                                           | dimension    | SI unit |
|----------------|---------------------------------------------------|--------------|---------|
| `time`         | sample time                                       | time         | s       |
| `theta{i}`     | link angle of joint i                             | angle        | rad     |
| `phi{i}`       | absolute angle of link i (base frame)             | angle        | rad     |
| `alpha{i}`     | rotor angle of elastic joint i (link side)        | angle        | rad     |
| `tip{i}`       | elastic tip deflection of link i                  | length       | m       |
| `curvature{i}` | bending curvature at the root of link i           | curvature    | 1/m     |
| `end_x/end_y`  | end-point position (base frame)                   | length       | m       |
| `accel_x/_y`   | end-point acceleration (base frame)               | acceleration | m/s^2   |
| `torque{i}`    | torque applied at joint i (input)                 | torque       | N m     |
| `voltage{i}`   | voltage command of joint i's motor (input)        | voltage      | V       |
| `current{i}`   | current command of joint i's motor (input)        | current      | A       |

A joint's input is one of `torque{i}`, `voltage{i}`, `current{i}`: the last two drive a
`flexdyn.DCMotor` on the joint (`[rig.motors.joint<i>]`) whose `drive` they match, a torque
drives a joint without a motor or a motor behind a torque amplifier (`drive = "torque"`).
A voltage channel's column in volts needs no calibration (it is already in SI).

A strain gauge's column in a strain unit (`[ue]`) maps to `curvature{i}` with the gauge's
distance from the neutral axis (`identify.logs.Calibration.neutral_axis_distance`).
"""

from __future__ import annotations

import math
import re

import numpy as np

TIME = "time"
ANGLE = "angle"
LENGTH = "length"
CURVATURE = "curvature"
ACCELERATION = "acceleration"
TORQUE = "torque"
VOLTAGE = "voltage"
CURRENT = "current"
FREQUENCY = "frequency"
#: a strain gauge's reading (dimensionless); a curvature once divided by the gauge's
#: distance from the neutral axis (`identify.logs.Calibration.neutral_axis_distance`)
STRAIN = "strain"

#: SI unit of each dimension (volts have none: they need a calibration).
SI_UNIT = {
    TIME: "s",
    ANGLE: "rad",
    LENGTH: "m",
    CURVATURE: "1/m",
    ACCELERATION: "m/s^2",
    TORQUE: "N m",
    VOLTAGE: "V",
    CURRENT: "A",
    FREQUENCY: "Hz",
    STRAIN: "strain",
}

#: unit -> (dimension, factor to SI).
UNITS: dict[str, tuple[str, float]] = {
    "s": (TIME, 1.0),
    "ms": (TIME, 1e-3),
    "us": (TIME, 1e-6),
    "rad": (ANGLE, 1.0),
    "mrad": (ANGLE, 1e-3),
    "deg": (ANGLE, math.pi / 180.0),
    "m": (LENGTH, 1.0),
    "cm": (LENGTH, 1e-2),
    "mm": (LENGTH, 1e-3),
    "um": (LENGTH, 1e-6),
    "1/m": (CURVATURE, 1.0),
    "strain": (STRAIN, 1.0),
    "ue": (STRAIN, 1e-6),
    "m/s^2": (ACCELERATION, 1.0),
    "g": (ACCELERATION, 9.80665),  # standard gravity, as accelerometers are rated
    "N m": (TORQUE, 1.0),
    "N cm": (TORQUE, 1e-2),
    "N mm": (TORQUE, 1e-3),
    "mN m": (TORQUE, 1e-3),
    "V": (VOLTAGE, 1.0),
    "mV": (VOLTAGE, 1e-3),
    "A": (CURRENT, 1.0),
    "mA": (CURRENT, 1e-3),
    "Hz": (FREQUENCY, 1.0),
    "kHz": (FREQUENCY, 1e3),
}

#: Other spellings accepted for the same units.
ALIASES = {
    "sec": "s",
    "µs": "us",
    "μs": "us",
    "degree": "deg",
    "degrees": "deg",
    "Deg": "deg",
    "DEG": "deg",
    "Degree": "deg",
    "Degrees": "deg",
    "Rad": "rad",
    "RAD": "rad",
    "SEC": "s",
    "Sec": "s",
    "°": "deg",
    "µm": "um",
    "μm": "um",
    "m/s2": "m/s^2",
    "m/s²": "m/s^2",
    "Nm": "N m",
    "N*m": "N m",
    "N.m": "N m",
    "N·m": "N m",
    "Ncm": "N cm",
    "N*cm": "N cm",
    "N.cm": "N cm",
    "N·cm": "N cm",
    "Nmm": "N mm",
    "N*mm": "N mm",
    "N.mm": "N mm",
    "N·mm": "N mm",
    "mNm": "mN m",
    "hz": "Hz",
    "m/m": "strain",
    "µε": "ue",
    "με": "ue",
    "uε": "ue",
    "microstrain": "ue",
    "µstrain": "ue",
    "ustrain": "ue",
    "mN*m": "mN m",
    "mN.m": "mN m",
}

_INDEXED = re.compile(r"^(theta|phi|alpha|tip|curvature|torque|voltage|current)([1-9][0-9]*)$")
_INDEXED_DIMENSION = {
    "theta": ANGLE,
    "phi": ANGLE,
    "alpha": ANGLE,
    "tip": LENGTH,
    "curvature": CURVATURE,
    "torque": TORQUE,
    "voltage": VOLTAGE,
    "current": CURRENT,
}

#: The input channels' kinds: what drives joint i (`DCMotor.drive` for the last two).
INPUT_KINDS = ("torque", "voltage", "current")
_PLAIN = {"end_x": LENGTH, "end_y": LENGTH, "accel_x": ACCELERATION, "accel_y": ACCELERATION}

#: The channel patterns, for error messages.
CHANNEL_PATTERNS = (
    "theta{i}, phi{i}, alpha{i}, tip{i}, curvature{i}, end_x, end_y, accel_x, accel_y (outputs); "
    "torque{i}, voltage{i}, current{i} (inputs); <output>_ref, e.g. theta1_ref (a controller's reference)"
)


def known_units() -> str:
    """The accepted units, grouped by dimension, for error messages."""
    by_dim: dict[str, list[str]] = {}
    for unit, (dim, _) in UNITS.items():
        by_dim.setdefault(dim, []).append(f"[{unit}]")
    return "; ".join(f"{dim}: {' '.join(units)}" for dim, units in by_dim.items())


def normalise_unit(unit: str) -> str | None:
    """The canonical spelling of `unit` (a key of `UNITS`), or None if unknown."""
    u = " ".join(unit.split())
    if u in UNITS:
        return u
    return ALIASES.get(u, ALIASES.get(u.replace(" ", "")))


def unit_dimension(unit: str) -> str:
    return UNITS[unit][0]


def unit_factor(unit: str) -> float:
    return UNITS[unit][1]


_HEADER = re.compile(r"^(?P<name>[^\[\]]*?)\s*\[(?P<unit>[^\[\]]*)\]\s*$")


def split_header(text: str) -> tuple[str, str | None]:
    """`'tip1 [mm]'` -> `('tip1', 'mm')`; `'tip1'` -> `('tip1', None)`. Raises
    `ValueError` for unbalanced or repeated brackets (the unit is not normalised here)."""
    text = text.strip()
    if "[" not in text and "]" not in text:
        return text, None
    m = _HEADER.match(text)
    if m is None:
        raise ValueError(f"expected 'name [unit]', got {text!r}")
    return m["name"].strip(), m["unit"].strip()


#: A closed-loop log's reference of an output channel: `theta1_ref` (`identify.Controller`)
_REFERENCE = re.compile(r"^(?P<channel>.+)_ref$")


def referenced_channel(channel: str) -> str | None:
    """`'theta1_ref'` -> `'theta1'`: the output channel a reference channel is the
    reference of, or None if `channel` is not a reference."""
    m = _REFERENCE.match(channel)
    if m is None or _output_dimension(m["channel"]) is None or is_input(m["channel"]):
        return None
    return m["channel"]


def is_reference(channel: str) -> bool:
    return referenced_channel(channel) is not None


def reference_channel(channel: str) -> str:
    """`'theta1'` -> `'theta1_ref'`: the log channel holding an output's reference."""
    return channel + "_ref"


def channel_dimension(channel: str) -> str | None:
    """Dimension of a channel name (`'time'` included), or None if it is not a channel."""
    if channel == "time":
        return TIME
    base = referenced_channel(channel)
    return _output_dimension(channel if base is None else base)


def _output_dimension(channel: str) -> str | None:
    m = _INDEXED.match(channel)
    if m:
        return _INDEXED_DIMENSION[m[1]]
    return _PLAIN.get(channel)


def near_channel(name: str) -> str | None:
    """The channel a column name spells differently, ignoring case, spaces, `_` and `-`
    (`'Tip_1'` -> `'tip1'`, `'THETA 1'` -> `'theta1'`), or None (also for a channel name
    itself). `load_log` refuses a near miss such as `tip_1 [mm]` rather than drop it in
    silence as an unused column."""
    folded = re.sub(r"[\s_\-]", "", name).lower()
    for plain in (*_PLAIN, "time"):
        if folded == plain.replace("_", ""):
            folded = plain
    if folded == name or channel_dimension(folded) is None:
        return None
    return folded


def channel_kind_index(channel: str) -> tuple[str, int | None]:
    """`'tip2'` -> `('tip', 2)`, `'end_x'` -> `('end_x', None)`."""
    m = _INDEXED.match(channel)
    if m:
        return m[1], int(m[2])
    return channel, None


def is_input(channel: str) -> bool:
    """True for input channels (a joint's torque, or its motor's voltage or current)."""
    return channel_kind_index(channel)[0] in INPUT_KINDS


def is_output(channel: str) -> bool:
    """True for measured output channels (everything but `time`, the inputs and the
    references)."""
    return (
        channel != "time"
        and channel_dimension(channel) is not None
        and not (is_input(channel) or is_reference(channel))
    )


_QUANTITY = re.compile(r"^\s*(?P<value>[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?)\s*(?P<unit>\S.*?)?\s*$")


def parse_quantity(text: str, dimension: str) -> float:
    """`'0.5 deg'` -> 0.008726... (SI) for a quantity of the given dimension. Raises
    `ValueError` saying what was expected. A string must carry its unit: `'0.03'` is
    refused rather than read as SI in silence (meant as degrees, 0.03 rad would be 57 times
    the intended noise); a number in SI units is written as a number."""
    m = _QUANTITY.match(text)
    if m is None:
        raise ValueError(f"expected a number with a unit, e.g. '0.5 {_example_unit(dimension)}', got {text!r}")
    value = float(m["value"])
    if m["unit"] is None:
        raise ValueError(
            f"{text!r} has no unit; write it with one (e.g. '{m['value']} {_example_unit(dimension)}'), "
            f"or as a number without quotes in SI units ({SI_UNIT[dimension]})"
        )
    unit = normalise_unit(m["unit"])
    if unit is None:
        raise ValueError(f"unknown unit {m['unit']!r} in {text!r}; known units: {known_units()}")
    if unit_dimension(unit) == STRAIN and dimension == CURVATURE:
        raise ValueError(
            f"{text!r} is a strain; expected a curvature: the strain over the gauge's distance c from the "
            f"neutral axis (e.g. {m['value']} {m['unit']} with c = 1 mm is "
            f"'{value * unit_factor(unit) / 1e-3:.6g} 1/m')"
        )
    if unit_dimension(unit) != dimension:
        raise ValueError(
            f"{text!r} is {article(unit_dimension(unit))}; expected {article(dimension)} "
            f"(e.g. '{m['value']} {_example_unit(dimension)}')"
        )
    return value * unit_factor(unit)


def article(word: str) -> str:
    """`'angle'` -> `'an angle'`."""
    return f"{'an' if word[:1] in 'aeiou' else 'a'} {word}"


def _example_unit(dimension: str) -> str:
    return {ANGLE: "deg", LENGTH: "mm", TIME: "ms"}.get(dimension, SI_UNIT.get(dimension, ""))


def display_unit(channel: str) -> tuple[float, str]:
    """(scale, unit) to show an SI channel value in: degrees for angles, mm for lengths."""
    if channel.startswith(("theta", "phi", "alpha")):
        return 180.0 / np.pi, "deg"
    if channel.startswith(("tip", "end_")):
        return 1e3, "mm"
    if channel.startswith("curvature"):
        return 1.0, "1/m"
    if channel.startswith("accel_"):
        return 1.0, "m/s^2"
    if is_input(channel):  # (a closed-loop log's command: an output of the model too)
        return 1.0, SI_UNIT[channel_dimension(channel)]
    return 1.0, "SI"


def state_display_unit(entry: str) -> tuple[float, str]:
    """(scale, unit) to show a state entry in (`identify.channels.state_names`): angles
    (`theta1`, `alpha1`) in deg, modal coordinates (`q1_1`: m, RMS deflection of the mode)
    in mm, and their `_rate`s per second."""
    base, rate = (entry[: -len("_rate")], True) if entry.endswith("_rate") else (entry, False)
    scale, unit = (1e3, "mm") if base.startswith("q") else display_unit(base)
    return scale, f"{unit}/s" if rate else unit
