"""Measured logs: CSV, MATLAB `.mat` files and ROS bags, read into SI arrays with checks.

A log is a set of sampled channels (see `identify.units` for the vocabulary):
the sample times, measured outputs (`theta1`, `tip1`, ...) and applied inputs
(`torque1`, ...). `load_log` reads one file, converts every channel to SI and
checks it; anything wrong raises `LogError` naming the file, the line and column
(CSV), the variable and sample (.mat) or the topic, field and message (bag), and what
was expected. Nothing is ever written. The file format is documented in `docs/experiment-format.md`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from . import units as u
from .bag_columns import BagTiming, parse_bag_mapping
from .bag_log import BAG_SUFFIXES, _read_bag, is_bag
from .columns import GAP_FACTOR, MIN_SAMPLES, Calibration, LogError, _parse_mapping, check_calibration
from .csv_log import _read_csv
from .files import absolute, input_problem
from .mat_log import _read_mat

#: Sampling rates of a rig's logs (Hz): outside, a log's summary asks about the time
#: column's unit (the loader cannot tell; the numbers are valid either way).
PLAUSIBLE_RATE_HZ = (1.0, 1e5)


CSV_SUFFIXES = (".csv", ".txt", ".tsv")


MAT_SUFFIXES = (".mat",)


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
    - `references`: a closed-loop log's reference columns, by the output channel they are
      the reference of (`{'theta1': rad}` from a `theta1_ref` column; `identify.Controller`).
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
    references: dict[str, np.ndarray] = dataclasses.field(default_factory=dict, repr=False)

    @property
    def channels(self) -> list[str]:
        return [*self.outputs, *self.inputs, *(u.reference_channel(c) for c in self.references)]

    def __len__(self) -> int:
        return self.t.shape[0]

    def torque(self, n_joints: int) -> np.ndarray | None:
        """The joints' inputs, shape (T, n_joints), SI: column j-1 is `torque<j>` (N m), or
        the motor's `voltage<j>` (V) or `current<j>` (A); 0 for a joint without one
        (unpowered). None if the log has no input column at all."""
        if not self.inputs:
            return None
        out = np.zeros((len(self), n_joints))
        seen = {}
        for c, values in self.inputs.items():
            j = u.channel_kind_index(c)[1]
            if j in seen:
                raise ValueError(
                    f"log {self.name!r} has both {seen[j]} and {c} for joint {j}; a joint has one input "
                    f"(columns {self.sources.get(seen[j], seen[j])!r} and {self.sources.get(c, c)!r} of {self.path})"
                )
            seen[j] = c
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


def load_log(
    path,
    columns: Mapping[str, str | Mapping] | None = None,
    *,
    calibration: Mapping[str, Calibration | Mapping] | None = None,
    strict: bool = False,
    min_samples: int = MIN_SAMPLES,
    name: str | None = None,
    context: str = "columns",
    decimal: str = ".",
    stamp: str | None = None,
    time_base: str | None = None,
    rate_hz: float | None = None,
) -> Log:
    """Read a CSV, MATLAB `.mat` or ROS bag log into SI units, with checks.

    **Arguments:**
    - `path`: the file (`.csv`, `.txt`, `.tsv`: text with a header row; `.mat`: MATLAB v5/v7;
      a ROS 2 bag folder, `.db3` or `.mcap` file, or a ROS 1 `.bag`).
    - `columns`: channel -> `'column [unit]'` (CSV header name or .mat variable, with its
      unit in brackets; for CSV the unit may be left out when the header has it). For CSV,
      None maps every column whose name is a channel (`time [s]`, `theta1 [deg]`, ...).
      For a bag, channel -> `{topic, field, unit}` (`field` a path such as `data` or
      `wrench.force.z`), with `joint` for a `sensor_msgs/msg/JointState`, and no `time`.
    - `calibration`: channel -> `Calibration` (or `{scale, offset, unit}`) for `[V]` columns;
      `{neutral_axis_distance}` for a strain gauge's, `{gear_ratio}` for a motor-side
      angle or torque, `{sign = -1}` for a reversed column of any unit (`Calibration`).
    - `strict`: if True, columns, variables or topics that no channel uses are an error
      (default: they are ignored and listed in `Log.ignored`).
    - `min_samples`: fewest samples accepted.
    - `name`: label of the log (default: the file's stem).
    - `context`: how the mapping is named in messages (e.g. `'logs[2].columns'`).
    - `decimal`: a CSV log's decimal mark, `"."` or `","` (cells then separated by
      semicolons or tabs). A comma is never taken for a decimal mark by guess: `1,234`
      may be 1.234 or 1234.
    - `stamp`, `time_base`, `rate_hz` (bags only): each message's time is its header stamp
      (`'header'`) or when the bag recorded it (`'receive'`; default: the header where the
      message has one); topics are linearly interpolated onto the stamps of topic
      `time_base` or a uniform `rate_hz` (Hz), inside the span all of them cover (needed when
      the channels come from more than one topic).

    Raises `LogError` (a `ValueError`) naming the file, line and column (or variable and
    sample, or topic, field and message) and what was expected.
    """
    path = Path(path)
    cals = {}
    for ch, c in (calibration or {}).items():
        spec = (
            {k: v for k, v in dataclasses.asdict(c).items() if v is not None and (k, v) != ("sign", 1.0)}
            if isinstance(c, Calibration)
            else c
        )
        cals[ch] = check_calibration(ch, spec, f"{path}: calibration.{ch}")
    bag = is_bag(path)
    problem = input_problem(path, bag)
    if problem is not None:
        raise LogError(f"{absolute(path)}: log file {problem}; expected a .csv or .mat file or a ROS bag")
    suffix = path.suffix.lower()
    timing = BagTiming(stamp, time_base, rate_hz)
    if not bag and timing != BagTiming():
        raise LogError(f"{path}: stamp, time_base and rate_hz apply to ROS bags only, not to a {suffix} file")
    if bag:
        wanted = parse_bag_mapping(path, columns, context)
    else:
        wanted = None if columns is None else _parse_mapping(path, columns, context)
    for ch in cals:
        if wanted is not None and ch not in {w.channel for w in wanted}:
            raise LogError(f"{path}: calibration.{ch}: no column is mapped to {ch}")
    if bag:
        t, t_relative, channels, sources, ignored = _read_bag(path, wanted, cals, strict, context, timing)
    elif suffix in MAT_SUFFIXES:
        if wanted is None:
            raise LogError(
                f"{path}: a .mat log needs a column mapping (.mat variables carry no units); expected "
                'columns = { time = "t [s]", theta1 = "enc [deg]", ... } naming each variable and its unit'
            )
        if decimal != ".":
            raise LogError(f"{path}: decimal = {decimal!r} applies to CSV logs; a .mat file holds binary numbers")
        t, t_relative, channels, sources, ignored = _read_mat(path, wanted, cals, strict, context)
    elif suffix in CSV_SUFFIXES:
        t, t_relative, channels, sources, ignored = _read_csv(path, wanted, cals, strict, context, decimal)
    else:
        known = ", ".join(CSV_SUFFIXES + MAT_SUFFIXES + BAG_SUFFIXES)
        raise LogError(f"{path}: unknown log type {path.suffix!r}; expected {known} or a ROS 2 bag folder")
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
        references={u.referenced_channel(k): v for k, v in channels.items() if u.is_reference(k)},
    )


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
