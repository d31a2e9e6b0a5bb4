"""Reading an experiment file's TOML with locations: `ExperimentError` names the file, line and key
of a bad entry, with the expected form.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from pathlib import Path

import flexdyn as fd


class ExperimentError(ValueError):
    """An experiment file is not usable; the message names the file, line, key and the fix."""


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
    for no, line in enumerate(text.split("\n"), start=1):  # TOML's newlines only: not splitlines()'s U+2028, \f, ...
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
