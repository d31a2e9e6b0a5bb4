"""The CSV reader of `load_log`: the header row and its columns' mapping, then the rows
(`csv_rows`), checked and converted to SI by line and column."""

from __future__ import annotations

import csv
from pathlib import Path

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
    _warn_if_turns,
)
from .csv_numbers import DECIMALS, is_number
from .csv_rows import Columns, read_rows
from .csv_text import find_header, open_bytes


def _read_csv(path: Path, wanted, cals, strict, context, decimal: str = ".", *, fast: bool = True):
    """`load_log`'s CSV reader: times, relative times, SI channels, their sources and the
    ignored columns. `decimal`: the numbers' decimal mark, "." or ","; `fast`: `read_rows`'s."""
    if decimal not in DECIMALS:
        raise LogError(f'{path}: decimal = {decimal!r}; expected "." or "," (the numbers\' decimal mark)')
    with open_bytes(path) as stream:
        try:
            return _read_open_csv(path, stream, wanted, cals, strict, context, decimal, fast)
        except OSError as e:
            raise LogError(f"{path}: log file cannot be read ({e.strerror})") from None


def _read_open_csv(path: Path, stream, wanted, cals, strict, context, decimal: str, fast: bool):
    found = find_header(path, stream)
    if decimal == "," and found.delimiter == ",":
        raise LogError(
            f'{path}, line {found.line}: decimal = "," but the cells are separated by commas; a log with '
            "decimal commas separates its cells by semicolons or tabs"
        )
    header, names, file_units = _header_cells(path, found)
    hline = found.line
    used, ignored = _used_columns(path, hline, header, names, file_units, wanted, cals, strict, context)
    stream.seek(found.rows_offset)
    values, line_of = read_rows(path, stream, Columns(hline, header, found.delimiter, decimal, list(used)), fast=fast)

    def where_for(c):
        return lambda j: f"line {line_of(j)}, column {c} ({header[c - 1]!r})"

    channels, sources, time_column = {}, {}, None
    for k, (c, (w, unit, cal)) in enumerate(used.items()):
        raw = values[k]
        _check_samples(path, w.channel, raw, where_for(c))
        if w.channel == "time":
            t_relative, time_column = _relative_time(raw, unit), c
        channels[w.channel] = _to_si(raw, unit, cal, w.channel, out=raw)  # (the file's values are not kept)
        _warn_if_turns(path, f"column {c} ({header[c - 1]!r})", w.channel, channels[w.channel], unit)
        sources[w.channel] = f"column {c} {header[c - 1]!r}" + _calibration_note(cal)
    t = channels.pop("time")
    if t.shape[0] >= 2:
        _check_time(path, t_relative, where_for(time_column), t)
    sources.pop("time")
    return t, t_relative, channels, sources, ignored


def _header_cells(path: Path, found) -> tuple[list[str], list[str], list[str | None]]:
    """The header row's cells, their names and their units (None where a cell has none)."""
    hline, text = found.line, found.text
    header = [h.strip() for h in next(csv.reader([text], delimiter=found.delimiter))]
    if all(is_number(h) for h in header):
        raise LogError(
            f"{path}, line {hline}: the first row is all numbers ({text.strip()[:60]!r}): the file seems "
            "to have no header row; add one naming each column with its unit, like 'time [s],theta1 [deg],tip1 [mm]'"
        )
    if len(header) == 1 and len(text.split()) > 1 and text.count("[") > 1:
        raise LogError(
            f"{path}, line {hline}: one column {text.strip()[:60]!r}, its cells separated by spaces; "
            "expected cells separated by commas, semicolons or tabs"
        )
    names, file_units = [], []
    for c, cell in enumerate(header, start=1):
        try:
            name, unit = u.split_header(cell)
        except ValueError as e:
            raise LogError(f"{path}, line {hline}, column {c}: {e}") from None
        names.append(name)
        file_units.append(unit)
    seen: dict[str, int] = {}
    for c, name in enumerate(names, start=1):
        if name and name in seen:
            raise LogError(f"{path}, line {hline}: columns {seen[name]} and {c} are both named {name!r}")
        seen[name] = c
    return header, names, file_units


def _used_columns(path: Path, hline: int, header, names, file_units, wanted, cals, strict, context):
    """Column (1-based) -> (wanted channel, canonical unit, calibration) of every mapped column,
    and the header cells of the columns no channel uses. `wanted` None maps the columns named
    like channels."""
    seen = {name: c for c, name in enumerate(names, start=1)}
    if wanted is None:
        wanted = _channels_by_name(path, hline, header, names)
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
    return used, ignored


def _channels_by_name(path: Path, hline: int, header, names) -> list[_Wanted]:
    """The identity mapping: every column named like a channel; a near miss (`tip_1`) is an error."""
    wanted = [_Wanted(n, n, None) for n in names if u.channel_dimension(n) is not None]
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
    return wanted
