"""The column mapping of a ROS bag log: channel -> `{ topic, field, joint, unit }`, and how its
topics are put on one time base (`stamp`, `time_base`, `rate_hz`).

A bag has no columns: each channel names the topic it is read from, the field of the
message holding the number (a path such as `data`, `wrench.force.z` or `values[2]`), for a
`sensor_msgs/msg/JointState` the joint by name, and the unit, which a ROS message does
not carry (as for a `.mat` variable). Problems raise `LogError` naming the file and the
mapping entry (`channel=`, so that an experiment file points at that entry's line).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path

from . import units as u
from .columns import LogError
from .message_fields import parse_field_path

#: the message type whose values are addressed by joint name
JOINT_STATE = "sensor_msgs/msg/JointState"

#: a JointState's fields -> the dimension of the channels each may map to (None: no
#: channel of the model is a rate, so a velocity has nowhere to go)
JOINT_STATE_FIELDS = {"position": u.ANGLE, "velocity": None, "effort": u.TORQUE}

#: which time a message is sampled at: its `header.stamp`, or when the bag recorded it
STAMPS = ("header", "receive")

_KEYS = ("topic", "field", "joint", "unit")

_EXAMPLE = '{ topic = "/joint_states", joint = "shoulder", field = "position", unit = "rad" }'


@dataclasses.dataclass(frozen=True)
class BagSource:
    """Where a channel of a bag log is read: `topic`, `field` (as written) and its parsed
    `path`, `joint` (JointState topics only), `unit` (as written)."""

    channel: str
    topic: str
    field: str
    path: tuple[str | int, ...]
    joint: str | None
    unit: str

    def describe(self) -> str:
        """E.g. `/joint_states position of joint 'shoulder' [rad]`, for messages and `Log.sources`."""
        joint = f" of joint {self.joint!r}" if self.joint is not None else ""
        return f"{self.topic} {self.field}{joint} [{self.unit}]"


@dataclasses.dataclass(frozen=True)
class BagTiming:
    """How a bag log's topics become one series: `stamp` (`'header'`, `'receive'`, or None:
    each message's header stamp where its type has a header, else its receive time), and the
    time base: the stamps of topic `time_base`, or a uniform `rate_hz` (Hz), or None (the one
    topic the channels are read from)."""

    stamp: str | None = None
    time_base: str | None = None
    rate_hz: float | None = None


def parse_bag_mapping(path: Path, columns, where: str) -> list[BagSource]:
    """The `BagSource` of each channel of `columns` (channel -> table), checked: channel
    names, keys, field paths, units, JointState fields against the channel's dimension, and
    no two channels reading the same number."""
    if not isinstance(columns, Mapping) or not columns:
        raise LogError(
            f"{path}: a ROS bag log needs a column mapping naming each channel's topic, field and unit; expected "
            f"columns = {{ theta1 = {_EXAMPLE}, ... }}"
        )
    sources, seen = [], {}
    for channel, spec in columns.items():
        source = _parse_entry(path, channel, spec, f"{where}.{channel}")
        key = (source.topic, source.path, source.joint)
        if key in seen:
            raise LogError(
                f"{path}: {where}: channels {seen[key]!r} and {channel!r} both read {source.describe()}",
                channel=channel,
            )
        seen[key] = channel
        sources.append(source)
    return sources


def _parse_entry(path: Path, channel: str, spec, key: str) -> BagSource:
    def error(message: str) -> LogError:
        return LogError(f"{path}: {key}: {message}", channel=channel)

    if channel == "time":
        raise error(
            "a bag's times are its messages' stamps, not a channel; remove time, and choose the stamps with "
            'stamp = "header" or "receive" and the time base with time_base = "<topic>" or rate_hz = ...'
        )
    dim = u.channel_dimension(channel)
    if dim is None:
        raise error(f"{channel!r} is not a channel; expected one of {u.CHANNEL_PATTERNS}")
    if not isinstance(spec, Mapping):
        raise error(f"expected a table {_EXAMPLE}, got {spec!r}")
    extra = [k for k in spec if k not in _KEYS]
    if extra:
        raise error(f"unknown key {extra[0]!r}; expected topic, field, unit and, for a {JOINT_STATE}, joint")
    for name in ("topic", "field", "unit"):
        if name not in spec:
            raise error(f"missing {name}; expected a table {_EXAMPLE}")
    for name in _KEYS:
        if name in spec and (not isinstance(spec[name], str) or not spec[name].strip()):
            raise error(f"{name}: expected a non-empty string, got {spec[name]!r}")
    topic, field, joint, unit = (spec.get(name) for name in _KEYS)
    try:
        field_path = parse_field_path(field)
    except ValueError as e:
        raise error(f"field: {e}") from None
    if joint is not None:
        if field not in JOINT_STATE_FIELDS:
            raise error(
                f"field {field!r}: a {JOINT_STATE}'s joint values are in position, velocity or effort; "
                "expected one of those with joint"
            )
        want = JOINT_STATE_FIELDS[field]
        if want is None:
            raise error(
                "a joint's velocity is a rate, and no channel of the model is one (the model predicts angles and is "
                "driven by torques); map position to theta<i> or alpha<i>, effort to torque<i>"
            )
        if want != dim:
            raise error(
                f"{channel} is {u.article(dim)}, but a {JOINT_STATE}'s {field} is {u.article(want)}; map "
                f"{field} to {'theta<i>, alpha<i> or phi<i>' if want == u.ANGLE else 'torque<i>'}"
            )
    if u.normalise_unit(unit) is None:
        raise error(f"unit: unknown unit {unit!r}; known units: {u.known_units()}")
    return BagSource(channel, topic.strip(), field.strip(), field_path, joint, unit)


def check_timing(path: Path, timing: BagTiming) -> None:
    """Raise `LogError` for a `stamp` that is not one of `STAMPS`, both a `time_base` and a
    `rate_hz`, or a rate that is not a positive number."""
    if timing.stamp is not None and timing.stamp not in STAMPS:
        raise LogError(
            f'{path}: stamp = {timing.stamp!r}; expected "header" (each message\'s header.stamp) or "receive" '
            "(when the bag recorded it), or no stamp (the header where a message has one, else the receive time)"
        )
    if timing.time_base is not None and timing.rate_hz is not None:
        raise LogError(
            f"{path}: both time_base = {timing.time_base!r} and rate_hz = {timing.rate_hz!r}; expected one "
            "(a topic's stamps, or a uniform rate)"
        )
    if timing.time_base is not None and (not isinstance(timing.time_base, str) or not timing.time_base.strip()):
        raise LogError(f'{path}: time_base = {timing.time_base!r}; expected a topic name like "/joint_states"')
    rate = timing.rate_hz
    if rate is not None and (isinstance(rate, bool) or not isinstance(rate, int | float) or not 0 < rate < math.inf):
        raise LogError(f"{path}: rate_hz = {rate!r}; expected a sampling rate > 0 (Hz)")
