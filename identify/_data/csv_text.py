"""A CSV log's text before its rows: the byte stream (byte-order marks, UTF-16), its lines, and
where the header row is, with the cells' separator.

Lines end at `\\n`, `\\r\\n` or `\\r` only. `str.splitlines` also splits at a form feed, U+2028
and other separators that a comment may hold (pasted from a word processor): a `#` comment
holding one made its tail the header row.
"""

from __future__ import annotations

import dataclasses
import io
import re
from pathlib import Path
from typing import BinaryIO

from .columns import LogError

_LINE_END = re.compile(r"\r\n|\r|\n")


_LINE_END_BYTES = re.compile(rb"\r\n|\r|\n")


#: Excel's separator line (`sep=;`), written before the header by some exports
_EXCEL_SEP = re.compile(r'^\s*"?sep=(?P<sep>.)"?\s*$', re.IGNORECASE)


#: How much of the file is searched for the header at a time (bytes)
_HEAD_BLOCK = 1 << 20


_UTF8_BOM = b"\xef\xbb\xbf"


def split_lines(text: str) -> list[str]:
    """The lines of `text` without their ends, split at `\\n`, `\\r\\n` and `\\r` only; a final
    line end does not start another line."""
    lines = _LINE_END.split(text)
    if lines and not lines[-1]:
        lines.pop()
    return lines


def decode(data: bytes) -> str:
    """UTF-8, else Windows-1252 (the DAQ software of Windows PCs), undecodable bytes replaced."""
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return data.decode("cp1252", errors="replace")


def skipped(line: str) -> bool:
    """A blank line or a `#` comment, skipped anywhere in a log."""
    s = line.strip()
    return not s or s.startswith("#")


def open_bytes(path: Path) -> BinaryIO:
    """The file's bytes after any UTF-8 byte-order mark; a UTF-16 file (with its byte-order mark:
    Windows' "Unicode text") transcoded to UTF-8 in memory."""
    try:
        stream = open(path, "rb")  # noqa: SIM115 (the caller closes it)
        start = stream.read(4)
    except OSError as e:
        raise LogError(f"{path}: log file cannot be read ({e.strerror})") from None
    if start.startswith((b"\xff\xfe", b"\xfe\xff")):
        with stream:
            data = start + stream.read()
        try:
            return io.BytesIO(data.decode("utf-16").encode("utf-8"))
        except UnicodeDecodeError as e:
            raise LogError(f"{path}: starts with a UTF-16 byte-order mark but is not valid UTF-16 ({e})") from None
    stream.seek(len(_UTF8_BOM) if start.startswith(_UTF8_BOM) else 0)
    return stream


@dataclasses.dataclass(frozen=True)
class Header:
    """The header row of a CSV log: its line (1-based), its text, the cells' separator, and the
    byte offset in the stream where the rows start."""

    line: int
    text: str
    delimiter: str
    rows_offset: int


def find_header(path: Path, stream: BinaryIO) -> Header:
    """The first line that is neither blank nor a `#` comment (after Excel's `sep=;` line, if
    any, which gives the separator); else the first of `;`, tab and `,` in the header."""
    base = stream.tell()
    head = b""
    while True:
        block = stream.read(_HEAD_BLOCK)
        head += block
        at_end = not block
        lines = _complete_lines(head, at_end)
        found = [k for k, (text, _) in enumerate(lines) if not skipped(text)]
        sep = _EXCEL_SEP.match(lines[found[0]][0]) if found else None
        if sep is not None and len(found) > 1:
            text, end = lines[found[1]]
            return Header(found[1] + 1, text, sep["sep"], base + end)
        if sep is None and found:
            text, end = lines[found[0]]
            delimiter = ";" if ";" in text else "\t" if "\t" in text else ","
            return Header(found[0] + 1, text, delimiter, base + end)
        if at_end:
            if sep is not None:
                raise LogError(f"{path}: no header row after the separator line 'sep={sep['sep']}'")
            raise LogError(f"{path}: no header row; expected a first row like 'time [s],theta1 [rad],tip1 [mm]'")


def _complete_lines(head: bytes, at_end: bool) -> list[tuple[str, int]]:
    """The lines of `head` whose end it holds, decoded, each with the offset after its line end;
    at the end of the file, the last line too. (A `\\r` ending `head` may be half of `\\r\\n`.)"""
    out, start = [], 0
    for m in _LINE_END_BYTES.finditer(head):
        if m.end() == len(head) and m.group() == b"\r" and not at_end:
            break
        out.append((decode(head[start : m.start()]), m.end()))
        start = m.end()
    if at_end and start < len(head):
        out.append((decode(head[start:]), len(head)))
    return out
