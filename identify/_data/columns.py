"""What every log reader shares: the column mapping (`"channel [unit]"`), units and calibrations
to SI, and the checks of time columns and samples (`LogError` names the file, line and column).
"""

from __future__ import annotations

import dataclasses
import math
import re
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from . import units as u

#: Fewest samples a log may have (a fit needs more data points than free parameters).
MIN_SAMPLES = 10


#: A sampling interval larger than this multiple of the median interval is a gap.
GAP_FACTOR = 1.5


#: A gap longer than both of these is an error (`_check_gaps`): this multiple of the median
#: interval, and this many seconds.
LONG_GAP_FACTOR = 1000
LONG_GAP_S = 1.0


class LogError(ValueError):
    """A log file (or its description in an experiment file) is not usable. The message
    names the file, the line and column or variable, and what was expected.

    `channel` is the channel whose entry in the column mapping the problem concerns (a
    unit or column name that disagrees with the file), or None: an experiment file then
    points at that entry's line rather than the log's."""

    def __init__(self, message: str, *, channel: str | None = None):
        super().__init__(message)
        self.channel = channel


@dataclasses.dataclass(frozen=True)
class Calibration:
    """Conversion of a voltage channel: `value = scale * volts + offset`, in `unit`
    (default: the channel's SI unit), then converted to SI.

    A strain gauge's channel (`curvature<i>`) in a strain unit (`[ue]`), or in volts with a
    `scale` to a strain `unit`, is converted to the root curvature the model predicts by
    `neutral_axis_distance` `c` (m; half the thickness for a gauge bonded on the surface of
    a symmetric strip): Euler-Bernoulli bending strain is `epsilon = c * kappa`, so
    `kappa = epsilon / c`. A strain column needs no `scale`.

    `gear_ratio` `G` (motor turns per link turn; negative for a gear that reverses the
    direction) refers a motor-side column to the link side, where the model's
    `theta<i>`, `alpha<i>` and `torque<i>` are (`fd.ElasticJoint`): an angle is divided by
    `G`, a torque multiplied by `G` (gear losses aside). It applies last, after any volt
    `scale` and `offset` (which are then motor-side), and to a column in any unit of the
    channel's dimension: a motor encoder in `[deg]` with `{ gear_ratio = 70 }`.

    `sign` (`1` or `-1`) multiplies the channel's value last, after every conversion above,
    on a column in any unit: a sensor wired or mounted against flexdyn's counter-clockwise
    positive convention (a strain gauge bridge with its arms swapped) is read without a
    negated copy of the log."""

    scale: float | None = None
    offset: float = 0.0
    unit: str | None = None
    neutral_axis_distance: float | None = None
    gear_ratio: float | None = None
    sign: float = 1.0


@dataclasses.dataclass(frozen=True)
class _Wanted:
    channel: str
    source: str  # column header name or .mat variable
    unit: str | None  # as written in the mapping (not normalised), or None


def _parse_mapping(path: Path, columns: Mapping[str, str], where: str) -> list[_Wanted]:
    wanted = []
    for channel, spec in columns.items():
        key = f"{where}.{channel}"
        if u.channel_dimension(channel) is None:
            raise LogError(
                f"{path}: {key}: {channel!r} is not a channel; expected 'time' or one of {u.CHANNEL_PATTERNS}"
            )
        if not isinstance(spec, str):
            raise LogError(f"{path}: {key}: expected a string 'column [unit]', got {spec!r}")
        try:
            source, unit = u.split_header(spec)
        except ValueError as e:
            raise LogError(f"{path}: {key}: {e}") from None
        if not source:
            raise LogError(f"{path}: {key}: expected 'column [unit]' naming a column, got {spec!r}")
        wanted.append(_Wanted(channel, source, unit))
    if not any(w.channel == "time" for w in wanted):
        raise LogError(f"{path}: {where}: no 'time' entry; expected e.g. time = \"time [s]\" naming the time column")
    sources = {}
    for w in wanted:
        if w.source in sources:
            raise LogError(
                f"{path}: {where}: channels {sources[w.source]!r} and {w.channel!r} both read column {w.source!r}"
            )
        sources[w.source] = w.channel
    return wanted


def _resolve_unit(path, w: _Wanted, file_unit: str | None, where: str, calibration) -> tuple[str, Calibration | None]:
    """The canonical unit of a wanted channel, checked against the channel's dimension."""
    written = w.unit if w.unit is not None else file_unit
    if w.unit is not None and u.normalise_unit(w.unit) is None:
        raise LogError(
            f"{where}: the experiment maps {w.channel} = '{w.source} [{w.unit}]': unknown unit [{w.unit}]; "
            f"known units: {u.known_units()}",
            channel=w.channel,
        )
    if w.unit is not None and file_unit is not None:
        a, b = u.normalise_unit(w.unit), u.normalise_unit(file_unit)
        if (a or w.unit) != (b or file_unit):
            raise LogError(
                f"{where}: the file's header says [{file_unit}] but the experiment maps {w.channel} = "
                f"'{w.source} [{w.unit}]'; make them agree",
                channel=w.channel,
            )
    if written is None:
        paren = re.match(r"^(?P<name>.*?)\s*\((?P<unit>[^()]+)\)\s*$", w.source)
        if paren and u.normalise_unit(paren["unit"]) is not None:
            example = f"'{paren['name']} [{paren['unit']}]', not '{w.source}'"
        else:
            example = f"e.g. '{w.source} [{_si(w.channel)}]'"
        raise LogError(f"{where}: no unit; expected the unit in square brackets, {example}", channel=w.channel)
    unit = u.normalise_unit(written)
    if unit is None:
        raise LogError(f"{where}: unknown unit [{written}]; known units: {u.known_units()}", channel=w.channel)
    dim, dim_unit = u.channel_dimension(w.channel), u.unit_dimension(unit)
    cal = (calibration or {}).get(w.channel)
    if dim_unit == u.VOLTAGE and dim not in (u.TIME, u.VOLTAGE):  # (a motor's voltage is in SI already)
        if cal is None or cal.scale is None:
            raise LogError(
                f"{where}: {w.channel} is in [{written}] and needs a calibration "
                f"(SI = scale * V + offset): add calibration = {{ {w.channel} = {{ scale = ..., offset = ... }} }} "
                "to this log in the experiment file",
                channel=w.channel,
            )
        return unit, cal
    if dim_unit == u.STRAIN and dim == u.CURVATURE:
        if cal is None or cal.neutral_axis_distance is None:
            raise LogError(
                f"{where}: {w.channel} is a curvature (1/m) and [{written}] a strain: the root curvature is the "
                "strain over the gauge's distance from the beam's neutral axis; add calibration = "
                f'{{ {w.channel} = {{ neutral_axis_distance = "1 mm" }} }} to this log in the experiment file '
                "(half the thickness for a gauge on the surface of a symmetric strip)",
                channel=w.channel,
            )
        if cal.scale is not None:
            raise LogError(
                f"{where}: a calibration scale is given for {w.channel}, whose column is a strain [{written}], "
                "not [V]; remove scale and offset (a strain column needs only neutral_axis_distance)",
                channel=w.channel,
            )
        return unit, cal
    if dim_unit != dim:
        extra = "" if dim == u.TIME else " or [V] with a calibration"
        if dim == u.CURVATURE:
            extra += ", or a strain ([ue], [strain]) with the gauge's neutral_axis_distance in its calibration"
        raise LogError(
            f"{where}: {w.channel} is {u.article(dim)} but [{written}] is {u.article(dim_unit)} "
            f"unit; expected one of {_units_of(dim)}" + extra,
            channel=w.channel,
        )
    if cal is not None and cal.neutral_axis_distance is not None:
        raise LogError(
            f"{where}: a neutral_axis_distance is given for {w.channel} but its unit is [{written}], not a strain "
            "([ue], [strain]); remove it (it turns a strain gauge's strain into the curvature)",
            channel=w.channel,
        )
    if cal is not None and cal.scale is not None:
        raise LogError(
            f"{where}: a calibration scale is given for {w.channel} but its unit is [{written}], not [V]; "
            "remove the scale and offset (they apply to voltage columns only"
            + ("; a gear_ratio alone refers a motor-side column to the link side" if _GEARED.match(w.channel) else "")
            + "; sign = -1 alone reverses the column)",
            channel=w.channel,
        )
    return unit, cal


def _si(channel: str) -> str:
    return u.SI_UNIT[u.channel_dimension(channel)]


def _units_of(dim: str) -> str:
    return " ".join(f"[{k}]" for k, (d, _) in u.UNITS.items() if d == dim)


def _to_si(
    values: np.ndarray, unit: str, cal: Calibration | None, channel: str, *, out: np.ndarray | None = None
) -> np.ndarray:
    """`values` in `unit` (volts or a strain with `cal`) converted to the channel's SI unit,
    into `out` (`values` itself converts in place: a large log keeps one copy)."""
    si = np.multiply(values, u.unit_factor(unit), out=out)
    if cal is not None:
        if cal.scale is not None:
            si *= cal.scale
            si += cal.offset
            if cal.unit is not None:
                si *= u.unit_factor(u.normalise_unit(cal.unit))
        if cal.neutral_axis_distance is not None:  # strain -> curvature (`Calibration`)
            si /= cal.neutral_axis_distance
        if cal.gear_ratio is not None:  # motor side -> link side (`Calibration`)
            if channel.startswith("torque"):
                si *= cal.gear_ratio
            else:
                si /= cal.gear_ratio
        if cal.sign != 1.0:  # last: the channel's value reversed (`Calibration`)
            np.negative(si, out=si)
    return si


def _calibration_note(cal: Calibration | None) -> str:
    """How a column was converted, for `Log.sources`."""
    if cal is None:
        return ""
    parts = ["calibrated"] if cal.scale is not None or cal.neutral_axis_distance is not None else []
    if cal.gear_ratio is not None:
        parts.append(f"gear ratio {cal.gear_ratio:g}: motor side to link side")
    if cal.sign != 1.0:
        parts.append("sign reversed")
    return f" ({', '.join(parts)})" if parts else ""


#: the channels a `Calibration.gear_ratio` applies to: joint, rotor angles and joint torques
_GEARED = re.compile(r"^(theta|alpha|torque)\d+$")


def check_calibration(channel: str, spec, where: str) -> Calibration:
    """A `Calibration` from an experiment-file table `{scale, offset, unit,
    neutral_axis_distance, gear_ratio, sign}`."""
    if not isinstance(spec, Mapping):
        raise LogError(f"{where}: expected a table {{ scale = ..., offset = ... }}, got {spec!r}")
    keys = {"scale", "offset", "unit", "neutral_axis_distance", "gear_ratio", "sign"}
    extra = set(spec) - keys
    if extra:
        raise LogError(
            f"{where}: unknown key(s) {sorted(extra)}; expected scale, offset and optionally unit "
            "(voltage columns), neutral_axis_distance (strain gauges), gear_ratio (motor-side angles "
            "and torques), or sign = -1 (a reversed column)"
        )
    dim = u.channel_dimension(channel)
    if dim is None or dim == u.TIME:
        raise LogError(f"{where}: calibrations apply to measured channels, not {channel!r}")
    sign = spec.get("sign", 1)
    if isinstance(sign, bool) or sign not in (1, -1):
        raise LogError(f"{where}.sign: expected -1 (the column's values reversed) or 1 (as recorded), got {sign!r}")
    gear = spec.get("gear_ratio")
    if gear is not None:
        if not _GEARED.match(channel):
            raise LogError(
                f"{where}.gear_ratio: applies to a joint's theta<i>, alpha<i> or torque<i> read on the motor side "
                f"of its gear, not {channel}"
            )
        if isinstance(gear, bool) or not isinstance(gear, int | float) or not math.isfinite(gear) or gear == 0:
            raise LogError(
                f"{where}.gear_ratio: expected a non-zero number (motor turns per link turn; negative for a gear "
                f"that reverses the direction), got {gear!r}"
            )
    distance = spec.get("neutral_axis_distance")
    if distance is not None:
        if dim != u.CURVATURE:
            raise LogError(
                f"{where}.neutral_axis_distance: applies to a strain gauge's curvature<i> channel, not {channel} "
                f"({u.article(dim)})"
            )
        try:
            distance = u.parse_quantity(distance, u.LENGTH) if isinstance(distance, str) else distance
        except ValueError as e:
            raise LogError(f"{where}.neutral_axis_distance: {e}") from None
        if isinstance(distance, bool) or not isinstance(distance, int | float) or not 0 < distance < math.inf:
            raise LogError(f"{where}.neutral_axis_distance: expected a distance > 0 (m, or '1 mm'), got {distance!r}")
    if "scale" not in spec and distance is None and gear is None and "sign" not in spec:
        raise LogError(f"{where}: missing 'scale' (SI = scale * V + offset)")
    if "scale" not in spec and spec.get("unit") is not None:
        raise LogError(f"{where}.unit: the unit of a volt scale's result, but no scale is given")
    if "scale" not in spec and spec.get("offset", 0.0) != 0.0:
        raise LogError(
            f"{where}: an offset without a scale; offset applies to voltage columns (SI = scale * V + offset)"
        )
    for key in ("scale", "offset"):
        v = spec.get(key, 0.0)
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise LogError(f"{where}.{key}: expected a finite number, got {v!r}")
    if spec.get("scale") == 0:
        raise LogError(f"{where}.scale: expected a non-zero number, got 0")
    unit = spec.get("unit")
    if unit is not None:
        if not isinstance(unit, str) or u.normalise_unit(unit) is None:
            raise LogError(f"{where}.unit: unknown unit {unit!r}; known units: {u.known_units()}")
        want = u.STRAIN if distance is not None else dim
        if u.unit_dimension(u.normalise_unit(unit)) != want:
            raise LogError(
                f"{where}.unit: [{unit}] is not {u.article(want)} unit; expected one of {_units_of(want)}"
                + (" (with neutral_axis_distance, the scale gives a strain)" if distance is not None else "")
            )
    scale = float(spec["scale"]) if "scale" in spec else None
    return Calibration(
        scale,
        float(spec.get("offset", 0.0)),
        unit,
        None if distance is None else float(distance),
        None if gear is None else float(gear),
        float(sign),
    )


def _relative_time(raw: np.ndarray, unit: str) -> np.ndarray:
    """Times from the first sample (s), differenced in the file's unit before scaling: an
    absolute clock (ms since 1970, ~1.7e12) scaled to seconds first keeps only ~2e-7 s of
    resolution, enough to make a 500 Hz log's intervals vary by 1e-4."""
    return (raw - raw[0]) * u.unit_factor(unit)


def _check_samples(path, channel: str, values: np.ndarray, where: Callable[[int], str]):
    bad = ~np.isfinite(values)
    if bad.any():
        j = int(np.argmax(bad))
        raise LogError(f"{path}, {where(j)}: {values[j]} in {channel}; expected a finite number")


def _check_time(path, t: np.ndarray, where: Callable[[int], str], shown: np.ndarray):
    """Strictly increasing `t` (relative times, compared exactly) without a long gap
    (`_check_gaps`); `shown`: the same times as in the file (s), for the message."""
    dt = np.diff(t)
    bad = dt <= 0
    if bad.any():
        j = int(np.argmax(bad)) + 1
        what = "duplicate time stamp" if dt[j - 1] == 0 else "time goes backwards"
        raise LogError(
            f"{path}, {where(j)}: {what} (t = {shown[j]:.9g} after t = {shown[j - 1]:.9g} at {where(j - 1)}); "
            "expected strictly increasing times"
        )
    _check_gaps(path, t, where, shown)


def _check_gaps(path, t: np.ndarray, where: Callable[[int], str], shown: np.ndarray):
    """No interval of the (increasing) relative times `t` (s) longer than `LONG_GAP_FACTOR`
    median intervals and `LONG_GAP_S` seconds. The fit integrates the model from sample to
    sample, across a gap too, as if it had been measured: a gap of a few dropped samples
    costs nothing, but one of 1000 intervals (5 s at 200 Hz; an hour between two runs saved
    in one file) is an unmeasured stretch the model must bridge with an unknown input. Two
    runs are two logs. The seconds keep a fast log's (10 kHz) short hiccup acceptable."""
    if t.shape[0] < 2:
        return
    dt = np.diff(t)
    median = float(np.median(dt))
    long = (dt > LONG_GAP_FACTOR * median) & (dt > LONG_GAP_S)
    if long.any():
        j = int(np.argmax(long)) + 1
        raise LogError(
            f"{path}, {where(j)}: a gap of {dt[j - 1]:.6g} s in the time stamps (t = {shown[j - 1]:.9g} s at "
            f"{where(j - 1)}, then t = {shown[j]:.9g} s), {dt[j - 1] / median:.3g} times the median interval "
            f"{median:.6g} s: the fit would integrate the model across it as if it had been measured. Split the log "
            f"into two logs at this sample (a [[logs]] entry each); shorter gaps (up to {LONG_GAP_FACTOR} median "
            f"intervals, or up to {LONG_GAP_S:g} s) are read"
        )


#: `load_log` warns of an angle channel read as radians that reaches this many turns
MANY_TURNS = 10


def _warn_if_turns(path, where: str, channel: str, si: np.ndarray, unit: str) -> None:
    """Warn when an angle channel whose column says radians reaches `MANY_TURNS` turns: most
    likely degrees labelled [rad], which the fit would otherwise only reveal later, in a
    warning pooled over all the logs. A link that really spins that far (the spinning-link
    example reaches 7 turns) can ignore it."""
    if u.channel_dimension(channel) != u.ANGLE or unit not in ("rad", "mrad"):
        return
    peak = float(np.max(np.abs(si))) if si.size else 0.0
    if peak > MANY_TURNS * 2 * np.pi:
        warnings.warn(
            f"{path}, {where}: {channel} reaches {peak:.4g} rad ({peak / (2 * np.pi):.3g} turns); if the column "
            f"is in degrees, label it [deg] (or map it as '... [deg]'); a link that spins this far can ignore this",
            UserWarning,
            stacklevel=4,
        )
