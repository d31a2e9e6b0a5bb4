"""Experiment files: a TOML description of a rig, its logs and what to fit.

`load_experiment(path)` reads the file (never writes anything), builds the rig as
a `flexdyn.Chain`, loads and checks every log (`identify.logs`) and returns an
`Experiment`. Every mistake raises `ExperimentError` (or `LogError` for a
problem inside a log file), both `ValueError`s, whose message names the file,
the line when it can be found, the key path (`logs[2].columns.tip1`) and what
was expected. The format is documented, with a full example, in
`identify/FORMAT.md`.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
import re
import tomllib
from collections.abc import Mapping
from pathlib import Path

import numpy as np

import flexdyn as fd

from . import measurement as meas, units as u
from .channels import channel_problem, channel_unit, state_names
from .logs import MIN_SAMPLES, Calibration, Log, LogError, check_calibration, load_log


class ExperimentError(ValueError):
    """An experiment file is not usable; the message names the file, line, key and the fix."""


ROLES = ("fit", "validation")

#: Named rigs (`rig.base`) and the functions that build them.
RIGS = {
    "rigid_pendulum": fd.rigs.rigid_pendulum,
    "flexible_pendulum": fd.rigs.flexible_pendulum,
    "two_link_flexible_arm": fd.rigs.two_link_flexible_arm,
    "flexible_link_joint_arm": fd.rigs.flexible_link_joint_arm,
}

#: Part types of an explicit chain (`[[rig.links]] type = ...`).
LINK_TYPES = {"rigid": fd.RigidLink, "flexible": fd.FlexibleLink}
JOINT_TYPES = {"rigid": fd.RigidJoint, "elastic": fd.ElasticJoint}

_TOP_KEYS = ("experiment", "rig", "parameters", "starts", "noise", "logs", "sensors", "actuators")
_EXPERIMENT_KEYS = ("name", "description", "strict", "min_samples")
_RIG_KEYS = ("base", "options", "set", "gravity", "links", "joints", "hubs", "payload")
_LOG_KEYS = ("file", "name", "role", "columns", "calibration", "initial", "fit_initial", "offsets", "strict", "set")
_PARAMETER_KEYS = ("guess", "lower", "upper", "per_log")
_SENSOR_KEYS = ("gain", "offset", "delay", "highpass")
_ACTUATOR_KEYS = ("lag",)


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
    - `columns`: channel -> `'column [unit]'` as written (empty if the CSV header was used).
    - `calibration`: channel -> `Calibration` for voltage, strain-gauge and motor-side columns.
    - `initial`: known initial-state entries, coordinate or `<coordinate>_rate` -> SI value
      (entries not listed are 0, except rotor angles/rates of elastic joints, which default
      to the link's: see FORMAT.md). Also the starting guess of entries in `fit_initial`.
    - `fit_initial`: initial-state entries to estimate for this log.
    - `offsets`: output channels whose constant sensor offset is estimated for this log.
    - `log`: the loaded data (SI).
    - `measured`: the entries of `initial` given as `"measured"` (the log's first sample).
    - `set`: this log's known parameter values that differ from the rig's (SI; a payload
      sweep: `{"payload.mass": 0.02}`), `identify.LogData.set`.
    """

    name: str
    file: Path
    role: str
    columns: dict[str, str]
    calibration: dict[str, Calibration]
    initial: dict[str, float]
    fit_initial: tuple[str, ...]
    offsets: tuple[str, ...]
    log: Log
    measured: tuple[str, ...] = ()
    set: dict[str, float] = dataclasses.field(default_factory=dict)

    @property
    def outputs(self) -> dict[str, np.ndarray]:
        return self.log.outputs

    def warnings(self) -> list[str]:
        """What in this entry may bias a fit beyond its intervals: an initial entry taken
        from the log's first sample (`"measured"`) and not estimated holds that sample,
        noise included, as exact (found in review: with 0.08 deg of noise on the first
        sample, the intervals of EI, the damping and the payload missed the truth by 10-13
        standard errors, and the fit reported no problem)."""
        out = []
        held = [s for s in self.measured if s not in self.fit_initial]
        if held:
            names = ", ".join(held)
            out.append(
                f'log {self.name!r}: {names} = "measured" holds the first sample, noise included, as the exact '
                f"initial value, which biases the fit beyond its intervals; add {names} to fit_initial to estimate "
                "it from the whole log (the first sample is its starting guess)"
            )
        # (review: a two-link log whose `torque2` was left out of `columns` ran with joint 2
        # unpowered, and only "columns not used: 'tau2 [N m]'" hinted at it)
        for header in self.log.ignored:
            if _looks_like_torque(header):
                mapped = ", ".join(sorted(self.log.inputs)) or "none"
                out.append(
                    f"log {self.name!r}: the unused column {header!r} looks like a torque, but a joint without a "
                    f"torque column is unpowered in the model (torque columns mapped: {mapped}); map it in columns "
                    f"(e.g. torque2 = {header!r}) if it drives a joint"
                )
        return out

    def torque(self, n_joints: int) -> np.ndarray | None:
        """Applied torques, shape (T, n_joints), N m (`Log.torque`)."""
        return self.log.torque(n_joints)


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
      present at its neutral value).
    - `starts`: `[[starts]]`, extra points for the fit's multi-start stage, each a dict of
      free parameter -> SI value (the others start at their guesses): `identify.fit`'s
      `extra_starts`.
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
        for n in meas.parameter_names(self.measurement):
            unit = meas.unit(n, channel_unit)
            lines.append(f"  measurement {n} = {float(meas.get_parameter(self.measurement, n)):g} {unit}".rstrip())
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
    (review: `identify check` echoed a "0.02 deg" noise as rad only)."""
    from .units import display_unit

    si = u.SI_UNIT[u.channel_dimension(channel)]
    scale, unit = display_unit(channel)
    shown = f" ({sigma * scale:.6g} {unit})" if unit not in (si, "SI") else ""
    return f"{sigma:g} {si}{shown}"


def gravity_text(gravity) -> str:
    """The rig's gravity and where it makes the first link hang, in the logs' angle
    convention (`theta1` from the base x axis, counter-clockwise): the check of a log's
    angle zero against the model's (FORMAT.md, "Gravity and the angle zero")."""
    g = np.asarray(gravity, float)
    if not np.any(g):
        return "gravity [0, 0]: a rig in a horizontal plane (give [rig] gravity for a vertical one)"
    hang = math.degrees(math.atan2(g[1], g[0]))
    return (
        f"gravity [{g[0]:g}, {g[1]:g}] m/s^2: the first link hangs at theta1 = {hang:.0f} deg "
        "(its centre of mass below the joint): a free swing settles about that angle"
    )


# ---------------------------------------------------------------------------
# Locating keys in the TOML text (tomllib gives no positions)
# ---------------------------------------------------------------------------

_KEY = r"(?:[A-Za-z0-9_-]+|\"[^\"]*\"|'[^']*')"
_DOTTED = rf"{_KEY}(?:\s*\.\s*{_KEY})*"
_TABLE_RE = re.compile(rf"^\s*(\[\[?)\s*({_DOTTED})\s*\]\]?")
_ASSIGN_RE = re.compile(rf"^\s*({_DOTTED})\s*=")
_INLINE_KEY_RE = re.compile(rf"[{{,]\s*({_DOTTED})\s*=")


def _split_key(dotted: str) -> list[str]:
    return [k.strip()[1:-1] if k.strip()[:1] in "\"'" else k.strip() for k in re.findall(_KEY, dotted)]


def _key_lines(text: str) -> dict[tuple, int]:
    """Best-effort map from key paths (array-of-tables entries numbered from 1) to the
    1-based line where they are defined."""
    lines: dict[tuple, int] = {}
    counts: dict[tuple, int] = {}
    table: tuple = ()
    for no, line in enumerate(text.splitlines(), start=1):
        stripped = line.split("#", 1)[0] if '"' not in line and "'" not in line else line
        m = _TABLE_RE.match(stripped)
        if m:
            path: tuple = ()
            for k in _split_key(m[2]):
                path = path + (k,)
                if path in counts and not (m[1] == "[[" and len(path) == len(_split_key(m[2]))):
                    path = path + (counts[path],)
            if m[1] == "[[":
                lines.setdefault(path, no)  # the array as a whole: its first entry
                counts[path] = counts.get(path, 0) + 1
                path = path + (counts[path],)
            table = path
            lines.setdefault(table, no)
            continue
        m = _ASSIGN_RE.match(stripped)
        if m:
            dotted = tuple(_split_key(m[1]))
            for n in range(1, len(dotted) + 1):  # a bare dotted key `a.b = 1` also makes table `a`
                lines.setdefault(table + dotted[:n], no)
            key = table + dotted
            rest = stripped[m.end() :]
            for inner in _INLINE_KEY_RE.finditer(rest):
                lines.setdefault(key + tuple(_split_key(inner[1])), no)
    return lines


def _key_text(path: tuple) -> str:
    out = ""
    for k in path:
        if isinstance(k, int):
            out += f"[{k}]"
        else:
            k = k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else f'"{k}"'
            out += ("." if out else "") + k
    return out


class _Reader:
    """Error helper: names the file, the line of a key path and the key path."""

    def __init__(self, path: Path, text: str):
        self.path = path
        self.lines = _key_lines(text)

    def where(self, *key) -> str:
        line = None
        for n in range(len(key), 0, -1):
            if key[:n] in self.lines:
                line = self.lines[key[:n]]
                break
        at = f"{self.path}, line {line}" if line is not None else str(self.path)
        return f"{at}: {_key_text(key)}" if key else at

    def error(self, key: tuple, message: str) -> ExperimentError:
        return ExperimentError(f"{self.where(*key)}: {message}")

    # -- typed getters ----------------------------------------------------
    def table(self, value, key: tuple, allowed=None) -> Mapping:
        if not isinstance(value, Mapping):
            raise self.error(key, f"expected a table, got {_show(value)}")
        if allowed is not None:
            extra = [k for k in value if k not in allowed]
            if extra:
                raise self.error(key + (extra[0],), f"unknown key; expected one of {', '.join(allowed)}")
        return value

    def number(self, value, key: tuple) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.error(key, f"expected a number (SI units), got {_show(value)}")
        if not math.isfinite(value):
            raise self.error(key, f"expected a finite number, got {value!r}")
        return float(value)

    def string(self, value, key: tuple) -> str:
        if not isinstance(value, str):
            raise self.error(key, f"expected a string, got {_show(value)}")
        return value

    def names(self, value, key: tuple) -> list[str]:
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise self.error(key, f'expected a list of names like ["theta1"], got {_show(value)}')
        return value


def _show(value) -> str:
    kind = {dict: "a table", list: "an array", str: "a string", bool: "a boolean"}.get(type(value))
    return f"{kind} {value!r}" if kind else repr(value)


# ---------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------


def load_experiment(path) -> Experiment:
    """Read an experiment file (TOML) and everything it refers to; see `identify/FORMAT.md`.

    Raises `ExperimentError` for a problem in the experiment file and `LogError` for one
    in a log file (both `ValueError`); nothing is written.
    """
    path = Path(path)
    if not path.is_file():
        raise ExperimentError(f"{path.resolve()}: experiment file does not exist")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise ExperimentError(f"{path}: expected a UTF-8 text file ({e})") from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ExperimentError(f"{path}: not valid TOML: {e}") from None
    r = _Reader(path, text)
    r.table(doc, (), _TOP_KEYS)

    meta = r.table(doc.get("experiment", {}), ("experiment",), _EXPERIMENT_KEYS)
    name = r.string(meta.get("name", path.stem), ("experiment", "name"))
    description = r.string(meta.get("description", ""), ("experiment", "description"))
    strict = meta.get("strict", False)
    if not isinstance(strict, bool):
        raise r.error(("experiment", "strict"), f"expected true or false, got {_show(strict)}")
    min_samples = meta.get("min_samples", MIN_SAMPLES)
    if isinstance(min_samples, bool) or not isinstance(min_samples, int) or min_samples < 2:
        raise r.error(("experiment", "min_samples"), f"expected an integer >= 2, got {_show(min_samples)}")

    if "rig" not in doc:
        raise r.error((), 'missing [rig]: expected base = "<named rig>" or an explicit chain ([[rig.links]], ...)')
    chain = _build_rig(r, r.table(doc["rig"], ("rig",), _RIG_KEYS))

    if "logs" not in doc:
        raise r.error((), 'no [[logs]]; expected at least one [[logs]] table with file = "..."')
    if not isinstance(doc["logs"], list) or not doc["logs"]:
        raise r.error(("logs",), "expected one or more [[logs]] tables")
    logs = []
    for k, spec in enumerate(doc["logs"], start=1):
        logs.append(_log_entry(r, chain, r.table(spec, ("logs", k), _LOG_KEYS), k, strict, min_samples))
    seen: dict[str, int] = {}
    for k, entry in enumerate(logs, start=1):
        if entry.name in seen:
            raise r.error(
                ("logs", k, "name"),
                f"log name {entry.name!r} is also used by logs[{seen[entry.name]}]; give each log a unique name",
            )
        seen[entry.name] = k
    same: dict[tuple, int] = {}
    for k, entry in enumerate(logs, start=1):
        read = (entry.file, tuple(sorted(entry.columns.items())))
        if read in same:
            raise r.error(
                ("logs", k, "file"),
                f"logs[{same[read]}] already reads {entry.file.name} with the same columns: the same samples "
                "would count twice (and the intervals come out too narrow); list each log once",
            )
        same[read] = k
    if not any(entry.role == "fit" for entry in logs):
        raise r.error(("logs",), 'every log has role = "validation"; expected at least one with role = "fit"')

    noise = _noise(r, logs, r.table(doc.get("noise", {}), ("noise",)))
    measurement = _measurement(r, chain, logs, doc)
    free, measurement, chain = _free_parameters(
        r, chain, measurement, logs, r.table(doc.get("parameters", {}), ("parameters",))
    )
    free_names = {p.name for p in free}
    for k, entry in enumerate(logs, start=1):
        for pname in entry.set:
            if pname in free_names:
                raise r.error(
                    ("logs", k, "set", pname),
                    f"{pname} is also a free parameter in [parameters]; a known value per log and a fitted one "
                    "exclude each other (to fit a value per log: per_log = true under [parameters]; every "
                    "parameter in each log on its own: identify fit --independent)",
                )
    starts = _starts(r, free, doc.get("starts", []))
    return Experiment(
        path=path,
        name=name,
        description=description,
        chain=chain,
        free=tuple(free),
        noise=noise,
        logs=tuple(logs),
        measurement=measurement,
        starts=starts,
    )


# -- the rig -----------------------------------------------------------------


def _build_rig(r: _Reader, rig: Mapping) -> fd.Chain:
    explicit = [k for k in ("gravity", "links", "joints", "hubs", "payload") if k in rig]
    if "base" in rig:
        if explicit:
            raise r.error(
                ("rig", explicit[0]),
                "rig.base names a built-in rig; give either base (with options) "
                "or an explicit chain ([[rig.links]], ...), not both",
            )
        chain = _named_rig(r, rig)
    elif "links" in rig:
        if "options" in rig:
            raise r.error(("rig", "options"), "options apply to a named rig (rig.base); remove them")
        chain = _explicit_rig(r, rig)
    else:
        raise r.error(("rig",), f"expected base = one of {', '.join(RIGS)}, or [[rig.links]] tables")
    return _apply_set(r, chain, r.table(rig.get("set", {}), ("rig", "set")))


def _named_rig(r: _Reader, rig: Mapping) -> fd.Chain:
    base = rig["base"]
    if base not in RIGS:
        raise r.error(("rig", "base"), f"unknown rig {base!r}; expected one of {', '.join(RIGS)}")
    build = RIGS[base]
    options = dict(r.table(rig.get("options", {}), ("rig", "options")))
    accepted = inspect.signature(build).parameters
    for key, value in options.items():
        if key not in accepted:
            listing = ", ".join(f"{k} (default {p.default!r})" for k, p in accepted.items())
            raise r.error(("rig", "options", key), f"{base} has no option {key!r}; its options are {listing}")
        default, okey = accepted[key].default, ("rig", "options", key)
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise r.error(okey, f"expected true or false, got {_show(value)}")
        elif key == "n_modes":
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise r.error(okey, f"expected an integer >= 1, got {_show(value)}")
        else:
            r.number(value, okey)
    try:
        return build(**options)
    except (ValueError, TypeError) as e:
        raise r.error(("rig", "options"), f"{base}({_kwargs(options)}) failed: {e}") from None


def _kwargs(options: Mapping) -> str:
    return ", ".join(f"{k}={v!r}" for k, v in options.items())


def _make_part(r: _Reader, cls, spec: Mapping, key: tuple, skip=("type",)):
    params = inspect.signature(cls.__init__).parameters
    accepted = [k for k in params if k != "self"]
    kwargs = {}
    for field, value in spec.items():
        if field in skip:
            continue
        if field not in accepted:
            raise r.error(key + (field,), f"{cls.__name__} has no parameter {field!r}; expected {', '.join(accepted)}")
        default = params[field].default
        if field == "n_modes":
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise r.error(key + (field,), f"expected an integer >= 1, got {_show(value)}")
        elif isinstance(default, bool):
            if not isinstance(value, bool):
                raise r.error(key + (field,), f"expected true or false, got {_show(value)}")
        elif isinstance(value, list):
            value = [r.number(v, key + (field,)) for v in value]
        else:
            value = r.number(value, key + (field,))
        kwargs[field] = value
    missing = [k for k, p in params.items() if k != "self" and p.default is inspect.Parameter.empty and k not in kwargs]
    if missing:
        raise r.error(key, f"{cls.__name__} needs {', '.join(missing)} (SI units)")
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as e:
        raise r.error(key, str(e)) from None


def _explicit_rig(r: _Reader, rig: Mapping) -> fd.Chain:
    def parts(name, kinds, default):
        specs = rig.get(name)
        if specs is None:
            return None
        if not isinstance(specs, list) or not all(isinstance(s, Mapping) for s in specs):
            raise r.error(("rig", name), f"expected [[rig.{name}]] tables, got {_show(specs)}")
        out = []
        for k, spec in enumerate(specs, start=1):
            key = ("rig", name, k)
            if kinds is None:
                out.append(_make_part(r, default, spec, key))
                continue
            kind = spec.get("type", None if default is None else "rigid")
            if kind not in kinds:
                raise r.error(key + ("type",), f"expected type = {' or '.join(repr(t) for t in kinds)}, got {kind!r}")
            out.append(_make_part(r, kinds[kind], spec, key))
        return out

    links = parts("links", LINK_TYPES, None)
    joints = parts("joints", JOINT_TYPES, fd.RigidJoint)
    hubs = parts("hubs", None, fd.Hub)
    n = len(links)
    for name, given in (("joints", joints), ("hubs", hubs)):
        if given is not None and len(given) != n:
            raise r.error(
                ("rig", name),
                f"{len(given)} [[rig.{name}]] table(s) for {n} link(s); expected one per link "
                f"(or none: {'rigid joints' if name == 'joints' else 'massless hubs'})",
            )
    payload = None
    if "payload" in rig:
        payload = _make_part(r, fd.Payload, r.table(rig["payload"], ("rig", "payload")), ("rig", "payload"))
    gravity = rig.get("gravity", [0.0, 0.0])
    if not isinstance(gravity, list) or len(gravity) != 2:
        raise r.error(("rig", "gravity"), f"expected [gx, gy] in m/s^2 (e.g. [0.0, -9.81]), got {_show(gravity)}")
    gravity = [r.number(g, ("rig", "gravity")) for g in gravity]
    try:
        return fd.Chain(links=links, joints=joints, hubs=hubs, payload=payload, gravity=gravity)
    except (ValueError, TypeError) as e:
        raise r.error(("rig",), str(e)) from None


def _parts(chain: fd.Chain):
    return [*chain.links, *chain.joints, *chain.hubs, chain.payload]


def _unknown_parameter(r: _Reader, chain: fd.Chain, key: tuple, value) -> ExperimentError:
    valid = fd.parameter_names(chain)
    name = key[-1]
    return _dotted_key_error(r, key, name, value, valid) or r.error(
        key, f"unknown parameter{fd.params.did_you_mean(name, valid)}; this rig has: {', '.join(valid)}"
    )


def _dotted_key_error(r: _Reader, key: tuple, name: str, value, valid) -> ExperimentError | None:
    """The error for `name.sub = ...` written bare (TOML makes a table `name` of it) where
    `"name.sub"` is one of `valid`; None otherwise."""
    if isinstance(value, Mapping) and any(f"{name}.{k}" in valid for k in value):
        sub = next(k for k in value if f"{name}.{k}" in valid)
        return r.error(key, f'a bare dotted key makes a table in TOML; quote the name: "{name}.{sub}" = ...')
    return None


def _apply_set(r: _Reader, chain: fd.Chain, overrides: Mapping) -> fd.Chain:
    valid = fd.parameter_names(chain)
    for name, value in overrides.items():
        key = ("rig", "set", name)
        if fd.params.absent_optional_term(chain, name):  # e.g. "joint2.coulomb": switched on
            chain = fd.with_optional_terms(chain, [name])
            valid = fd.parameter_names(chain)
        if name not in valid:
            raise _unknown_parameter(r, chain, key, value)
        value = r.number(value, key)
        if not fd.is_signed(chain, name) and value < 0:
            raise r.error(key, f"expected a value >= 0 [{fd.parameter_unit(chain, name)}], got {value!r}")
        try:  # with_parameters re-runs the part's own checks (e.g. EI > 0)
            chain = fd.with_parameters(chain, {name: value})
        except ValueError as e:
            raise r.error(key, str(e)) from None
    return chain


def _free_parameters(
    r: _Reader, chain: fd.Chain, measurement: meas.Measurement, logs: list[LogSpec], table: Mapping
) -> tuple[list[FreeParameter], meas.Measurement, fd.Chain]:
    """The `[parameters]` entries, the measurement model with every free measurement
    parameter present (at its neutral value when `[sensors]`/`[actuators]` do not give it),
    and the chain with every optional term they name present (`joint2.coulomb` on a rig
    without dry friction: at 0.0, the fit starts from the guess)."""
    valid = fd.parameter_names(chain)
    free = []
    for name, spec in table.items():
        key = ("parameters", name)
        if fd.params.absent_optional_term(chain, name):
            # (review: "joint2.coulomb" on a named rig said "unknown parameter", although
            # the README lists it; a named rig cannot be given the term any other way)
            chain = fd.with_optional_terms(chain, [name])
            valid = fd.parameter_names(chain)
        if meas.is_measurement_parameter(name):
            measurement = _measurement_parameter(r, chain, measurement, logs, name, key)
            unit = meas.unit(name, channel_unit)
            log_scale = not meas.is_signed(name)
            current = float(meas.get_parameter(measurement, name))
        elif name not in valid:
            raise _unknown_parameter(r, chain, key, spec)
        else:
            unit = fd.parameter_unit(chain, name)
            log_scale = not fd.is_signed(chain, name)
            current = float(fd.get_parameter(chain, name))
        if not isinstance(spec, Mapping):
            spec = {"guess": spec}
        r.table(spec, key, _PARAMETER_KEYS)
        guess = r.number(spec["guess"], key + ("guess",)) if "guess" in spec else current
        lower = r.number(spec["lower"], key + ("lower",)) if "lower" in spec else None
        upper = r.number(spec["upper"], key + ("upper",)) if "upper" in spec else None
        if lower is not None and upper is not None and lower >= upper:
            raise r.error(key, f"lower = {lower:g} is not below upper = {upper:g}; expected lower < upper")
        if log_scale:
            if lower is not None and lower <= 0:
                raise r.error(
                    key + ("lower",),
                    f"{name} cannot be negative and is fitted in log space; expected lower > 0 "
                    f"(e.g. {_positive_example(guess, upper)}), got {lower:g}",
                )
            if guess <= 0:
                source = "guess" if "guess" in spec else f"the model's value of {name} (used as the guess)"
                raise r.error(key + ("guess",), f"{source} is {guess:g}; expected a guess > 0 (fitted in log space)")
        if (lower is not None and guess < lower) or (upper is not None and guess > upper):
            source = "guess" if "guess" in spec else f"the rig's value (no guess given) {guess:g}"
            raise r.error(
                key,
                f"{source} = {guess:g} is outside [{_bound(lower)}, {_bound(upper)}] {unit}; "
                "expected lower <= guess <= upper",
            )
        per_log = spec.get("per_log", False)
        if not isinstance(per_log, bool):
            raise r.error(key + ("per_log",), f"expected true or false, got {_show(per_log)}")
        free.append(FreeParameter(name, guess, lower, upper, unit, log_scale, per_log))
    return free, measurement, chain


def _starts(r: _Reader, free: list[FreeParameter], entries) -> tuple[dict[str, float], ...]:
    """The `[[starts]]` tables: each names free parameters (quoted, as in `[parameters]`)
    and gives each a value in SI units inside its bounds (> 0 for a parameter fitted in log
    space)."""
    if not isinstance(entries, list):
        raise r.error(("starts",), f'expected [[starts]] tables ("link1.EI" = 2.0, ...), got {_show(entries)}')
    if entries and not free:
        raise r.error(("starts",), "there are no free parameters ([parameters]) for a start to set")
    by_name = {p.name: p for p in free}
    out = []
    for k, entry in enumerate(entries, start=1):
        key = ("starts", k)
        entry = r.table(entry, key)
        if not entry:
            raise r.error(key, 'empty start; expected free parameters and their values, e.g. "link1.EI" = 2.0')
        start = {}
        for name, value in entry.items():
            if name not in by_name:
                raise _dotted_key_error(r, key + (name,), name, value, by_name) or r.error(
                    key + (name,),
                    f"not a free parameter; a start sets those listed under [parameters] ({', '.join(by_name)})",
                )
            p = by_name[name]
            v = r.number(value, key + (name,))
            if p.log_scale and v <= 0:
                raise r.error(key + (name,), f"{name} is fitted in log space; expected a value > 0, got {v:g}")
            if (p.lower is not None and v < p.lower) or (p.upper is not None and v > p.upper):
                raise r.error(
                    key + (name,),
                    f"{v:g} is outside [{_bound(p.lower)}, {_bound(p.upper)}] {p.unit}; expected a value inside "
                    "the parameter's bounds",
                )
            start[name] = v
        out.append(start)
    return tuple(out)


def _measurement_parameter(r: _Reader, chain, measurement, logs, name: str, key: tuple) -> meas.Measurement:
    """`measurement` with the free measurement parameter `name` present (checked: its
    channel is measured by a log, its joint exists)."""
    channel, joint = meas.target(name)
    if channel is not None:
        measured = sorted({c for entry in logs for c in entry.log.outputs})
        if channel not in measured:
            raise r.error(key, f"no log measures {channel}; the logs measure {', '.join(measured)}")
    elif not 1 <= joint <= chain.n_links:
        raise r.error(key, f"the rig has joints 1 to {chain.n_links}; got actuator{joint}")
    try:
        meas.get_parameter(measurement, name)
        return measurement
    except KeyError:
        return meas.with_effect(measurement, name)


def _measurement(r: _Reader, chain: fd.Chain, logs: list[LogSpec], doc: Mapping) -> meas.Measurement:
    """`[sensors.<channel>]` (gain, offset, delay, highpass) and `[actuators.joint<i>]`
    (lag): the measurement model between the rig and the logs (`identify.measurement`)."""
    measured = sorted({c for entry in logs for c in entry.log.outputs})
    sensors = {}
    for channel, spec in r.table(doc.get("sensors", {}), ("sensors",)).items():
        key = ("sensors", channel)
        if channel not in measured:
            raise r.error(key, f"no log measures {channel}; the logs measure {', '.join(measured)}")
        spec = r.table(spec, key, _SENSOR_KEYS)
        dims = {"gain": None, "offset": u.channel_dimension(channel), "delay": u.TIME, "highpass": u.FREQUENCY}
        values = {field: _quantity(r, value, dims[field], key + (field,)) for field, value in spec.items()}
        for field in ("delay", "highpass"):
            if values.get(field, 0.0) < 0:
                raise r.error(key + (field,), f"expected a value >= 0, got {values[field]:g}")
        if values.get("gain", 1.0) <= 0:
            raise r.error(key + ("gain",), f"expected a gain > 0, got {values['gain']:g}")
        sensors[channel] = meas.Sensor(**values)
    lags = [None] * chain.n_links
    for joint, spec in r.table(doc.get("actuators", {}), ("actuators",)).items():
        key = ("actuators", joint)
        m = re.fullmatch(r"joint([1-9][0-9]*)", joint)
        if m is None or int(m[1]) > chain.n_links:
            raise r.error(key, f"expected joint1 ... joint{chain.n_links} (the rig's joints), got {joint!r}")
        spec = r.table(spec, key, _ACTUATOR_KEYS)
        if "lag" in spec:
            lag = _quantity(r, spec["lag"], u.TIME, key + ("lag",))
            if lag < 0:
                raise r.error(key + ("lag",), f"expected a lag >= 0 (s), got {lag:g}")
            lags[int(m[1]) - 1] = lag
    return meas.Measurement(sensors, lags if any(v is not None for v in lags) else ())


def _quantity(r: _Reader, value, dimension: str | None, key: tuple) -> float:
    """A number (SI) or, for a quantity with a dimension, a string with a unit."""
    if isinstance(value, str) and dimension is not None:
        try:
            value = u.parse_quantity(value, dimension)
        except ValueError as e:
            raise r.error(key, str(e)) from None
    return r.number(value, key)


def _bound(x):
    return "unbounded" if x is None else f"{x:g}"


def _positive_example(guess, upper):
    ref = guess if guess > 0 else (upper if upper is not None and upper > 0 else 1.0)
    return f"{ref / 100:g}"


# -- logs --------------------------------------------------------------------


def _log_entry(r: _Reader, chain: fd.Chain, spec: Mapping, k: int, strict: bool, min_samples: int) -> LogSpec:
    key = ("logs", k)
    if "file" not in spec:
        raise r.error(key, 'missing file = "..." (the log, relative to this experiment file)')
    file = r.string(spec["file"], key + ("file",))
    resolved = (r.path.parent / Path(file).expanduser()).resolve()
    if not resolved.is_file():
        what = "is a directory" if resolved.is_dir() else "does not exist"
        raise r.error(key + ("file",), f"log file {resolved} {what} (paths are relative to {r.path.parent.resolve()})")
    name = r.string(spec.get("name", resolved.stem), key + ("name",))
    role = spec.get("role", "fit")
    if role not in ROLES:
        raise r.error(key + ("role",), f'expected "fit" or "validation", got {_show(role)}')
    log_strict = spec.get("strict", strict)
    if not isinstance(log_strict, bool):
        raise r.error(key + ("strict",), f"expected true or false, got {_show(log_strict)}")

    columns = dict(r.table(spec.get("columns", {}), key + ("columns",)))
    if "columns" in spec and "time" not in columns:
        raise r.error(key + ("columns",), 'no time column; expected time = "<column> [s]" among the columns')
    for channel, source in columns.items():
        why = channel_problem(chain, channel)
        if why is not None:
            raise r.error(key + ("columns", channel), why)
        if not isinstance(source, str):
            raise r.error(key + ("columns", channel), f"expected a string 'column [unit]', got {_show(source)}")
    calibration = {}
    for channel, cal in r.table(spec.get("calibration", {}), key + ("calibration",)).items():
        ckey = key + ("calibration", channel)
        try:
            calibration[channel] = check_calibration(channel, cal, r.where(*ckey))
        except LogError as e:
            raise ExperimentError(str(e)) from None
        if columns and channel not in columns:
            raise r.error(ckey, f"no column is mapped to {channel}; expected one of {', '.join(columns)}")

    context = f"{r.path.name} {_key_text(key + ('columns',))}"
    try:
        log = load_log(
            resolved,
            columns or None,
            calibration=calibration,
            strict=log_strict,
            min_samples=min_samples,
            name=name,
            context=context,
        )
    except LogError as e:
        # a problem with one entry of the column mapping points at that entry's line
        at = key + ("columns", e.channel) if columns and e.channel in columns else key
        raise LogError(f"{e} [{r.where(*at)}]", channel=e.channel) from None
    if not columns:  # CSV read through its header: check the channels it found
        for channel in log.channels:
            why = channel_problem(chain, channel)
            if why is not None:
                raise r.error(key + ("file",), f"column {log.sources[channel]} of {resolved.name}: {why}")

    states = state_names(chain)
    initial, measured = {}, []
    for state, value in r.table(spec.get("initial", {}), key + ("initial",)).items():
        ikey = key + ("initial", state)
        if state not in states:
            raise r.error(ikey, f"not a coordinate of this rig; expected one of {', '.join(states)}")
        if value == "measured":
            if state not in log.outputs:
                raise r.error(ikey, f'"measured" needs a {state} channel in this log; it has {", ".join(log.outputs)}')
            value = float(log.outputs[state][0])
            measured.append(state)
        elif isinstance(value, str):
            # angles and modal coordinates (m, the mode's RMS deflection) take units (review:
            # "2 mm" for q1_1 was refused while [noise] takes any unit); rates take SI numbers
            dim = None if state.endswith("_rate") else u.ANGLE if state.startswith(("theta", "alpha")) else u.LENGTH
            if dim is None:
                raise r.error(
                    ikey,
                    f'expected a number (SI units: rad/s for an angle rate, m/s for a modal one) or "measured", '
                    f"got {_show(value)}",
                )
            try:
                value = u.parse_quantity(value, dim)
            except ValueError as e:
                raise r.error(ikey, f'{e}; or "measured"') from None
        initial[state] = r.number(value, ikey)
    # Rotor angles default to the link's (unloaded spring), as in flexdyn.initial_state.
    for i, joint in enumerate(chain.joints, start=1):
        if joint.elastic:
            for suffix in ("", "_rate"):
                if f"alpha{i}{suffix}" not in initial and f"theta{i}{suffix}" in initial:
                    initial[f"alpha{i}{suffix}"] = initial[f"theta{i}{suffix}"]
    fit_initial = r.names(spec.get("fit_initial", []), key + ("fit_initial",))
    for state in fit_initial:
        if state not in states:
            raise r.error(key + ("fit_initial",), f"{state!r} is not a coordinate; expected one of {', '.join(states)}")
    offsets = r.names(spec.get("offsets", []), key + ("offsets",))
    for channel in offsets:
        if channel not in log.outputs:
            raise r.error(
                key + ("offsets",),
                f"{channel!r} is not an output channel of this log; expected one of {', '.join(log.outputs)}",
            )
    return LogSpec(
        name=name,
        file=resolved,
        role=role,
        columns=columns,
        calibration=calibration,
        initial=initial,
        fit_initial=tuple(fit_initial),
        offsets=tuple(offsets),
        log=log,
        measured=tuple(measured),
        set=_log_set(r, chain, spec.get("set", {}), key + ("set",)),
    )


def _log_set(r: _Reader, chain: fd.Chain, table, key: tuple) -> dict[str, float]:
    """A log's `set` table: known values of the rig's parameters for this log (SI)."""
    out = {}
    valid = fd.parameter_names(chain)
    for name, value in r.table(table, key).items():
        pkey = key + (name,)
        if name not in valid:
            raise _unknown_parameter(r, chain, pkey, value)
        v = r.number(value, pkey)
        if not fd.is_signed(chain, name) and v < 0:
            raise r.error(pkey, f"expected a value >= 0 [{fd.parameter_unit(chain, name)}], got {v!r}")
        try:  # the part's own checks (e.g. EI > 0)
            fd.with_parameters(chain, {name: v})
        except ValueError as e:
            raise r.error(pkey, str(e)) from None
        out[name] = v
    return out


def _noise(r: _Reader, logs: list[LogSpec], table: Mapping) -> dict[str, float | None]:
    measured = sorted({c for entry in logs for c in entry.log.outputs})
    noise: dict[str, float | None] = {c: None for c in measured}
    for channel, value in table.items():
        key = ("noise", channel)
        if u.channel_dimension(channel) is None or not u.is_output(channel):
            raise r.error(key, f"not an output channel; expected one the logs measure: {', '.join(measured)}")
        if channel not in noise:
            raise r.error(key, f"no log measures {channel}; the logs measure {', '.join(measured)}")
        if value == "estimate":
            continue
        if isinstance(value, str):
            try:
                value = u.parse_quantity(value, u.channel_dimension(channel))
            except ValueError as e:
                raise r.error(key, f'{e}; or "estimate"') from None
        value = r.number(value, key)
        if value <= 0:
            raise r.error(key, f'expected a standard deviation > 0 (SI) or "estimate", got {value!r}')
        noise[channel] = value
    return noise
