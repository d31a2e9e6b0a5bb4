"""JSON output: plain JSON types, the versions a result was computed with."""

from __future__ import annotations

import platform
from pathlib import Path

import numpy as np


def jsonable(x):
    """`x` in plain JSON types for `result.json` and `diagnosis.json`: arrays as lists,
    paths as strings, and NaN and infinities (a parameter the data do not determine has an
    infinite standard error and interval) as null, which every JSON reader accepts."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not np.isfinite(x):
        return None
    if isinstance(x, Path):
        return str(x)
    return x


def package_versions() -> dict:
    import importlib.metadata as md

    out = {"python": platform.python_version()}
    for pkg in ("flexdyn", "jax", "jaxlib", "equinox", "diffrax", "optimistix", "numpy", "scipy", "matplotlib"):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            out[pkg] = None
    return out
