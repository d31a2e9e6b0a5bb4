"""Experiment files: a TOML description of a rig, its logs and what to fit.

`load_experiment(path)` reads the file (never writes anything), builds the rig as
a `flexdyn.Chain`, loads and checks every log (`identify.logs`) and returns an
`Experiment`. Every mistake raises `ExperimentError` (or `LogError` for a
problem inside a log file), both `ValueError`s, whose message names the file,
the line when it can be found, the key path (`logs[2].columns.tip1`) and what
was expected. The format is documented, with a full example, in
`docs/experiment-format.md`.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

import flexdyn as fd

from . import measurement as meas, units as u
from .channels import channel_unit
from .columns import Calibration
from .controller import Controller
from .logs import Log

ROLES = ("fit", "validation")


@dataclasses.dataclass(frozen=True)
class FreeParameter:
    """A parameter to fit: its name (`flexdyn.parameter_names`), initial guess and bounds
    (SI; None for unbounded), SI unit, and whether it is fitted in log space (parameters
    that cannot be negative); `per_log`: each fit log gets its own value
    (`identify.Parameter.per_log`), the other free parameters are shared."""

    name: str
    guess: float
    lower: float | None
    upper: float | None
    unit: str
    log_scale: bool
    per_log: bool = False


@dataclasses.dataclass(frozen=True, eq=False)
class LogSpec:
    """One `[[logs]]` entry and its loaded `Log`.

    - `file`: the log's path, resolved against the experiment file's folder.
    - `role`: `'fit'` or `'validation'` (held out of the fit).
    - `columns`: channel -> `'column [unit]'` as written (empty if the CSV header was used);
      for a ROS bag, channel -> `{topic, field, joint, unit}`.
    - `calibration`: channel -> `Calibration` for voltage, strain-gauge and motor-side columns.
    - `initial`: known initial-state entries, coordinate or `<coordinate>_rate` -> SI value
      (entries not listed are 0, except rotor angles/rates of elastic joints, which default
      to the link's: see docs/experiment-format.md). Also the starting guess of entries in `fit_initial`.
    - `fit_initial`: initial-state entries to estimate for this log.
    - `offsets`: output channels whose constant sensor offset is estimated for this log.
    - `log`: the loaded data (SI).
    - `measured`: the entries of `initial` given as `"measured"` (the log's first sample).
    - `set`: this log's known parameter values that differ from the rig's (SI; a payload
      sweep: `{"payload.mass": 0.02}`), `identify.LogData.set`.
    - `hold`: how its torque is read between samples (`identify.LogData.hold`).
    """

    name: str
    file: Path
    role: str
    columns: dict[str, str | dict]
    calibration: dict[str, Calibration]
    initial: dict[str, float]
    fit_initial: tuple[str, ...]
    offsets: tuple[str, ...]
    log: Log
    measured: tuple[str, ...] = ()
    set: dict[str, float] = dataclasses.field(default_factory=dict)
    hold: str | tuple[str, ...] = "linear"
    # whether the experiment file says `hold` for this log (else the default, linear)
    hold_declared: bool = False

    @property
    def outputs(self) -> dict[str, np.ndarray]:
        return self.log.outputs

    def warnings(self) -> list[str]:
        """What in this entry may bias a fit beyond its intervals: an initial entry taken
        from the log's first sample (`"measured"`) and not estimated holds that sample,
        noise included, as exact, which nothing else in the fit reports (0.08 deg of noise
        on that sample can put the intervals of EI, the damping and the payload 10 or more
        standard errors off the truth)."""
        out = []
        held = [s for s in self.measured if s not in self.fit_initial]
        if held:
            names = ", ".join(held)
            out.append(
                f'log {self.name!r}: {names} = "measured" holds the first sample, noise included, as the exact '
                f"initial value, which biases the fit beyond its intervals; add {names} to fit_initial to estimate "
                "it from the whole log (the first sample is its starting guess)"
            )
        # a torque column left out of `columns` leaves its joint unpowered: say so, rather
        # than only listing the column as unused
        for header in self.log.ignored:
            if _looks_like_torque(header):
                mapped = ", ".join(sorted(self.log.inputs)) or "none"
                out.append(
                    f"log {self.name!r}: the unused column {header!r} looks like a torque, but a joint without a "
                    f"torque column is unpowered in the model (torque columns mapped: {mapped}); map it in columns "
                    f"(e.g. torque2 = {header!r}) if it drives a joint"
                )
        if not self.hold_declared:
            out.extend(_held_looking(self.name, self.log.inputs))
        return out

    def torque(self, n_joints: int) -> np.ndarray | None:
        """Applied torques, shape (T, n_joints), N m (`Log.torque`)."""
        return self.log.torque(n_joints)


#: A torque column whose consecutive samples are equal at least this often is a staircase
#: (`_held_looking`); a sampled continuous signal, even a quantised one, changes far more
HELD_FRACTION = 0.5


def _held_looking(log_name: str, inputs: dict) -> list[str]:
    """A warning per torque column read linearly by default whose samples come in runs of
    equal values (at least `HELD_FRACTION` of consecutive pairs equal, and some change):
    the shape of a digital controller's held command, which read linearly leads the rig's
    real input by half a sample."""
    out = []
    for column, values in sorted(inputs.items()):
        v = np.asarray(values)
        if v.size < 3:
            continue
        same = float(np.mean(v[1:] == v[:-1]))
        if HELD_FRACTION <= same < 1.0:
            out.append(
                f"log {log_name!r}: {column} is piecewise constant ({100 * same:.0f} % of consecutive samples "
                "equal) and is read linearly between samples (the default); if it logs a digital controller's "
                f'command, declare hold = "zoh" (or {{ {column} = "zoh" }}) in this [[logs]] entry: read linearly, '
                "a held command leads the real input by half a sample (docs/experiment-format.md, hold)"
            )
    return out


def _looks_like_torque(header: str) -> bool:
    """A column header with a torque unit (`[N m]`, `[mN m]`, ...) or named like one
    (`tau`, `torque`, `moment`)."""
    try:
        name, unit = u.split_header(header)
    except ValueError:
        return False
    canonical = u.normalise_unit(unit) if unit else None
    if canonical is not None and u.unit_dimension(canonical) == u.TORQUE:
        return True
    return any(word in name.lower() for word in ("tau", "torque", "moment"))


@dataclasses.dataclass(frozen=True, eq=False)
class Experiment:
    """A loaded experiment file.

    - `path`, `name`, `description`.
    - `chain`: the rig as a `flexdyn.Chain`, with `rig.set` applied (the free parameters
      are at these nominal values, not at their guesses: see `chain_at_guess`).
    - `free`: the `FreeParameter`s, in file order (chain and measurement parameters).
    - `noise`: every output channel -> standard deviation (SI), or None to estimate it.
    - `logs`: the `LogSpec`s, in file order.
    - `measurement`: the sensors and drives between the model and the logs
      (`identify.measurement.Measurement`, from `[sensors.<channel>]` and
      `[actuators.joint<i>]`; a measurement parameter that is free but not given there is
      present at its neutral value); a sensor's declared `kind` and `resolution` are on its
      `Sensor`.
    - `starts`: `[[starts]]`, extra points for the fit's multi-start stage, each a dict of
      free parameter -> SI value (the others start at their guesses): `identify.fit`'s
      `extra_starts`.
    - `controller`: `[controller]`, the feedback law every log ran under
      (`identify.Controller`), or None (open loop).
    """

    path: Path
    name: str
    description: str
    chain: fd.Chain
    free: tuple[FreeParameter, ...]
    noise: dict[str, float | None]
    logs: tuple[LogSpec, ...]
    measurement: meas.Measurement = dataclasses.field(default_factory=meas.Measurement)
    starts: tuple[dict[str, float], ...] = ()
    controller: Controller | None = None

    @property
    def fit_logs(self) -> tuple[LogSpec, ...]:
        return tuple(entry for entry in self.logs if entry.role == "fit")

    @property
    def validation_logs(self) -> tuple[LogSpec, ...]:
        return tuple(entry for entry in self.logs if entry.role == "validation")

    @property
    def output_channels(self) -> tuple[str, ...]:
        """Measured output channels across all logs, sorted."""
        return tuple(sorted({c for entry in self.logs for c in entry.log.outputs}))

    @property
    def input_channels(self) -> tuple[str, ...]:
        return tuple(sorted({c for entry in self.logs for c in entry.log.inputs}))

    def chain_at_guess(self) -> fd.Chain:
        """The chain with every free chain parameter at its guess."""
        return fd.with_parameters(self.chain, meas.split_values({p.name: p.guess for p in self.free})[0])

    def measurement_at_guess(self) -> meas.Measurement:
        """The measurement model with every free measurement parameter at its guess."""
        return meas.with_parameters(self.measurement, meas.split_values({p.name: p.guess for p in self.free})[1])

    def summary(self) -> str:
        lines = [f"experiment {self.name!r} ({self.path})", f"  coordinates: {self.chain.coordinate_names()}"]
        lines.append(f"  {gravity_text(self.chain.gravity)}")
        for p in self.free:
            scale = "log" if p.log_scale else "linear"
            own = ", one value per log" if p.per_log else ""
            lines.append(f"  free {p.name} = {p.guess:g} in [{p.lower}, {p.upper}] {p.unit} ({scale}{own})")
        for k, start in enumerate(self.starts, start=1):
            lines.append(f"  start {k}: " + ", ".join(f"{n} = {v:g}" for n, v in start.items()))
        for c, s in self.noise.items():
            lines.append(f"  noise {c}: {'estimate' if s is None else _noise_text(c, s)}")
        for c, sensor in sorted(self.measurement.sensors.items()):
            described = [sensor.kind] if sensor.kind is not None else []
            if sensor.resolution is not None:
                described.append(f"resolution {_noise_text(c, sensor.resolution)}")
            if described:
                lines.append(f"  sensor {c}: {', '.join(described)}")
        for n in meas.parameter_names(self.measurement):
            unit = meas.unit(n, channel_unit)
            lines.append(f"  measurement {n} = {float(meas.get_parameter(self.measurement, n)):g} {unit}".rstrip())
        if self.controller is not None:
            lines.append(f"  controller: {self.controller.describe()}")
        for entry in self.logs:
            lines.append(f"  [{entry.role}] " + entry.log.summary().replace("\n", "\n    "))
            estimated = [
                f"{what} {', '.join(items)}"
                for what, items in (("initial state", entry.fit_initial), ("sensor offset of", entry.offsets))
                if items
            ]
            if estimated:
                lines.append("    estimated for this log: " + "; ".join(estimated))
            if entry.set:
                units = {n: fd.parameter_unit(self.chain, n) for n in entry.set}
                lines.append("    set: " + ", ".join(f"{n} = {v:g} {units[n]}" for n, v in entry.set.items()))
            lines.extend(f"  warning: {w}" for w in entry.warnings())
        return "\n".join(lines)


def _noise_text(channel: str, sigma: float) -> str:
    """`0.000349066 rad (0.02 deg)`: SI, and in the unit the reports use when it differs
    (a noise declared in degrees is echoed in degrees too)."""
    from .units import display_unit

    si = u.SI_UNIT[u.channel_dimension(channel)]
    scale, unit = display_unit(channel)
    shown = f" ({sigma * scale:.6g} {unit})" if unit not in (si, "SI") else ""
    return f"{sigma:g} {si}{shown}"


def gravity_text(gravity) -> str:
    """The rig's gravity and where it makes the first link hang, in the logs' angle
    convention (`theta1` from the base x axis, counter-clockwise): the check of a log's
    angle zero against the model's (docs/experiment-format.md, "Gravity and the angle zero")."""
    g = np.asarray(gravity, float)
    if not np.any(g):
        return "gravity [0, 0]: a rig in a horizontal plane (give [rig] gravity for a vertical one)"
    hang = math.degrees(math.atan2(g[1], g[0]))
    return (
        f"gravity [{g[0]:g}, {g[1]:g}] m/s^2: the first link hangs at theta1 = {hang:.0f} deg "
        "(its centre of mass below the joint): a free swing settles about that angle"
    )
