"""Lazy public names: a package's re-exports imported on first use (PEP 562).

`import identify` (and with it the `identify` command, which must parse its arguments,
print `--help` and handle Ctrl-C before anything slow happens) then costs milliseconds
instead of the seconds of importing JAX, diffrax and optimistix. The package lists its
public names once, as ordinary `from .module import name as name` lines under
`if TYPE_CHECKING:` (so that type checkers, IDEs and the API reference see them as usual);
`exports` reads those lines from the package's own source and serves each name from
its module when it is first asked for, as scientific Python's `lazy_loader` (SPEC 1) does from a stub file.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path


def _re_exports(source: str, filename: str) -> dict[str, tuple[str, str]]:
    """`{public name: (relative module, name in it)}` of the `from .x import y as y` lines
    inside the module's `if TYPE_CHECKING:` block."""
    tree = ast.parse(source, filename)
    names: dict[str, tuple[str, str]] = {}
    for node in tree.body:
        if not (isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING"):
            continue
        for line in node.body:
            if isinstance(line, ast.ImportFrom) and line.level >= 1:
                module = "." * line.level + (line.module or "")
                names.update({a.asname or a.name: (module, a.name) for a in line.names})
    if not names:
        raise ImportError(f"{filename}: no `from .module import name as name` lines under `if TYPE_CHECKING:`")
    return names


def _load(package: str, module: str, name: str):
    """`from {module} import {name}` relative to `package`: an attribute of the module, or
    its submodule of that name."""
    mod = importlib.import_module(module, package)
    try:
        return getattr(mod, name)
    except AttributeError:
        return importlib.import_module(f"{mod.__name__}.{name}")


def exports(package: str, init_file: str):
    """`(__getattr__, __dir__, __all__)` for the package `package` whose `__init__.py` is
    `init_file`: each public name imported on first access and kept in the package's
    namespace from then on."""
    names = _re_exports(Path(init_file).read_text(encoding="utf-8"), init_file)
    namespace = importlib.import_module(package).__dict__

    def __getattr__(name: str):
        if name not in names:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = _load(package, *names[name])
        namespace[name] = value  # (found directly next time, without this function)
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(names))

    return __getattr__, __dir__, sorted(names)
