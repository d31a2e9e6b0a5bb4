"""The shipped examples' scripts (`identify/examples/<name>/make_logs.py`) as modules, for
the tests that read their truth or write logs with them."""

from __future__ import annotations

import importlib.util
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parents[1] / "identify" / "examples"


def make_logs_module(example: str):
    """The example's `make_logs.py`, imported (under a name of its own per example)."""
    spec = importlib.util.spec_from_file_location(f"{example}_make_logs", EXAMPLES / example / "make_logs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
