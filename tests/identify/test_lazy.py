"""`identify`'s public names are imported on first use (`identify/_lazy.py`): the package
and the command line start without JAX, every public name still resolves to the object of
its module, and Ctrl-C while the command imports the library is a one-line message."""

from __future__ import annotations

import ast
import importlib
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import identify
from identify import _lazy

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "identify" / "examples" / "pendulum_friction" / "experiment.toml"


def _declared() -> dict[str, tuple[str, str]]:
    """The `from .module import name as name` lines of identify/__init__.py, read here
    independently of `_lazy`."""
    tree = ast.parse((ROOT / "identify" / "__init__.py").read_text(encoding="utf-8"))
    out = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 1 and node.module != "_lazy":
            out.update({a.asname: (node.module, a.name) for a in node.names})
    return out


def test_import_and_help_do_not_import_jax():
    code = (
        "import sys, identify, identify.cli; print(sorted(m for m in ('jax', 'numpy', 'diffrax') if m in sys.modules))"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[]"


def test_every_public_name_is_its_modules_object():
    declared = _declared()
    assert len(declared) > 30 and set(declared) == set(identify.__all__)
    for name, (module, attr) in declared.items():
        mod = importlib.import_module(f"identify.{module}")
        expected = getattr(mod, attr, None) or importlib.import_module(f"identify.{module}.{attr}")
        assert getattr(identify, name) is expected, name
    assert set(identify.__all__) <= set(dir(identify))


def test_from_import_and_unknown_names():
    from identify import Parameter, catalogue

    assert Parameter.__module__ == "identify._model.parameters"
    assert catalogue.__name__ == "identify._diagnose.catalogue"
    with pytest.raises(AttributeError, match="module 'identify' has no attribute 'no_such_name'"):
        identify.no_such_name  # noqa: B018
    with pytest.raises(ImportError):
        exec("from identify import no_such_name", {})


def test_a_package_without_declared_names_is_an_error(tmp_path):
    with pytest.raises(ImportError, match="no `from .module import name as name` lines"):
        _lazy._re_exports("import os\n", str(tmp_path / "__init__.py"))


def test_ctrl_c_while_the_command_imports_the_library_is_one_line():
    """SIGINT half a second after start, while `identify check` imports JAX and the library
    (seconds of work): the command says it was interrupted, without a traceback, and exits
    130. (Such a Ctrl-C often lands in JAX's garbage-collection callback, where Python
    prints "Exception ignored" and drops it: the command must not go on as if never
    interrupted.)"""
    cmd = [sys.executable, "-m", "identify", "check", str(EXAMPLE)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, (out, err)
    assert err == "identify check: interrupted; nothing was written\n", err
