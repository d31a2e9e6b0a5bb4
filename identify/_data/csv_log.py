"""The CSV reader of `load_log`: delimiters, comment headers, decimal commas, numbers by line and column."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np

from . import units as u
from .columns import (
    LogError,
    _calibration_note,
    _check_samples,
    _check_time,
    _relative_time,
    _resolve_unit,
    _to_si,
    _Wanted,
    _warn_if_cut_off,
    _warn_if_turns,
)


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
