"""Numbers inside a deserialized ROS message: a field path (`data`, `wrench.force.z`,
`values[2]`), a joint of a `sensor_msgs/msg/JointState` by name, and the header stamp.

The messages are those `rosbags` deserializes: dataclasses (one per message type) whose
arrays of numbers are NumPy arrays and whose other sequences are lists. Each lookup
raises `FieldError` saying what it found and what was expected; the bag reader adds the
file, topic and message number.
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np

#: one dotted piece of a field path: a name and any number of `[index]`
_PIECE = re.compile(r"(?P<name>[A-Za-z_][A-Za-z0-9_]*)(?P<indexes>(?:\[\d+\])*)")


class FieldError(ValueError):
    """A field path does not lead to one number in a message (the text says why)."""


def parse_field_path(text: str) -> tuple[str | int, ...]:
    """`'a.b[2].c'` -> `('a', 'b', 2, 'c')`. Raises `ValueError` saying what a path looks like."""
    pieces = text.strip().split(".") if isinstance(text, str) else [""]
    path: list[str | int] = []
    for piece in pieces:
        m = _PIECE.fullmatch(piece.strip())
        if m is None:
            raise ValueError(
                f"{text!r} is not a field path; expected field names separated by dots, each with an optional "
                "[index] into an array, like 'data', 'wrench.force.z' or 'values[2]'"
            )
        path.append(m["name"])
        path += [int(i) for i in re.findall(r"\d+", m["indexes"])]
    return tuple(path)


def field_number(message, path: tuple[str | int, ...]) -> float:
    """The number at `path` in `message`; raises `FieldError` for a missing field, an index
    out of range, or a value that is not one number (text, a message, an array, a boolean)."""
    value, walked = message, ""
    for part in path:
        if isinstance(part, int):
            if not _is_sequence(value):
                raise FieldError(f"{walked!r} is {_describe(value)}, not an array; remove the index [{part}]")
            if part >= len(value):
                raise FieldError(f"{walked!r} has {len(value)} value(s); expected an index below {len(value)}")
            value, walked = value[part], f"{walked}[{part}]"
        else:
            if not dataclasses.is_dataclass(value) or part not in _fields(value):
                owner = f"{walked!r} ({_describe(value)})" if walked else _describe(value)
                fields = f"; its fields are {_fields(value)}" if dataclasses.is_dataclass(value) else ""
                raise FieldError(f"{owner} has no field {part!r}{fields}")
            value, walked = getattr(value, part), f"{walked}.{part}" if walked else part
    return _number(value, walked)


def joint_number(message, joint: str, field: str) -> float:
    """The value of `joint` in a `sensor_msgs/msg/JointState`'s `field` (`position`,
    `velocity`, `effort`): looked up by name in each message, since a publisher may order or
    omit joints differently from one message to the next."""
    names = list(message.name)
    if names.count(joint) != 1:
        if joint in names:
            raise FieldError(f"joint {joint!r} appears {names.count(joint)} times in name {names}; expected once")
        raise FieldError(f"no joint {joint!r}; its joints are {names}")
    values = getattr(message, field)
    if len(values) != len(names):
        empty = " (the publisher leaves it empty)" if len(values) == 0 else ""
        raise FieldError(
            f"{field} has {len(values)} value(s) for {len(names)} joint name(s){empty}; expected one per joint"
        )
    return _number(values[names.index(joint)], f"{field}[{joint!r}]")


def header_stamp_ns(message) -> int | None:
    """`header.stamp` in integer nanoseconds, or None for a message without a header."""
    header = getattr(message, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None or not hasattr(stamp, "sec") or not hasattr(stamp, "nanosec"):
        return None
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def message_type(message) -> str:
    """The ROS type of a deserialized message, e.g. `'std_msgs/msg/Float64'`."""
    return getattr(message, "__msgtype__", type(message).__name__)


def _fields(message) -> list[str]:
    return [f.name for f in dataclasses.fields(message) if not f.name.startswith("__")]  # (not `__msgtype__`)


def _is_sequence(value) -> bool:
    return isinstance(value, list | tuple) or (isinstance(value, np.ndarray) and value.ndim == 1)


def _describe(value) -> str:
    if isinstance(value, bool | np.bool_):
        return "a boolean"
    if isinstance(value, str):
        return "text"
    if dataclasses.is_dataclass(value):
        return f"a {message_type(value)} message"
    if _is_sequence(value):
        return f"an array of {len(value)} value(s)"
    return f"a {type(value).__name__}"


def _number(value, walked: str) -> float:
    if isinstance(value, bool | np.bool_) or not isinstance(value, int | float | np.integer | np.floating):
        hint = ""
        if dataclasses.is_dataclass(value):
            fields = _fields(value)
            hint = f" with fields {fields}: address one, e.g. '{walked}.{fields[0]}'" if fields else ""
        elif _is_sequence(value):
            hint = f": address one element, e.g. '{walked}[0]'" if len(value) else ""
        raise FieldError(f"{walked!r} is {_describe(value)}{hint}; expected a number")
    return float(value)
