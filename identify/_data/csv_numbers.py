"""Numbers in a CSV log's cells: one plain grammar, read the same by the fast and the careful reader.

A cell is digits with at most one decimal mark and an optional exponent (`-1.5e-3`), or `nan`
or `inf` (which the loader then refuses as not finite, naming the channel). The decimal mark is
the log's `decimal`: `"."` (the default) or `","` (declared for a log written with decimal
commas). Python's `float` is not the grammar: it reads `-16_6.9411` as -166.9411 (underscores
group digits in Python source), and a comma read as a decimal mark by guess turns the
thousands separator of `1,234` into 1.234. Such cells are errors that say what they look like.
"""

from __future__ import annotations

import re

DECIMALS = (".", ",")


def _grammar(mark: str) -> re.Pattern:
    m = re.escape(mark)
    return re.compile(rf"[+-]?(?:[0-9]+(?:{m}[0-9]*)?|{m}[0-9]+)(?:[eE][+-]?[0-9]+)?|[+-]?(?:nan|inf|infinity)", re.I)


_NUMBER = {mark: _grammar(mark) for mark in DECIMALS}


def parse_number(text: str, decimal: str) -> float:
    """The value of a cell (surrounding white space ignored) with decimal mark `decimal`;
    `ValueError` if it is not a number of the grammar. (The grammar is Python's float
    literal, `nan` and `inf` in ASCII without underscores: `float` reads the rest.)"""
    s = text.strip()
    if decimal == ",":
        if "." in s:
            raise ValueError(s)
        s = s.replace(",", ".")
    if "_" in s or not s.isascii():
        raise ValueError(s)
    return float(s)


def is_number(text: str) -> bool:
    """Whether a cell is a number with either decimal mark (a header row made of numbers
    is a missing header)."""
    s = text.strip()
    return any(g.fullmatch(s) for g in _NUMBER.values())


def number_problem(text: str, decimal: str) -> str:
    """Why a cell is not a number, as the message's end: `expected a number, got ...` and,
    for a cell that would be one without a separator, which separator and the fix."""
    s = text.strip()
    if not s:
        return "expected a number, got an empty cell"
    got = f"expected a number, got {text!r}"
    plain = _NUMBER[decimal]
    other = "," if decimal == "." else "."
    if "_" in s and plain.fullmatch(s.replace("_", "")):
        return f"{got}: an underscore is not part of a number"
    if decimal == "." and s.count(",") == 1 and "." not in s and _NUMBER[","].fullmatch(s):
        what = f"a decimal comma ({s.replace(',', '.')})"
        if re.fullmatch(r"[+-]?[0-9]+,[0-9]{3}", s):  # 1,234: 1234 with a thousands separator just as well
            what += f" or a thousands separator ({s.replace(',', '')})"
        return (
            f"{got}: {what}? "
            'If the file writes decimal commas, say so: decimal = "," in its [[logs]] entry '
            '(load_log(..., decimal=",")); a number has no thousands separators'
        )
    if decimal == "," and s.count(".") == 1 and "," not in s and _NUMBER["."].fullmatch(s):
        return (
            f"{got}: the log is read with decimal commas (decimal = \",\"), where a '.' could only separate "
            f"thousands ({s.replace('.', '')}), which is not read; expected a decimal comma, like '1234,5'"
        )
    for sep, name in ((" ", "a space"), ("'", "an apostrophe"), (other, f"a {other!r}")):
        if sep in s and plain.fullmatch(s.replace(sep, "")):
            return f"{got}: {name} separating thousands is not read; expected {s.replace(sep, '')!r}"
    return got
