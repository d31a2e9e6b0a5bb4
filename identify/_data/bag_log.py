"""The ROS bag reader of `load_log`: ROS 2 bags (a bag folder, or one `.db3` or `.mcap` storage
file) and ROS 1 `.bag` files, read with `rosbags` (pure Python, no ROS installation), their
topics resampled onto one time base.

Each channel is one number per message of one topic (`bag_columns.BagSource`), sampled at
the message's header stamp or its receive time (`BagTiming.stamp`). Topics recorded at
different rates are put on one time base (a topic's stamps, or a uniform rate) by linear
interpolation inside the span every topic covers (`resample`): no value is extrapolated.
Every problem raises `LogError` naming the bag, the topic, the field and the message
(counted from 1 in the order the bag recorded them); the bag is opened read-only. A bag
split while recording (a folder whose `metadata.yaml` lists several storage files) is read
whole, file after file in the order listed; a storage file missing from it, a damaged record
and a message that cannot be deserialised are errors, not a part of the bag left out (one
storage file of a split bag given on its own is read alone, with a warning).
"""

from __future__ import annotations

import warnings
from pathlib import Path, PurePath

import numpy as np

from . import resample
from .bag_columns import JOINT_STATE, BagSource, BagTiming, check_timing
from .columns import GAP_FACTOR, LogError, _calibration_note, _resolve_unit, _to_si, _Wanted, _warn_if_turns
from .message_fields import FieldError, field_number, header_stamp_ns, joint_number

#: storage files of a bag (`.db3`: ROS 2 sqlite3, `.mcap`: ROS 2 MCAP, `.bag`: ROS 1)
BAG_SUFFIXES = (".bag", ".db3", ".mcap")


def is_bag(path: Path) -> bool:
    """True for a bag file (`BAG_SUFFIXES`) or a ROS 2 bag folder (one with `metadata.yaml`)."""
    return path.suffix.lower() in BAG_SUFFIXES or (path.is_dir() and (path / "metadata.yaml").is_file())


def _read_bag(path: Path, sources: list[BagSource], cals, strict: bool, context: str, timing: BagTiming):
    check_timing(path, timing)
    units = {}
    for s in sources:
        where = f"{path}: {context}.{s.channel} ({s.describe()})"
        units[s.channel] = _resolve_unit(path, _Wanted(s.channel, s.describe(), s.unit), None, where, cals)
    reader = _open(path)
    try:
        topics = reader.topics
        needed = _check_topics(path, sources, topics, timing, context)
        stamps, kinds, raw = _read_messages(path, reader, sources, needed, timing, context)
    finally:
        reader.close()
    ignored = sorted(set(topics) - set(needed))
    if strict and ignored:
        raise LogError(
            f"{path}: topic(s) {ignored} are not mapped to any channel (strict = true); map them in columns, "
            "or remove strict"
        )
    base = None if timing.rate_hz is not None else timing.time_base or needed[0]  # (one topic: checked)
    ref, t_relative, values = _resampled(path, sources, stamps, raw, base, timing.rate_hz)
    onto = f"{timing.rate_hz:g} Hz" if base is None else f"the stamps of {base}"
    channels, out_sources = {}, {}
    for s in sources:
        unit, cal = units[s.channel]
        channels[s.channel] = _to_si(values[s.channel], unit, cal, s.channel)
        _warn_if_turns(path, f"topic {s.topic!r}, {s.field}", s.channel, channels[s.channel], unit)
        note = "header stamps" if kinds[s.topic] == "header" else "receive times"
        note += "" if s.topic == base else f", interpolated onto {onto}"
        out_sources[s.channel] = f"{s.describe()} ({note})" + _calibration_note(cal)
    t = ref / 1e9 + t_relative
    return t, t_relative, channels, out_sources, ignored


def _resampled(path: Path, sources, stamps: dict, raw: dict, base: str | None, rate_hz: float | None):
    """`(ref, t, values)`: the time base (`ref` ns, `t` s from it) and each channel's values on
    it: the stamps of topic `base` (its own values, exact) or a uniform `rate_hz`, inside the
    span every topic read covers; a single topic read on its own stamps keeps all of them."""
    if len(stamps) == 1 and base is not None:
        start, end = int(stamps[base][0]), int(stamps[base][-1])
        ref, t = start, (stamps[base] - start) / 1e9
    else:
        _check_overlap(path, stamps)
        start, end = resample.common_span(stamps)
        ref, t = resample.base_times(stamps, base, rate_hz)
        _warn_of_gaps(path, stamps, base)
    values = {}
    for s in sources:
        if s.topic == base:
            values[s.channel] = raw[s.channel][(stamps[base] >= start) & (stamps[base] <= end)]
        else:
            values[s.channel] = resample.interpolate(t, ref, stamps[s.topic], raw[s.channel])
    return ref, t, values


def _open(path: Path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    _check_storage_files(path)
    # a bag without message definitions (ROS 2 sqlite3 bags before Iron) is read with
    # Humble's standard types
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as e:  # rosbags raises several types for a file that is not a bag
        raise LogError(f"{path}: not a readable ROS bag ({type(e).__name__}: {e})") from None
    return reader


def _storage_files(folder: Path) -> list[str] | None:
    """The storage files a ROS 2 bag folder's `metadata.yaml` lists (`relative_file_paths`, by
    name, as rosbags finds them in the folder), in its order; None where it cannot be read
    (rosbags then says why)."""
    try:
        from ruamel.yaml import YAML  # (rosbags' own reader of this file; without it, rosbags' checks)

        info = YAML(typ="safe").load((folder / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        return [PurePath(str(name)).name for name in info["relative_file_paths"]]
    except Exception:
        return None


def _check_storage_files(path: Path) -> None:
    """A bag folder holds every storage file its `metadata.yaml` lists (a bag split while
    recording has one per part: `LogError` naming those missing); a storage file given on
    its own that is one part of a split bag is read alone, with a warning naming its folder."""
    if path.is_dir():
        files = _storage_files(path) or []
        missing = [name for name in files if not (path / name).exists()]
        if missing:
            raise LogError(
                f"{path}: storage file(s) {', '.join(missing)} listed in its metadata.yaml are missing from the "
                f"folder; expected every file of the bag ({', '.join(files)}): a bag split while recording needs "
                "all its parts"
            )
    elif path.suffix.lower() in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
        files = _storage_files(path.parent) or []
        if len(files) > 1 and path.name in files:
            warnings.warn(
                f"{path} is one of the {len(files)} storage files of the bag {path.parent} ({', '.join(files)}): "
                "only its own messages are read; give the bag's folder as the log to read them all",
                UserWarning,
                stacklevel=4,
            )


def _listing(topics) -> str:
    return ", ".join(f"{name!r} ({info.msgtype}, {info.msgcount} messages)" for name, info in topics.items())


def _check_topics(path: Path, sources: list[BagSource], topics, timing: BagTiming, context: str) -> list[str]:
    """The topics to read (the channels' and the time base's), checked against the bag."""
    for s in sources:
        mapped = f"(mapped by {context}.{s.channel})"
        if s.topic not in topics:
            raise LogError(f"{path}: no topic {s.topic!r} {mapped}; the bag has {_listing(topics)}", channel=s.channel)
        msgtype = topics[s.topic].msgtype
        if msgtype is None:
            raise LogError(
                f"{path}: topic {s.topic!r} {mapped} holds messages of several types; expected one type per topic",
                channel=s.channel,
            )
        if s.joint is not None and msgtype != JOINT_STATE:
            raise LogError(
                f"{path}: topic {s.topic!r} {mapped} is {msgtype}, not {JOINT_STATE}; joint applies to joint "
                f"states only: remove it and address the number by its field path",
                channel=s.channel,
            )
    needed = list(dict.fromkeys(s.topic for s in sources))
    if timing.time_base is not None:
        if timing.time_base not in topics:
            raise LogError(f"{path}: time_base = {timing.time_base!r}: no such topic; the bag has {_listing(topics)}")
        needed = list(dict.fromkeys([*needed, timing.time_base]))
    elif timing.rate_hz is None and len(needed) > 1:
        raise LogError(
            f"{path}: the channels are read from {len(needed)} topics ({', '.join(needed)}), each with its own "
            f'times; expected a time base to resample them onto: time_base = "{needed[0]}" (that topic\'s stamps) '
            "or rate_hz = ... (a uniform rate)"
        )
    return needed


def _read_messages(path: Path, reader, sources, needed, timing: BagTiming, context: str):
    """Per topic its stamps (int64 ns) and which (`'header'`/`'receive'`); per channel its raw
    values (as in the message)."""
    by_topic = {topic: [s for s in sources if s.topic == topic] for topic in needed}
    stamps: dict[str, list[int]] = {topic: [] for topic in needed}
    values: dict[str, list[float]] = {s.channel: [] for s in sources}
    kinds: dict[str, str] = {}
    connections = [c for c in reader.connections if c.topic in by_topic]
    counts = {topic: info.msgcount for topic, info in reader.topics.items()}
    for connection, k, received, data in _messages(path, reader, connections):
        topic = connection.topic
        at = f"{path}: topic {topic!r}, message {k}" + (f" of {counts[topic]}" if counts[topic] >= k else "")
        try:
            message = reader.deserialize(data, connection.msgtype)
        except Exception as e:  # rosbags raises several types for bytes that are not the message
            raise LogError(_not_deserialised(at, connection.msgtype, received, data, e)) from None
        header = header_stamp_ns(message)
        if topic not in kinds:
            kinds[topic] = _stamp_kind(path, topic, connection.msgtype, header, timing)
        stamps[topic].append(header if kinds[topic] == "header" else received)
        for s in by_topic[topic]:
            try:
                if connection.msgtype == JOINT_STATE:
                    values[s.channel].append(_joint_value(message, s))
                else:
                    values[s.channel].append(field_number(message, s.path))
            except FieldError as e:
                raise LogError(
                    f"{at}, field {s.field!r} (mapped by {context}.{s.channel}): {e}", channel=s.channel
                ) from None
    out = {}
    for topic in needed:
        if not stamps[topic]:
            raise LogError(f"{path}: topic {topic!r} has no messages; expected one per sample")
        out[topic] = np.asarray(stamps[topic], dtype=np.int64)
        _check_stamps(path, topic, out[topic], kinds[topic])
    raw = {s.channel: np.asarray(values[s.channel], dtype=float) for s in sources}
    for s in sources:
        bad = ~np.isfinite(raw[s.channel])
        if bad.any():
            j = int(np.argmax(bad))
            raise LogError(
                f"{path}: topic {s.topic!r}, message {j + 1} of {len(raw[s.channel])}, field {s.field!r}: "
                f"{raw[s.channel][j]} in {s.channel}; expected a finite number",
                channel=s.channel,
            )
    return out, kinds, raw


def _messages(path: Path, reader, connections):
    """`reader.messages` of `connections` as `(connection, k, received, data)`, `k` the
    message's number in its topic (from 1), `received` its receive time (ns). A damaged
    record in the bag's storage raises `LogError` naming the last message read (not
    rosbags' own error, whatever its type), and so does a topic whose receive times go back
    (the storage files of a split bag listed out of recording order)."""
    read: dict[str, tuple[int, int]] = {}  # topic -> (messages read, the last one's receive time)
    last = None  # (topic, k, received) of the last message read
    stream = reader.messages(connections=connections)
    while True:
        try:
            connection, received, data = next(stream)
        except StopIteration:
            return
        except Exception as e:  # rosbags raises several types (and struct's, zstd's) for a damaged record
            raise LogError(
                f"{path}: a damaged record in the bag's storage, found {_last_read(last)} ({type(e).__name__}: "
                f"{e}); expected an intact bag: this copy is cut short or corrupt"
            ) from None
        topic = connection.topic
        k, before = read.get(topic, (0, received))
        if received < before:
            raise LogError(
                f"{path}: topic {topic!r}, message {k + 1}: received at {_seconds(received)}, before message {k} "
                f"({_seconds(before)}); expected the messages in the order received: a bag split while recording "
                "is read file after file as its metadata.yaml lists them (relative_file_paths), which must be "
                "the order they were recorded in"
            )
        read[topic], last = (k + 1, received), (topic, k + 1, received)
        yield connection, k + 1, received, data


def _last_read(last: tuple[str, int, int] | None) -> str:
    if last is None:
        return "before any message was read"
    topic, k, received = last
    return f"after reading topic {topic!r}, message {k} (received at {_seconds(received)})"


def _not_deserialised(at: str, msgtype: str, received: int, data: bytes, e: Exception) -> str:
    return (
        f"{at} (received at {_seconds(received)}, {len(data)} bytes): not a readable {msgtype} "
        f"({type(e).__name__}: {e}); expected the bytes of a {msgtype} as its definition in the bag lays them "
        "out: the message is cut short or corrupt, or was recorded with another definition of the type"
    )


def _joint_value(message, s: BagSource) -> float:
    if s.joint is None:
        raise FieldError(
            f"a {JOINT_STATE} holds several joints, addressed by name; expected joint = one of "
            f"{list(message.name)} and field = position or effort"
        )
    return joint_number(message, s.joint, s.field)


def _stamp_kind(path: Path, topic: str, msgtype: str, header: int | None, timing: BagTiming) -> str:
    if timing.stamp == "receive":
        return "receive"
    if header is None:
        if timing.stamp == "header":
            raise LogError(
                f'{path}: topic {topic!r} is {msgtype}, which has no header stamp; stamp = "header" needs one on '
                'every topic read: use stamp = "receive", or leave stamp out (header stamps where a message has '
                "one, else the receive time)"
            )
        return "receive"
    return "header"


def _seconds(ns: int) -> str:
    return f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d} s"


def _check_stamps(path: Path, topic: str, stamps: np.ndarray, kind: str) -> None:
    dt = np.diff(stamps)
    bad = dt <= 0
    if not bad.any():
        return
    j = int(np.argmax(bad)) + 1
    what = "the same as" if dt[j - 1] == 0 else "before"
    hint = (
        '; a publisher that leaves header.stamp unset, or stamps out of order, needs stamp = "receive"'
        if kind == "header"
        else ""
    )
    raise LogError(
        f"{path}: topic {topic!r}, message {j + 1} of {len(stamps)}: its {kind} stamp {_seconds(int(stamps[j]))} is "
        f"{what} message {j}'s ({_seconds(int(stamps[j - 1]))}); expected strictly increasing stamps{hint}"
    )


def _check_overlap(path: Path, stamps: dict[str, np.ndarray]) -> None:
    for topic, s in stamps.items():
        if len(s) < 2:
            raise LogError(f"{path}: topic {topic!r} has {len(s)} message; expected at least 2 to interpolate between")
    start, end = resample.common_span(stamps)
    if start >= end:
        first = min(int(s[0]) for s in stamps.values())
        spans = ", ".join(f"{topic!r} {_from(s[0], first)}-{_from(s[-1], first)} s" for topic, s in stamps.items())
        raise LogError(
            f"{path}: the topics do not overlap in time ({spans}, from the earliest stamp); expected a common span "
            "to resample them onto"
        )


def _from(ns, first: int) -> str:
    return f"{(int(ns) - first) / 1e9:.6g}"


def _warn_of_gaps(path: Path, stamps: dict[str, np.ndarray], base: str | None) -> None:
    """Warn of a topic interpolated across a gap (values made up between two distant messages);
    the base topic's own gaps show in the log's `Sampling`."""
    start, end = resample.common_span(stamps)
    for topic, s in stamps.items():
        if topic == base:
            continue
        found, median = resample.gaps(s, start, end)
        if found.size:
            dt = np.diff(s)
            k = int(found[np.argmax(dt[found])])
            warnings.warn(
                f"{path}: topic {topic!r} has {found.size} gap(s) longer than {GAP_FACTOR:g} x its median interval "
                f"({median / 1e9:.3g} s), the longest {dt[k] / 1e9:.3g} s after message {k + 1}; the time base's "
                "samples inside are interpolated linearly across it",
                UserWarning,
                stacklevel=4,
            )
