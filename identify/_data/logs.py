"""Measured logs: CSV and MATLAB `.mat` files, read into SI arrays with checks.

A log is a set of sampled channels (see `identify.units` for the vocabulary):
the sample times, measured outputs (`theta1`, `tip1`, ...) and applied inputs
(`torque1`, ...). `load_log` reads one file, converts every channel to SI and
checks it; anything wrong raises `LogError` naming the file, the line and column
(CSV) or the variable and sample (.mat), and what was expected. Nothing is ever
written. The file format is documented in `identify/FORMAT.md`.
"""

from __future__ import annotations

import csv
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

#: Sampling rates of a rig's logs (Hz): outside, a log's summary asks about the time
#: column's unit (the loader cannot tell; the numbers are valid either way).
PLAUSIBLE_RATE_HZ = (1.0, 1e5)
#: A sampling interval larger than this multiple of the median interval is a gap.
GAP_FACTOR = 1.5

CSV_SUFFIXES = (".csv", ".txt", ".tsv")
MAT_SUFFIXES = (".mat",)


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
    channel's dimension: a motor encoder in `[deg]` with `{ gear_ratio = 70 }`."""

    scale: float | None = None
    offset: float = 0.0
    unit: str | None = None
    neutral_axis_distance: float | None = None
    gear_ratio: float | None = None


@dataclasses.dataclass(frozen=True)
class Sampling:
    """Summary of a log's time stamps (s). Non-uniform sampling and gaps are allowed;
    a gap is an interval longer than `GAP_FACTOR` times the median interval."""

    n_samples: int
    duration: float
    median_dt: float
    min_dt: float
    max_dt: float
    largest_gap_at: float  # time (s, as in the file) where the longest interval starts
    n_gaps: int

    @property
    def rate(self) -> float:
        """Nominal sampling rate, Hz (1 / median interval)."""
        return 1.0 / self.median_dt

    @property
    def uniform(self) -> bool:
        return self.n_gaps == 0 and self.min_dt >= self.median_dt / GAP_FACTOR

    def __str__(self) -> str:
        text = (
            f"{self.n_samples} samples over {self.duration:.6g} s, median dt {self.median_dt:.6g} s "
            f"({self.rate:.6g} Hz), dt range [{self.min_dt:.6g}, {self.max_dt:.6g}] s"
        )
        if self.n_gaps:
            text += f", {self.n_gaps} gap(s), the largest {self.max_dt:.6g} s at t = {self.largest_gap_at:.6g} s"
        hint = self.time_unit_hint
        return f"{text} ({hint})" if hint else text

    @property
    def time_unit_hint(self) -> str:
        """A question about the time column's unit when the rate is outside what a rig's log
        has (`PLAUSIBLE_RATE_HZ`): seconds read as milliseconds give 1,000x the rate,
        milliseconds read as seconds 1/1,000 of it. Else ''."""
        lo, hi = PLAUSIBLE_RATE_HZ
        if self.rate > hi:
            return f"a rate above {hi:g} Hz: is the time column in seconds but labelled [ms] or [us]?"
        if self.rate < lo:
            return f"a rate below {lo:g} Hz: is the time column in milliseconds but labelled [s]?"
        return ""


@dataclasses.dataclass(frozen=True, eq=False)
class Log:
    """One loaded log, in SI units (arrays are float64 and read-only).

    - `name`: a label (the file's stem unless the experiment names it).
    - `path`: the file it was read from.
    - `t`: sample times, s, as in the file (absolute).
    - `t_relative`: sample times from the first sample, s, differenced before the unit
      conversion (exact for an absolute clock, where `t - t[0]` loses digits).
    - `outputs`: measured channels, e.g. `{'theta1': rad, 'tip1': m}`.
    - `inputs`: applied torques, e.g. `{'torque1': N m}`.
    - `sampling`: a `Sampling` summary.
    - `sources`: channel -> where it came from (`'enc [deg]'`), for messages.
    - `ignored`: columns or variables in the file that no channel uses.
    """

    name: str
    path: Path
    t: np.ndarray = dataclasses.field(repr=False)
    t_relative: np.ndarray = dataclasses.field(repr=False)
    outputs: dict[str, np.ndarray] = dataclasses.field(repr=False)
    inputs: dict[str, np.ndarray] = dataclasses.field(repr=False)
    sampling: Sampling
    sources: dict[str, str] = dataclasses.field(repr=False)
    ignored: tuple[str, ...] = ()

    @property
    def channels(self) -> list[str]:
        return [*self.outputs, *self.inputs]

    def __len__(self) -> int:
        return self.t.shape[0]

    def torque(self, n_joints: int) -> np.ndarray | None:
        """Applied torques, shape (T, n_joints), N m: column j-1 is `torque<j>`, 0 for a joint
        without one (unpowered). None if the log has no torque column at all."""
        if not self.inputs:
            return None
        out = np.zeros((len(self), n_joints))
        for c, values in self.inputs.items():
            j = int(c.removeprefix("torque"))
            if not 1 <= j <= n_joints:
                raise ValueError(
                    f"log {self.name!r} has {c}, the rig {n_joints} joint(s) "
                    f"(column {self.sources.get(c, c)!r} of {self.path})"
                )
            out[:, j - 1] = values
        return out

    def summary(self) -> str:
        lines = [f"log {self.name!r} ({self.path}): {self.sampling}"]
        for ch in self.channels:
            lines.append(f"  {ch:<12} <- {self.sources[ch]}")
        if self.ignored:
            lines.append(f"  ignored: {', '.join(self.ignored)}")
        return "\n".join(lines)


# ---------------------------------------------------------------------------
# The column mapping
# ---------------------------------------------------------------------------


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
    if dim_unit == u.VOLTAGE and dim != u.TIME:
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
    if cal is not None and (cal.scale is not None or cal.gear_ratio is None):
        raise LogError(
            f"{where}: a calibration scale is given for {w.channel} but its unit is [{written}], not [V]; "
            "remove the scale and offset (they apply to voltage columns only"
            + (
                "; a gear_ratio alone refers a motor-side column to the link side)" if _GEARED.match(w.channel) else ")"
            ),
            channel=w.channel,
        )
    return unit, cal


def _si(channel: str) -> str:
    return u.SI_UNIT[u.channel_dimension(channel)]


def _units_of(dim: str) -> str:
    return " ".join(f"[{k}]" for k, (d, _) in u.UNITS.items() if d == dim)


def _to_si(values: np.ndarray, unit: str, cal: Calibration | None, channel: str) -> np.ndarray:
    values = values * u.unit_factor(unit)
    if cal is not None:
        if cal.scale is not None:
            values = cal.scale * values + cal.offset
            if cal.unit is not None:
                values = values * u.unit_factor(u.normalise_unit(cal.unit))
        if cal.neutral_axis_distance is not None:  # strain -> curvature (`Calibration`)
            values = values / cal.neutral_axis_distance
        if cal.gear_ratio is not None:  # motor side -> link side (`Calibration`)
            values = values * cal.gear_ratio if channel.startswith("torque") else values / cal.gear_ratio
    return values


def _calibration_note(cal: Calibration | None) -> str:
    """How a column was converted, for `Log.sources`."""
    if cal is None:
        return ""
    parts = ["calibrated"] if cal.scale is not None or cal.neutral_axis_distance is not None else []
    if cal.gear_ratio is not None:
        parts.append(f"gear ratio {cal.gear_ratio:g}: motor side to link side")
    return f" ({', '.join(parts)})"


#: the channels a `Calibration.gear_ratio` applies to: joint, rotor angles and joint torques
_GEARED = re.compile(r"^(theta|alpha|torque)\d+$")


def check_calibration(channel: str, spec, where: str) -> Calibration:
    """A `Calibration` from an experiment-file table `{scale, offset, unit,
    neutral_axis_distance, gear_ratio}`."""
    if not isinstance(spec, Mapping):
        raise LogError(f"{where}: expected a table {{ scale = ..., offset = ... }}, got {spec!r}")
    keys = {"scale", "offset", "unit", "neutral_axis_distance", "gear_ratio"}
    extra = set(spec) - keys
    if extra:
        raise LogError(
            f"{where}: unknown key(s) {sorted(extra)}; expected scale, offset and optionally unit "
            "(voltage columns), neutral_axis_distance (strain gauges), or gear_ratio (motor-side angles "
            "and torques)"
        )
    dim = u.channel_dimension(channel)
    if dim is None or dim == u.TIME:
        raise LogError(f"{where}: calibrations apply to measured channels, not {channel!r}")
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
    if "scale" not in spec and distance is None and gear is None:
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
    )


# ---------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------


def load_log(
    path,
    columns: Mapping[str, str] | None = None,
    *,
    calibration: Mapping[str, Calibration | Mapping] | None = None,
    strict: bool = False,
    min_samples: int = MIN_SAMPLES,
    name: str | None = None,
    context: str = "columns",
) -> Log:
    """Read a CSV or MATLAB `.mat` log into SI units, with checks.

    **Arguments:**
    - `path`: the file (`.csv`, `.txt`, `.tsv`: text with a header row; `.mat`: MATLAB v5/v7).
    - `columns`: channel -> `'column [unit]'` (CSV header name or .mat variable, with its
      unit in brackets; for CSV the unit may be left out when the header has it). For CSV,
      None maps every column whose name is a channel (`time [s]`, `theta1 [deg]`, ...).
    - `calibration`: channel -> `Calibration` (or `{scale, offset, unit}`) for `[V]` columns;
      `{neutral_axis_distance}` for a strain gauge's, `{gear_ratio}` for a motor-side
      angle or torque (`Calibration`).
    - `strict`: if True, columns or variables that no channel uses are an error (default:
      they are ignored and listed in `Log.ignored`).
    - `min_samples`: fewest samples accepted.
    - `name`: label of the log (default: the file's stem).
    - `context`: how the mapping is named in messages (e.g. `'logs[2].columns'`).

    Raises `LogError` (a `ValueError`) naming the file, line and column (or variable and
    sample) and what was expected.
    """
    path = Path(path)
    cals = {}
    for ch, c in (calibration or {}).items():
        spec = {k: v for k, v in dataclasses.asdict(c).items() if v is not None} if isinstance(c, Calibration) else c
        cals[ch] = check_calibration(ch, spec, f"{path}: calibration.{ch}")
    if not path.is_file():
        what = "is a directory" if path.is_dir() else "does not exist"
        raise LogError(f"{path.resolve()}: log file {what}; expected a .csv or .mat file")
    suffix = path.suffix.lower()
    wanted = None if columns is None else _parse_mapping(path, columns, context)
    for ch in cals:
        if wanted is not None and ch not in {w.channel for w in wanted}:
            raise LogError(f"{path}: calibration.{ch}: no column is mapped to {ch}")
    if suffix in MAT_SUFFIXES:
        if wanted is None:
            raise LogError(
                f"{path}: a .mat log needs a column mapping (.mat variables carry no units); expected "
                'columns = { time = "t [s]", theta1 = "enc [deg]", ... } naming each variable and its unit'
            )
        t, t_relative, channels, sources, ignored = _read_mat(path, wanted, cals, strict, context)
    elif suffix in CSV_SUFFIXES:
        t, t_relative, channels, sources, ignored = _read_csv(path, wanted, cals, strict, context)
    else:
        raise LogError(f"{path}: unknown log type {path.suffix!r}; expected {', '.join(CSV_SUFFIXES + MAT_SUFFIXES)}")
    n = t.shape[0]
    if n < max(min_samples, 2):
        raise LogError(
            f"{path}: {n} samples; expected at least {min_samples} to fit a model (the experiment file's "
            "[experiment] min_samples, default 10)"
        )
    sampling = _sampling(t_relative, t[0])
    for arr in [t, t_relative, *channels.values()]:
        arr.flags.writeable = False
    return Log(
        name=path.stem if name is None else name,
        path=path,
        t=t,
        t_relative=t_relative,
        outputs={k: v for k, v in channels.items() if u.is_output(k)},
        inputs={k: v for k, v in channels.items() if u.is_input(k)},
        sampling=sampling,
        sources=sources,
        ignored=tuple(ignored),
    )


def _relative_time(raw: np.ndarray, unit: str) -> np.ndarray:
    """Times from the first sample (s), differenced in the file's unit before scaling: an
    absolute clock (ms since 1970, ~1.7e12) scaled to seconds first keeps only ~2e-7 s of
    resolution, which showed as a 500 Hz log's intervals varying by 1e-4 (review)."""
    return (raw - raw[0]) * u.unit_factor(unit)


def _sampling(t: np.ndarray, start: float) -> Sampling:
    """`t`: times from the first sample (s); `start`: the first sample's time in the file (s)."""
    dt = np.diff(t)
    median = float(np.median(dt))
    k = int(np.argmax(dt))
    return Sampling(
        n_samples=int(t.shape[0]),
        duration=float(t[-1] - t[0]),
        median_dt=median,
        min_dt=float(dt.min()),
        max_dt=float(dt[k]),
        largest_gap_at=float(start + t[k]),
        n_gaps=int(np.sum(dt > GAP_FACTOR * median)),
    )


def _check_samples(path, channel: str, values: np.ndarray, where: Callable[[int], str]):
    bad = ~np.isfinite(values)
    if bad.any():
        j = int(np.argmax(bad))
        raise LogError(f"{path}, {where(j)}: {values[j]} in {channel}; expected a finite number")


def _check_time(path, t: np.ndarray, where: Callable[[int], str], shown: np.ndarray):
    """Strictly increasing `t` (relative times, compared exactly); `shown`: the same times
    as in the file (s), for the message."""
    dt = np.diff(t)
    bad = dt <= 0
    if bad.any():
        j = int(np.argmax(bad)) + 1
        what = "duplicate time stamp" if dt[j - 1] == 0 else "time goes backwards"
        raise LogError(
            f"{path}, {where(j)}: {what} (t = {shown[j]:.9g} after t = {shown[j - 1]:.9g} at {where(j - 1)}); "
            "expected strictly increasing times"
        )


# -- CSV ---------------------------------------------------------------------


def _read_text(path: Path) -> str:
    data = path.read_bytes()
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):  # UTF-16 with its byte-order mark ("Unicode text" on Windows)
        try:
            return data.decode("utf-16")
        except UnicodeDecodeError as e:
            raise LogError(f"{path}: starts with a UTF-16 byte-order mark but is not valid UTF-16 ({e})") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return data.decode("cp1252", errors="replace")  # Windows DAQ software


#: Excel's separator line (`sep=;`), written before the header by some exports
_EXCEL_SEP = re.compile(r'^\s*"?sep=(?P<sep>.)"?\s*$', re.IGNORECASE)


def _is_number(cell: str) -> bool:
    try:
        float(cell.strip().replace(",", "."))
    except ValueError:
        return False
    return True


def _skip(line: str) -> bool:
    s = line.strip()
    return not s or s.startswith("#")


def _read_csv(path: Path, wanted, cals, strict, context):
    content = _read_text(path)
    lines = content.splitlines()
    header_at = next((i for i, line in enumerate(lines) if not _skip(line)), None)
    if header_at is None:
        raise LogError(f"{path}: no header row; expected a first row like 'time [s],theta1 [rad],tip1 [mm]'")
    sep = _EXCEL_SEP.match(lines[header_at])
    if sep is not None:  # Excel's "sep=;" line: the separator given, the header on the next row
        header_at = next((i for i in range(header_at + 1, len(lines)) if not _skip(lines[i])), None)
        if header_at is None:
            raise LogError(f"{path}: no header row after the separator line 'sep={sep['sep']}'")
    header_line = lines[header_at]
    if sep is not None:
        delimiter = sep["sep"]
    else:
        delimiter = ";" if ";" in header_line else "\t" if "\t" in header_line else ","
    decimal_comma = delimiter != ","

    def split(line: str) -> list[str]:
        return next(csv.reader([line], delimiter=delimiter))

    header = [h.strip() for h in split(header_line)]
    hline = header_at + 1
    if all(_is_number(h) for h in header):
        raise LogError(
            f"{path}, line {hline}: the first row is all numbers ({header_line.strip()[:60]!r}): the file seems "
            "to have no header row; add one naming each column with its unit, like 'time [s],theta1 [deg],tip1 [mm]'"
        )
    if len(header) == 1 and len(header_line.split()) > 1 and header_line.count("[") > 1:
        raise LogError(
            f"{path}, line {hline}: one column {header_line.strip()[:60]!r}, its cells separated by spaces; "
            "expected cells separated by commas, semicolons or tabs"
        )
    names, file_units = [], []
    for c, text in enumerate(header, start=1):
        try:
            name, unit = u.split_header(text)
        except ValueError as e:
            raise LogError(f"{path}, line {hline}, column {c}: {e}") from None
        names.append(name)
        file_units.append(unit)
    seen: dict[str, int] = {}
    for c, name in enumerate(names, start=1):
        if name and name in seen:
            raise LogError(f"{path}, line {hline}: columns {seen[name]} and {c} are both named {name!r}")
        seen[name] = c

    if wanted is None:  # identity mapping: columns named like channels
        wanted = [_Wanted(n, n, None) for n, unit in zip(names, file_units) if u.channel_dimension(n) is not None]
        for c, name in enumerate(names, start=1):
            near = u.near_channel(name)
            if near is not None and near not in names:
                raise LogError(
                    f"{path}, line {hline}, column {c}: {header[c - 1]!r} is not a channel name, but "
                    f"{near!r} is; rename the column '{near} [...]', or map the columns in the experiment "
                    f'file (columns = {{ {near} = "{header[c - 1]}", ... }})'
                )
        if not any(w.channel == "time" for w in wanted):
            raise LogError(
                f"{path}, line {hline}: no 'time' column among {names}; expected a column 'time [s]', "
                'or map the time column in the experiment file: columns = { time = "<header> [s]", ... }'
            )
    used = {}
    for w in wanted:
        if w.source not in seen:
            raise LogError(
                f"{path}, line {hline}: no column {w.source!r} (mapped by {context}.{w.channel}); "
                f"the header has {[n for n in names if n]}",
                channel=w.channel,
            )
        c = seen[w.source]
        where = f"{path}, line {hline}, column {c} ({header[c - 1]!r})"
        unit, cal = _resolve_unit(path, w, file_units[c - 1], where, cals)
        used[c] = (w, unit, cal)
    ignored = [header[c - 1] for c in range(1, len(names) + 1) if c not in used and names[c - 1]]
    if strict and ignored:
        raise LogError(
            f"{path}, line {hline}: column(s) {ignored} are not mapped to any channel (strict = true); "
            "map them in columns, or remove strict"
        )

    cells: dict[int, list[str]] = {c: [] for c in used}
    line_numbers = []
    for i in range(header_at + 1, len(lines)):
        if _skip(lines[i]):
            continue
        row = split(lines[i])
        if len(row) != len(header):
            cut = i == len(lines) - 1 and not content.endswith(("\n", "\r"))
            raise LogError(
                f"{path}, line {i + 1}: {len(row)} cells; expected {len(header)} like the header on line {hline}"
                + ("; the file ends in this row without a newline: it may have been cut off mid-write" if cut else "")
            )
        line_numbers.append(i + 1)
        for c in used:
            cells[c].append(row[c - 1])
    if not line_numbers:
        raise LogError(f"{path}: no data rows after the header on line {hline}; expected one row per sample")
    _warn_if_cut_off(path, content, lines, line_numbers)

    def where_for(c):
        return lambda j: f"line {line_numbers[j]}, column {c} ({header[c - 1]!r})"

    channels, sources = {}, {}
    for c, (w, unit, cal) in used.items():
        raw = _parse_floats(path, cells[c], decimal_comma, where_for(c))
        _check_samples(path, w.channel, raw, where_for(c))
        channels[w.channel] = _to_si(raw, unit, cal, w.channel)
        _warn_if_turns(path, f"column {c} ({header[c - 1]!r})", w.channel, channels[w.channel], unit)
        sources[w.channel] = f"column {c} {header[c - 1]!r}" + _calibration_note(cal)
        if w.channel == "time":
            t_relative = _relative_time(raw, unit)
    t = channels.pop("time")
    if t.shape[0] >= 2:
        _check_time(path, t_relative, where_for(seen[next(w.source for w in wanted if w.channel == "time")]), t)
    sources.pop("time")
    return t, t_relative, channels, sources, ignored


#: `load_log` warns of an angle channel read as radians that reaches this many turns
MANY_TURNS = 10


def _warn_if_turns(path, where: str, channel: str, si: np.ndarray, unit: str) -> None:
    """Warn when an angle channel whose column says radians reaches `MANY_TURNS` turns: most
    likely degrees labelled [rad] (found in review: 87-273 "rad" were loaded without a word,
    and the fit failed 2 minutes later with a warning pooled over all the logs). A link that
    really spins that far (the spinning-link example reaches 7 turns) can ignore it."""
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


def _warn_if_cut_off(path, text: str, lines: list[str], line_numbers: list[int]) -> None:
    """Warn when the file ends without a newline in a data row shorter than every other:
    the mark of a write interrupted mid-number (review: `1.9950,-51.` read as -51.0 deg,
    the sample written as -51.90, and nothing noticed it). A file that merely lacks the
    final newline has a last row as long as the others."""
    last = line_numbers[-1]
    if text.endswith(("\n", "\r")) or last != len(lines) or len(line_numbers) < 3:
        return
    others = min(len(lines[n - 1].strip()) for n in line_numbers[:-1])
    if len(lines[last - 1].strip()) < others:
        warnings.warn(
            f"{path}, line {last}: the file ends without a newline in a row shorter than every other "
            f"({lines[last - 1].strip()!r}): it may have been cut off mid-write; check that row, or delete it",
            UserWarning,
            stacklevel=2,
        )


def _parse_floats(path, texts: list[str], decimal_comma: bool, where) -> np.ndarray:
    out = np.empty(len(texts))
    for j, text in enumerate(texts):
        s = text.strip()
        if decimal_comma:
            s = s.replace(",", ".")
        try:
            out[j] = float(s)
        except ValueError:
            got = "an empty cell" if not s else repr(text)
            raise LogError(f"{path}, {where(j)}: expected a number, got {got}") from None
    return out


# -- MATLAB ------------------------------------------------------------------


def _load_mat_variables(path: Path) -> dict:
    import scipy.io

    try:
        return scipy.io.loadmat(path)
    except NotImplementedError:  # scipy's answer for v7.3 (HDF5) files
        try:
            import h5py
        except ImportError:
            raise LogError(
                f"{path}: a MATLAB v7.3 (HDF5) file, which needs h5py; re-save it in MATLAB with "
                "save('file.mat', ..., '-v7'), or install h5py"
            ) from None
        with h5py.File(path, "r") as f:  # MATLAB stores arrays transposed; vectors don't mind
            out = {}

            def visit(name, obj):  # a struct is a group, its fields datasets (or groups) in it
                if isinstance(obj, h5py.Dataset) and not name.startswith("#"):
                    out[name.replace("/", ".")] = np.asarray(obj).T

            f.visititems(visit)
            return out
    except Exception as e:  # scipy raises several types for a file that is not a .mat
        raise LogError(f"{path}: not a readable MATLAB .mat file ({type(e).__name__}: {e})") from None


def _with_fields(variables: dict) -> dict:
    """`variables` and, for each scalar (1 x 1) struct, its fields as `struct.field`
    (nested structs: `a.b.c`), read as variables are. A struct array (several elements)
    keeps only its own entry: which element a field is from would be a guess."""
    out = dict(variables)
    for name, value in variables.items():
        kind, fields = _mat_kind(value)
        if kind == "a struct" and value.size == 1:
            element = value.reshape(-1)[0]
            out.update(_with_fields({f"{name}.{field}": element[field] for field in fields}))
    return out


def _leaves(variables: dict) -> list[str]:
    """The names of `_with_fields(variables)` that are not structs themselves (scalar
    structs are read through their fields); sorted."""
    return sorted(k for k, v in variables.items() if not (_mat_kind(v)[0] == "a struct" and getattr(v, "size", 0) == 1))


def _mat_kind(value) -> tuple[str, list[str]]:
    """What a variable read by `scipy.io.loadmat` is, in MATLAB's words: `("numeric", [])`
    for a real numeric array, `("a struct", fields)`, `("a cell array", [])`, `("text
    (a char array)", [])`, `("complex numbers", [])`, or its type."""
    if not isinstance(value, np.ndarray):
        return type(value).__name__, []
    if value.dtype.names:
        return "a struct", list(value.dtype.names)
    return {
        "b": "numeric",
        "i": "numeric",
        "u": "numeric",
        "f": "numeric",
        "c": "complex numbers",
        "O": "a cell array",
        "U": "text (a char array)",
        "S": "text (a char array)",
    }.get(value.dtype.kind, f"dtype {value.dtype}"), []


def _read_mat(path: Path, wanted, cals, strict, context):
    data = _load_mat_variables(path)
    variables = _with_fields({k: v for k, v in data.items() if not k.startswith("__")})
    leaves = _leaves(variables)
    used = {}
    for w in wanted:
        if w.source not in variables:
            holder = next((k for k in leaves if k.rsplit(".", 1)[-1] == w.source and "." in k), None)
            head = next((k for k in variables if w.source.startswith(k + ".")), None)
            if holder is not None:  # (the struct's name left out)
                hint = f"; it is the field {holder!r} of a struct: map it as '{holder} [unit]'"
            elif head is not None and _mat_kind(variables[head])[0] == "a struct":
                hint = (
                    f"; {head!r} is a struct array of {variables[head].size} elements, whose fields are not read "
                    "(which element?): save the element you mean as a struct of its own, or its fields as variables"
                )
            else:
                hint = ""
            raise LogError(
                f"{path}: no variable {w.source!r} (mapped by {context}.{w.channel}); the file has {leaves}{hint}",
                channel=w.channel,
            )
        where = f"{path}: variable {w.source!r}"
        unit, cal = _resolve_unit(path, w, None, where, cals)
        value = variables[w.source]
        kind, fields = _mat_kind(value)
        if kind != "numeric":
            extra = f" with fields {fields}" if fields else ""
            if fields and value.size == 1:
                extra += f": map one of them, e.g. '{w.source}.{fields[0]} [unit]'"
            raise LogError(f"{where}: expected a real numeric vector, got {kind}{extra}")
        if sum(d > 1 for d in value.shape) > 1:
            raise LogError(f"{where}: shape {value.shape}; expected a vector (one channel per variable)")
        if w.channel == "time" and value.size < 2:
            raise LogError(
                f"{where} (time): holds {value.size} value(s); expected a vector of sample times, one per sample"
            )
        used[w] = (value.astype(np.float64).ravel(), unit, cal)
    ignored = sorted(set(leaves) - {w.source for w in wanted})
    if strict and ignored:
        raise LogError(f"{path}: variable(s) {ignored} are not mapped to any channel (strict = true)")
    time_w = next(w for w in wanted if w.channel == "time")
    n = used[time_w][0].shape[0]
    channels, sources = {}, {}
    for w, (raw, unit, cal) in used.items():
        if raw.shape[0] != n:
            raise LogError(
                f"{path}: variable {w.source!r} ({w.channel}) has {raw.shape[0]} samples; "
                f"expected {n} like the time variable {time_w.source!r}"
            )
        where = lambda j, s=w.source: f"variable {s!r}, sample {j + 1}"  # noqa: E731 (1-based, as in MATLAB)
        _check_samples(path, w.channel, raw, where)
        channels[w.channel] = _to_si(raw, unit, cal, w.channel)
        _warn_if_turns(path, f"variable {w.source!r}", w.channel, channels[w.channel], unit)
        sources[w.channel] = f"variable {w.source!r} [{w.unit}]" + _calibration_note(cal)
        if w.channel == "time":
            t_relative = _relative_time(raw, unit)
    t = channels.pop("time")
    sources.pop("time")
    _check_time(path, t_relative, lambda j: f"variable {time_w.source!r}, sample {j + 1}", t)
    return t, t_relative, channels, sources, ignored


__all__ = [
    "Calibration",
    "Log",
    "LogError",
    "MIN_SAMPLES",
    "Sampling",
    "load_log",
]


def write_log(log, path, *, units: Mapping[str, str] | None = None, comments=(), overwrite: bool = False) -> Path:
    """Write a log (`identify.LogData`, e.g. from `simulate_log`) as a CSV file that
    `load_log` and experiment files read back: a header `time [s], theta1 [deg], ...,
    torque1 [N m], ...` (outputs, then one torque column per joint), every value with 17
    significant digits (the same float64 read back).

    **Arguments:**
    - `units`: channel -> unit of its column (`{"theta1": "deg", "tip1": "mm"}`); the
      others in SI (`time` too: `{"time": "ms"}`).
    - `comments`: lines written first, each after `# ` (what made the log, its licence).
    - `overwrite`: replace an existing file (default: refuse, naming it).

    Returns the path written. Raises `ValueError` naming the channel for a unit of the
    wrong dimension, and `FileExistsError` for an existing file without `overwrite`."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: exists; not overwritten (pass overwrite=True to replace it)")
    t = np.asarray(log.t, float)
    columns = {"time": t, **{c: np.asarray(v, float) for c, v in log.outputs.items()}}
    if log.torque is not None:
        torque = np.asarray(log.torque, float).reshape(len(t), -1)
        columns.update({f"torque{j + 1}": torque[:, j] for j in range(torque.shape[1])})
    units = dict(units or {})
    unknown = set(units) - set(columns)
    if unknown:
        raise ValueError(f"write_log: units for {sorted(unknown)}, which the log does not have; it has {list(columns)}")
    header, scaled = [], []
    for c, values in columns.items():
        dim = u.channel_dimension(c)
        if dim is None:
            raise ValueError(f"write_log: {c!r} is not a channel name (expected e.g. theta1, tip1, torque1)")
        unit = units.get(c, u.SI_UNIT[dim])
        canonical = u.normalise_unit(unit)
        if canonical is None or u.unit_dimension(canonical) != dim:
            raise ValueError(
                f"write_log: units[{c!r}] = {unit!r}: expected {u.article(dim)} unit, e.g. {u._example_unit(dim)!r}"
            )
        header.append(f"{c} [{canonical}]")
        scaled.append(values / u.unit_factor(canonical))
    lines = [f"# {line}" for line in comments] + [",".join(header)]
    lines += [",".join(f"{v:.17g}" for v in row) for row in zip(*scaled)]
    path.write_text("\n".join(lines) + "\n")
    return path
