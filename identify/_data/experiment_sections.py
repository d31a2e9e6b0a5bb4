"""The sections of an experiment file: the rig (named or explicit, `[rig.set]`), the free parameters
and extra starts, the sensors and actuator, the logs and noise levels.
"""

from __future__ import annotations

import inspect
import re
from collections.abc import Mapping

import flexdyn as fd

from . import measurement as meas, units as u
from .bag_columns import STAMPS
from .bag_log import is_bag
from .channels import channel_problem, channel_unit, state_names
from .columns import LogError, check_calibration
from .csv_numbers import DECIMALS
from .experiment import ROLES, FreeParameter, LogSpec
from .files import absolute, expand_user, input_problem, resolved as resolved_path
from .logs import MAT_SUFFIXES, load_log
from .toml_reader import ExperimentError, _dotted_key_error, _key_text, _Reader, _show, _unknown_parameter

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


_PARAMETER_KEYS = ("guess", "lower", "upper", "per_log")


_SENSOR_KEYS = ("gain", "offset", "delay", "highpass", "kind", "resolution")


_ACTUATOR_KEYS = ("lag",)


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
    if "motors" in rig:
        chain = _with_motors(r, chain, r.table(rig["motors"], ("rig", "motors")))
    return _apply_set(r, chain, r.table(rig.get("set", {}), ("rig", "set")))


def _with_motors(r: _Reader, chain: fd.Chain, table: Mapping) -> fd.Chain:
    """`chain` with the `[rig.motors.joint<i>]` tables' `flexdyn.DCMotor`s on their joints
    (parameters `motor<i>.<field>`, SI: resistance in ohm, torque_constant in N m/A, ...;
    `drive` one of `flexdyn.motor.DRIVES`)."""
    motors = list(chain.motors)
    for name, spec in table.items():
        key = ("rig", "motors", name)
        index = name.removeprefix("joint")
        if not name.startswith("joint") or not index.isdigit() or not 1 <= int(index) <= chain.n_links:
            raise r.error(key, f"expected a table joint<i> for i = 1 to {chain.n_links} (the joint the motor drives)")
        spec = r.table(spec, key)
        drive = spec.get("drive", "voltage")
        if drive not in fd.motor.DRIVES:
            listed = ", ".join(f'"{d}" ({unit})' for d, unit in fd.motor.DRIVES.items())
            raise r.error(
                key + ("drive",), f"expected one of {listed}: what the joint's input column is, got {_show(drive)}"
            )
        motor = _make_part(r, fd.DCMotor, spec, key, skip=("drive",))
        if drive != motor.drive:
            try:
                motor = fd.DCMotor(**{f: getattr(motor, f) for f in _MOTOR_FIELDS}, drive=drive)
            except ValueError as e:
                raise r.error(key, str(e)) from None
        motors[int(index) - 1] = motor
    return fd.Chain(chain.links, chain.joints, chain.hubs, chain.payload, chain.gravity, motors)


_MOTOR_FIELDS = (
    "resistance",
    "torque_constant",
    "efficiency",
    "inductance",
    "viscous",
    "coulomb",
    "voltage_limit",
    "smoothing_velocity",
)


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
            # an optional term named here is added to the chain (a named rig cannot be
            # given the term any other way), not refused as an unknown parameter
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
        sensor = measurement.sensors.get(channel)
        field = name.rsplit(".", 1)[1]
        why = meas.lacks(None if sensor is None else sensor.kind).get(field)
        if why is not None:
            raise r.error(key, f"{channel}'s sensor is of kind = {sensor.kind!r}, which has no {field}: {why}")
    elif not 1 <= joint <= chain.n_links:
        raise r.error(key, f"the rig has joints 1 to {chain.n_links}; got actuator{joint}")
    try:
        meas.get_parameter(measurement, name)
        return measurement
    except KeyError:
        return meas.with_effect(measurement, name)


def _measurement(r: _Reader, chain: fd.Chain, logs: list[LogSpec], doc: Mapping) -> meas.Measurement:
    """`[sensors.<channel>]` (kind, resolution, gain, offset, delay, highpass) and
    `[actuators.joint<i>]` (lag): the measurement model between the rig and the logs
    (`identify.measurement`). A kind that cannot measure the channel, or given an effect it
    cannot have (an encoder's gain), is an error."""
    measured = sorted({c for entry in logs for c in entry.log.outputs})
    sensors = {}
    for channel, spec in r.table(doc.get("sensors", {}), ("sensors",)).items():
        key = ("sensors", channel)
        if channel not in measured:
            raise r.error(key, f"no log measures {channel}; the logs measure {', '.join(measured)}")
        spec = dict(r.table(spec, key, _SENSOR_KEYS))
        described = {"kind": _sensor_kind(r, spec.pop("kind", None), channel, key), "resolution": None}
        dims = {"gain": None, "offset": u.channel_dimension(channel), "delay": u.TIME, "highpass": u.FREQUENCY}
        if "resolution" in spec:
            described["resolution"] = _quantity(r, spec.pop("resolution"), dims["offset"], key + ("resolution",))
            if described["resolution"] <= 0:
                raise r.error(
                    key + ("resolution",), f"expected a quantisation step > 0, got {described['resolution']:g}"
                )
        values = {field: _quantity(r, value, dims[field], key + (field,)) for field, value in spec.items()}
        for field in ("delay", "highpass"):
            if values.get(field, 0.0) < 0:
                raise r.error(key + (field,), f"expected a value >= 0, got {values[field]:g}")
        if values.get("gain", 1.0) <= 0:
            raise r.error(key + ("gain",), f"expected a gain > 0, got {values['gain']:g}")
        for field, why in meas.lacks(described["kind"]).items():
            if field in values:
                raise r.error(key + (field,), f"a sensor of kind = {described['kind']!r} has no {field}: {why}")
        sensors[channel] = meas.Sensor(**values, **described)
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


def _sensor_kind(r: _Reader, kind, channel: str, key: tuple) -> str | None:
    """A sensor's `kind` (`identify.measurement.KINDS`), checked against its channel."""
    if kind is None:
        return None
    why = meas.kind_problem(kind, channel)
    if why is not None:
        raise r.error(key + ("kind",), why)
    return kind


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


def _log_entry(r: _Reader, chain: fd.Chain, spec: Mapping, k: int, strict: bool, min_samples: int) -> LogSpec:
    key = ("logs", k)
    if "file" not in spec:
        raise r.error(key, 'missing file = "..." (the log, relative to this experiment file)')
    file = r.string(spec["file"], key + ("file",))
    written = r.path.parent / expand_user(file)
    bag = is_bag(written)
    problem = input_problem(written, bag)
    if problem is not None:
        raise r.error(
            key + ("file",), f"log file {absolute(written)} {problem} (paths are relative to {absolute(r.path.parent)})"
        )
    resolved = resolved_path(written)
    name = r.string(spec.get("name", resolved.stem), key + ("name",))
    role = spec.get("role", "fit")
    if role not in ROLES:
        raise r.error(key + ("role",), f'expected "fit" or "validation", got {_show(role)}')
    log_strict = spec.get("strict", strict)
    if not isinstance(log_strict, bool):
        raise r.error(key + ("strict",), f"expected true or false, got {_show(log_strict)}")
    decimal = spec.get("decimal", ".")
    if decimal not in DECIMALS:
        raise r.error(key + ("decimal",), f'expected "." or "," (the decimal mark), got {_show(decimal)}')
    if decimal != "." and resolved.suffix.lower() in MAT_SUFFIXES:
        raise r.error(key + ("decimal",), "applies to CSV logs; a .mat file holds binary numbers")

    timing = _bag_timing(r, spec, key, bag)
    columns = dict(r.table(spec.get("columns", {}), key + ("columns",)))
    if bag and "columns" not in spec:
        raise r.error(
            key,
            f"{resolved.name} is a ROS bag, whose messages carry no units; expected columns = {{ theta1 = {{ topic = "
            '"/joint_states", joint = "shoulder", field = "position", unit = "rad" }, ... } (see "ROS bags" in '
            "docs/experiment-format.md)",
        )
    if not bag and "columns" in spec and "time" not in columns:
        raise r.error(key + ("columns",), 'no time column; expected time = "<column> [s]" among the columns')
    for channel, source in columns.items():
        why = channel_problem(chain, channel)
        if why is not None:
            raise r.error(key + ("columns", channel), why)
        if bag and channel != "time" and not isinstance(source, Mapping):  # (a bag's time: load_log says why not)
            raise r.error(
                key + ("columns", channel),
                f'expected a table {{ topic = "...", field = "...", unit = "..." }} (a ROS bag), got {_show(source)}',
            )
        if not bag and not isinstance(source, str):
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
            decimal=decimal,
            **timing,
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
            # angles and modal coordinates (m, the mode's RMS deflection) take units, as
            # [noise] does ("2 mm" for q1_1); rates take SI numbers
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
        hold=_log_hold(r, spec.get("hold", "linear"), key + ("hold",), log, chain.n_links),
        hold_declared="hold" in spec,
    )


def _log_hold(r: _Reader, value, key: tuple, log, n_joints: int) -> str | tuple[str, ...]:
    """A log entry's `hold`: how its torque columns are read between samples, `"linear"`
    (the default) or `"zoh"` for all of them, or a table per column (`{ torque1 = "zoh" }`,
    the others linear); returned as `flexdyn.SampledTorque.hold` takes it (one per joint)."""
    kinds = ("linear", "zoh")
    if isinstance(value, str):
        if value not in kinds:
            raise r.error(key, f'expected "linear" or "zoh" (a digital controller\'s command), got {value!r}')
        return value
    holds = ["linear"] * n_joints
    for column, kind in r.table(value, key).items():
        if column not in log.inputs:
            inputs = ", ".join(sorted(log.inputs)) or "none"
            raise r.error(key + (column,), f"not an input column of this log; expected one of: {inputs}")
        if kind not in kinds:
            raise r.error(key + (column,), f'expected "linear" or "zoh", got {_show(kind)}')
        holds[u.channel_kind_index(column)[1] - 1] = kind
    return holds[0] if len(set(holds)) == 1 else tuple(holds)


def _bag_timing(r: _Reader, spec: Mapping, key: tuple, bag: bool) -> dict:
    """A log entry's `stamp`, `time_base` and `rate_hz` (ROS bags only), checked, as
    keywords of `load_log`."""
    given = {name: spec[name] for name in ("stamp", "time_base", "rate_hz") if name in spec}
    if given and not bag:
        raise r.error(key + (next(iter(given)),), "applies to ROS bags (a bag folder, .db3, .mcap or .bag file) only")
    if "stamp" in given and given["stamp"] not in STAMPS:
        raise r.error(
            key + ("stamp",),
            f'expected "header" (each message\'s header.stamp) or "receive" (when the bag recorded it), got '
            f"{_show(given['stamp'])}",
        )
    if "time_base" in given:
        r.string(given["time_base"], key + ("time_base",))
    if "rate_hz" in given:
        rate = r.number(given["rate_hz"], key + ("rate_hz",))
        if rate <= 0:
            raise r.error(key + ("rate_hz",), f"expected a sampling rate > 0 (Hz), got {rate!r}")
        if "time_base" in given:
            raise r.error(
                key + ("rate_hz",), "time_base is given too; expected one of them (a topic's stamps, or a uniform rate)"
            )
    return given


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


def _noise(r: _Reader, logs: list[LogSpec], table: Mapping, command: str | None = None) -> dict[str, float | None]:
    """`[noise]`; `command`: a `[controller]`'s command channel, an output of the fit too."""
    measured = sorted({c for entry in logs for c in entry.log.outputs})
    if command is not None and u.is_input(command):
        measured.append(command)
    noise: dict[str, float | None] = {c: None for c in measured}
    for channel, value in table.items():
        key = ("noise", channel)
        if channel != command and (u.channel_dimension(channel) is None or not u.is_output(channel)):
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
