"""A CSV log's data rows, read in chunks: a fast vectorised reader, and the careful line-by-line one
that names the line and column of every problem.

A log of hundreds of megabytes read line by line (a `csv` reader and a `float` per cell) takes
minutes and several times the file's size in Python objects. Here the file is read in chunks of
`CHUNK_BYTES` ending at a line end. A chunk of plain rows (no quotes, comments, blank lines or
text in a mapped column) is parsed with only the mapped columns, after a
vectorised count of every row's cells (PyArrow's CSV reader parses them where installed,
`np.loadtxt` else); any other chunk, or one the fast reader refuses, is read
by the careful reader, which either names the first problem (file, line, column, the cell) or
reads what the fast reader could not (quoted cells, comment lines). Both accept exactly the
grammar of `csv_numbers`, so the result does not depend on which read a chunk. Only the mapped
columns' values are kept: 8 bytes per cell.
"""

from __future__ import annotations

import bisect
import csv
import dataclasses
import os
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np

from .columns import LogError
from .csv_numbers import number_problem, parse_number
from .csv_text import decode, skipped, split_lines

#: Bytes read at a time (the chunk ends at the last line end in it).
CHUNK_BYTES = 8 << 20


#: Memory the loader needs per mapped cell, in units of its 8-byte value: the values (converted
#: to SI in place), the relative times and the checks' temporaries (measured: 1.7).
MEMORY_PER_VALUE = 2


#: A chunk holding any of these is read by the careful reader: quoted cells, comments, NUL.
_CAREFUL = (b'"', b"#", b"\0")


#: Nor does the fast reader read a line that starts or ends in white space (the careful reader
#: strips it) or a blank line.
_BLANK = np.array([ord(" "), ord("\t"), ord("\n")], dtype=np.uint8)


@dataclasses.dataclass(frozen=True)
class Columns:
    """What to read: the header row (its line and cells), the cells' separator and decimal mark,
    and the (1-based) columns whose values are kept."""

    header_line: int
    header: list[str]
    delimiter: str
    decimal: str
    used: list[int]


class RowLines:
    """The line number (1-based) of each data row, kept by chunk: a run of consecutive lines
    as its first line, a chunk with skipped lines as an array."""

    def __init__(self):
        self._starts: list[int] = []  # first row of each chunk
        self._firsts: list[int] = []  # its line
        self._lines: list[np.ndarray | None] = []

    def add(self, first_row: int, first_line: int, lines: np.ndarray | None) -> None:
        self._starts.append(first_row)
        self._firsts.append(first_line)
        self._lines.append(lines)

    def __call__(self, j: int) -> int:
        k = bisect.bisect_right(self._starts, j) - 1
        lines = self._lines[k]
        return self._firsts[k] + j - self._starts[k] if lines is None else int(lines[j - self._starts[k]])


@dataclasses.dataclass(frozen=True)
class _Chunk:
    """A chunk's rows: the mapped cells' values (rows, columns), the rows' lines (None: every
    line of the chunk, in order), their lengths (white space stripped), the last row's text,
    and the chunk's count of lines."""

    values: np.ndarray
    lines: np.ndarray | None
    lengths: np.ndarray
    last: str
    n_lines: int


def read_rows(path: Path, stream: BinaryIO, columns: Columns, *, fast: bool = True) -> tuple[np.ndarray, RowLines]:
    """The mapped columns' values, shape (len(columns.used), rows) (each column contiguous),
    and the rows' lines (`RowLines`), from `stream` positioned after the header row.
    `fast=False` reads every chunk with the careful reader, line by line (as the loader did
    before the fast reader; kept for comparison). Raises `LogError` naming the line and
    column of a problem."""
    out, rows = np.empty((len(columns.used), 0)), RowLines()
    n_rows, line = 0, columns.header_line + 1
    shortest, last, last_line, ends_in_newline = np.inf, "", 0, True
    for data, at_end in _chunks(stream):
        chunk = (_fast(data, columns) if fast else None) or _careful(path, data, line, at_end, columns)
        n = chunk.values.shape[0]
        if n:
            if n_rows + n > out.shape[1]:
                out = _grown(out, n_rows, n_rows + n if n_rows else _expected_rows(path, stream, len(data) / n, out))
            out[:, n_rows : n_rows + n] = chunk.values.T
            rows.add(n_rows, line, chunk.lines)
            shortest = min(shortest, len(last) if last_line else np.inf, _min(chunk))
            last, last_line = chunk.last, line + chunk.n_lines - 1 if chunk.lines is None else int(chunk.lines[-1])
            n_rows += n
        line += chunk.n_lines
        ends_in_newline = data.endswith((b"\n", b"\r"))
    if not n_rows:
        raise LogError(
            f"{path}: no data rows after the header on line {columns.header_line}; expected one row per sample"
        )
    if not ends_in_newline and last_line == line - 1 and n_rows >= 3:
        _warn_if_cut_off(path, last_line, last, shortest)
    return out[:, :n_rows], rows


def _grown(out: np.ndarray, n_rows: int, capacity: int) -> np.ndarray:
    """`out` with room for `capacity` rows (at least 1.5 times its own), its first `n_rows` kept.
    Pages of `np.empty` not written yet take no memory, so room to spare costs nothing."""
    bigger = np.empty((out.shape[0], max(capacity, int(1.5 * out.shape[1]))))
    bigger[:, :n_rows] = out[:, :n_rows]
    return bigger


def _warn_if_cut_off(path: Path, line: int, text: str, shortest: float) -> None:
    """Warn when the file ends, without a newline, in a data row shorter than every other: the
    mark of a write interrupted mid-number (`1.9950,-51.` reads as -51.0 deg, whatever digits
    the sample had left). A file that merely lacks the final newline has a last row as long as
    the others."""
    if len(text) < shortest:
        warnings.warn(
            f"{path}, line {line}: the file ends without a newline in a row shorter than every other "
            f"({text!r}): it may have been cut off mid-write; check that row, or delete it",
            UserWarning,
            stacklevel=6,  # load_log's caller
        )


def _min(chunk: _Chunk) -> float:
    """The shortest row of the chunk but its last."""
    return float(chunk.lengths[:-1].min()) if chunk.lengths.shape[0] > 1 else np.inf


def _chunks(stream: BinaryIO) -> Iterator[tuple[bytes, bool]]:
    """Chunks of about `CHUNK_BYTES`, each ending at a `\\n` but the last; with whether it is the
    last (a file without a final newline ends in a chunk of its own)."""
    rest = b""
    while True:
        block = stream.read(CHUNK_BYTES)
        if not block:
            if rest:
                yield rest, True
            return
        data = rest + block
        cut = data.rfind(b"\n") + 1
        if cut:
            yield data[:cut], False
        rest = data[cut:]


def _fast(chunk: bytes, columns: Columns) -> _Chunk | None:
    """The chunk read by `np.loadtxt`, or None where the careful reader must read it: a chunk
    that is not plain rows, a row with other than the header's count of cells, or a cell
    `np.loadtxt` refuses (whose line and column the careful reader names)."""
    if any(s in chunk for s in _CAREFUL) or len(columns.delimiter.encode()) != 1:
        return None
    if b"\r" in chunk:
        if chunk.count(b"\r") != chunk.count(b"\r\n"):
            return None  # a line ending in a bare \r (old Mac files)
        chunk = chunk.replace(b"\r\n", b"\n")
    if columns.decimal == ",":
        if b"." in chunk:
            return None
        chunk = chunk.replace(b",", b".")
    buf = np.frombuffer(chunk, np.uint8)
    ends = np.flatnonzero(buf == ord("\n"))
    if not chunk.endswith(b"\n"):
        ends = np.append(ends, len(chunk))
    starts = np.concatenate([[0], ends[:-1] + 1])
    if np.isin(buf[starts], _BLANK).any() or np.isin(buf[ends - 1], _BLANK[:2]).any():
        return None
    delimiters = np.flatnonzero(buf == columns.delimiter.encode()[0])
    if np.any(np.diff(np.searchsorted(delimiters, ends), prepend=0) != len(columns.header) - 1):
        return None
    values = _numbers(chunk, columns, len(ends))
    if values is None:
        return None
    last = decode(chunk[starts[-1] : ends[-1]]).strip()
    return _Chunk(values, None, ends - starts, last, len(ends))


def _numbers(chunk: bytes, columns: Columns, n_rows: int) -> np.ndarray | None:
    """The mapped cells of a chunk of `n_rows` plain rows (checked by `_fast`), shape
    (rows, mapped columns), or None where a cell is not a plain number. PyArrow's CSV
    reader where it is installed (a dependency; an install without it, `pip --no-deps`,
    falls back): it parses several times faster than `np.loadtxt`, on every core, to the
    same correctly rounded doubles. Neither reads a cell the grammar (`csv_numbers`)
    refuses: a cell either refuses goes to the careful reader, which names it."""
    try:
        import pyarrow as pa
        import pyarrow.csv as pa_csv
    except ImportError:
        return _numbers_loadtxt(chunk, columns)
    names = [str(k) for k in range(len(columns.header))]
    used = [names[c - 1] for c in columns.used]
    try:
        table = pa_csv.read_csv(
            pa.py_buffer(chunk),
            read_options=pa_csv.ReadOptions(column_names=names),
            parse_options=pa_csv.ParseOptions(
                delimiter=columns.delimiter, quote_char=False, escape_char=False, ignore_empty_lines=False
            ),
            # no cell is a null: "", "NA", "NULL" are not numbers (the careful reader says so)
            convert_options=pa_csv.ConvertOptions(
                include_columns=used,
                column_types={n: pa.float64() for n in used},
                null_values=[],
                strings_can_be_null=False,
                quoted_strings_can_be_null=False,
            ),
        )
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
        return None
    if table.num_rows != n_rows or any(table.column(n).null_count for n in used):
        return None
    values = np.empty((n_rows, len(used)))
    for k, n in enumerate(used):
        values[:, k] = table.column(n).to_numpy()
    # PyArrow reads `nan(1)` too: a NaN (refused as not finite in any case) is left to the
    # careful reader, whose grammar decides which cells are `nan`
    return None if np.isnan(values).any() else values


def _numbers_loadtxt(chunk: bytes, columns: Columns) -> np.ndarray | None:
    """`_numbers` by `np.loadtxt`, where PyArrow is not installed."""
    lines = chunk.split(b"\n")
    if not lines[-1]:
        lines.pop()
    try:
        return np.loadtxt(
            lines, delimiter=columns.delimiter, usecols=[c - 1 for c in columns.used], comments=None, ndmin=2
        )
    except ValueError:
        return None


def _careful(path: Path, chunk: bytes, first_line: int, at_end: bool, columns: Columns) -> _Chunk:
    """The chunk read line by line; `LogError` names the first bad row or cell."""
    lines = split_lines(decode(chunk))
    header, n, delimiter = columns.header, len(columns.header), columns.delimiter
    values, numbers, lengths = [], [], []
    for i, text in enumerate(lines):
        if skipped(text):
            continue
        no = first_line + i
        try:  # (without quotes, the csv module splits at the delimiter)
            row = next(csv.reader([text], delimiter=delimiter)) if '"' in text else text.split(delimiter)
        except csv.Error as e:
            raise LogError(f"{path}, line {no}: {e}; expected cells separated by {delimiter!r}") from None
        if len(row) != n:
            cut = at_end and i == len(lines) - 1 and not chunk.endswith((b"\n", b"\r"))
            raise LogError(
                f"{path}, line {no}: {len(row)} cells; expected {n} like the header on line {columns.header_line}"
                + ("; the file ends in this row without a newline: it may have been cut off mid-write" if cut else "")
            )
        for c in columns.used:
            try:
                values.append(parse_number(row[c - 1], columns.decimal))
            except ValueError:
                where = f"line {no}, column {c} ({header[c - 1]!r})"
                raise LogError(f"{path}, {where}: {number_problem(row[c - 1], columns.decimal)}") from None
        numbers.append(no)
        lengths.append(len(text.strip()))
    last = lines[numbers[-1] - first_line].strip() if numbers else ""
    return _Chunk(
        np.array(values, dtype=np.float64).reshape(len(numbers), len(columns.used)),
        np.array(numbers, dtype=np.int64),
        np.array(lengths, dtype=np.int64),
        last,
        len(lines),
    )


def _expected_rows(path: Path, stream: BinaryIO, bytes_per_row: float, out: np.ndarray) -> int:
    """The rows the file holds at the first chunk's bytes per row, with a quarter to spare;
    `LogError` (before the file is read on) if their mapped columns would not fit in the
    memory available."""
    at = stream.tell()
    size = stream.seek(0, os.SEEK_END)
    stream.seek(at)
    rows = size / bytes_per_row
    need = rows * out.shape[0] * 8 * MEMORY_PER_VALUE
    available = available_memory()
    if available is not None and need > available:
        raise LogError(
            f"{path}: about {rows:.3g} rows x {out.shape[0]} mapped column(s) need about {need / 1e9:.3g} GB of "
            f"memory to load, more than the {available / 1e9:.3g} GB available; split the log into shorter files "
            "(a [[logs]] entry each), or map fewer columns"
        )
    return int(1.25 * rows) + 1000


def available_memory() -> int | None:
    """Memory available to this process (bytes): Linux's MemAvailable, else the free pages;
    None where the system does not say."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None
