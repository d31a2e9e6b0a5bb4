"""Input files before they are opened: what a path is when it is not a readable regular file
(missing, a directory, a named pipe, a symbolic link loop), and its absolute form for messages.

The check uses `os.stat` only: a named pipe (FIFO) is never opened, so reading it cannot block,
and a symbolic link loop is named instead of escaping as `OSError` or `RuntimeError`.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

_KINDS = (
    (stat.S_ISFIFO, "a named pipe (FIFO)"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
)


def file_problem(path: Path) -> str | None:
    """Why `path` cannot be read as an input file, as the end of a sentence ("is a directory"),
    or None for a regular file (symbolic links followed)."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "is a broken symbolic link (its target does not exist)" if os.path.islink(path) else "does not exist"
    except OSError as e:
        if e.errno == errno.ELOOP:
            return "is a symbolic link loop (a link that leads back to itself)"
        return f"cannot be read ({e.strerror})"
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISDIR(mode):
        return "is a directory"
    kind = next((name for test, name in _KINDS if test(mode)), "a special file")
    return f"is not a regular file ({kind})"


def absolute(path: Path) -> Path:
    """`path` made absolute and normalised for a message, its symbolic links kept: a broken link
    or a loop is named as written, not as its target."""
    return Path(os.path.abspath(path))


def resolved(path: Path) -> Path:
    """`path` with its symbolic links resolved (which file it is), or `absolute(path)` where
    they cannot be (a loop)."""
    try:
        return path.resolve()
    except (OSError, RuntimeError):
        return absolute(path)


def expand_user(path: str) -> Path:
    """`~` and `~user` expanded; a `~user` with no such user stays as written (then it does not
    exist), where `Path.expanduser` raises `RuntimeError`."""
    return Path(os.path.expanduser(path))


def input_problem(path: Path, bag: bool) -> str | None:
    """`file_problem`, with a folder accepted where it is a ROS 2 bag (`bag`)."""
    problem = file_problem(path)
    if problem == "is a directory":
        return None if bag else "is a directory without a metadata.yaml (not a ROS 2 bag)"
    return problem
