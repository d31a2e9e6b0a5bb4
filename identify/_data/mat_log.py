"""The MATLAB `.mat` reader of `load_log`: v5/v7 files through SciPy, v7.3 through h5py, struct fields by path."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .columns import (
    LogError,
    _calibration_note,
    _check_samples,
    _check_time,
    _relative_time,
    _resolve_unit,
    _to_si,
    _warn_if_turns,
)


def _load_mat_variables(path: Path) -> dict:
    import scipy.io

    try:
        return scipy.io.loadmat(path)
    except NotImplementedError:  # scipy's answer for v7.3 (HDF5) files
        try:
            import h5py
        except ImportError:
            raise LogError(
                f"{path}: a MATLAB v7.3 (HDF5) file, which needs h5py; re-save it in MATLAB with "
                "save('file.mat', ..., '-v7'), or install h5py"
            ) from None
        with h5py.File(path, "r") as f:  # MATLAB stores arrays transposed; vectors don't mind
            out = {}

            def visit(name, obj):  # a struct is a group, its fields datasets (or groups) in it
                if isinstance(obj, h5py.Dataset) and not name.startswith("#"):
                    out[name.replace("/", ".")] = np.asarray(obj).T

            f.visititems(visit)
            return out
    except Exception as e:  # scipy raises several types for a file that is not a .mat
        raise LogError(f"{path}: not a readable MATLAB .mat file ({type(e).__name__}: {e})") from None


def _with_fields(variables: dict) -> dict:
    """`variables` and, for each scalar (1 x 1) struct, its fields as `struct.field`
    (nested structs: `a.b.c`), read as variables are. A struct array (several elements)
    keeps only its own entry: which element a field is from would be a guess."""
    out = dict(variables)
    for name, value in variables.items():
        kind, fields = _mat_kind(value)
        if kind == "a struct" and value.size == 1:
            element = value.reshape(-1)[0]
            out.update(_with_fields({f"{name}.{field}": element[field] for field in fields}))
    return out


def _leaves(variables: dict) -> list[str]:
    """The names of `_with_fields(variables)` that are not structs themselves (scalar
    structs are read through their fields); sorted."""
    return sorted(k for k, v in variables.items() if not (_mat_kind(v)[0] == "a struct" and getattr(v, "size", 0) == 1))


def _mat_kind(value) -> tuple[str, list[str]]:
    """What a variable read by `scipy.io.loadmat` is, in MATLAB's words: `("numeric", [])`
    for a real numeric array, `("a struct", fields)`, `("a cell array", [])`, `("text
    (a char array)", [])`, `("complex numbers", [])`, or its type."""
    if not isinstance(value, np.ndarray):
        return type(value).__name__, []
    if value.dtype.names:
        return "a struct", list(value.dtype.names)
    return {
        "b": "numeric",
        "i": "numeric",
        "u": "numeric",
        "f": "numeric",
        "c": "complex numbers",
        "O": "a cell array",
        "U": "text (a char array)",
        "S": "text (a char array)",
    }.get(value.dtype.kind, f"dtype {value.dtype}"), []


def _read_mat(path: Path, wanted, cals, strict, context):
    data = _load_mat_variables(path)
    variables = _with_fields({k: v for k, v in data.items() if not k.startswith("__")})
    leaves = _leaves(variables)
    used = {}
    for w in wanted:
        if w.source not in variables:
            holder = next((k for k in leaves if k.rsplit(".", 1)[-1] == w.source and "." in k), None)
            head = next((k for k in variables if w.source.startswith(k + ".")), None)
            if holder is not None:  # (the struct's name left out)
                hint = f"; it is the field {holder!r} of a struct: map it as '{holder} [unit]'"
            elif head is not None and _mat_kind(variables[head])[0] == "a struct":
                hint = (
                    f"; {head!r} is a struct array of {variables[head].size} elements, whose fields are not read "
                    "(which element?): save the element you mean as a struct of its own, or its fields as variables"
                )
            else:
                hint = ""
            raise LogError(
                f"{path}: no variable {w.source!r} (mapped by {context}.{w.channel}); the file has {leaves}{hint}",
                channel=w.channel,
            )
        where = f"{path}: variable {w.source!r}"
        unit, cal = _resolve_unit(path, w, None, where, cals)
        value = variables[w.source]
        kind, fields = _mat_kind(value)
        if kind != "numeric":
            extra = f" with fields {fields}" if fields else ""
            if fields and value.size == 1:
                extra += f": map one of them, e.g. '{w.source}.{fields[0]} [unit]'"
            raise LogError(f"{where}: expected a real numeric vector, got {kind}{extra}")
        if sum(d > 1 for d in value.shape) > 1:
            raise LogError(f"{where}: shape {value.shape}; expected a vector (one channel per variable)")
        if w.channel == "time" and value.size < 2:
            raise LogError(
                f"{where} (time): holds {value.size} value(s); expected a vector of sample times, one per sample"
            )
        used[w] = (value.astype(np.float64).ravel(), unit, cal)
    ignored = sorted(set(leaves) - {w.source for w in wanted})
    if strict and ignored:
        raise LogError(f"{path}: variable(s) {ignored} are not mapped to any channel (strict = true)")
    time_w = next(w for w in wanted if w.channel == "time")
    n = used[time_w][0].shape[0]
    channels, sources = {}, {}
    for w, (raw, unit, cal) in used.items():
        if raw.shape[0] != n:
            raise LogError(
                f"{path}: variable {w.source!r} ({w.channel}) has {raw.shape[0]} samples; "
                f"expected {n} like the time variable {time_w.source!r}"
            )
        where = lambda j, s=w.source: f"variable {s!r}, sample {j + 1}"  # noqa: E731 (1-based, as in MATLAB)
        _check_samples(path, w.channel, raw, where)
        channels[w.channel] = _to_si(raw, unit, cal, w.channel)
        _warn_if_turns(path, f"variable {w.source!r}", w.channel, channels[w.channel], unit)
        sources[w.channel] = f"variable {w.source!r} [{w.unit}]" + _calibration_note(cal)
        if w.channel == "time":
            t_relative = _relative_time(raw, unit)
    t = channels.pop("time")
    sources.pop("time")
    _check_time(path, t_relative, lambda j: f"variable {time_w.source!r}, sample {j + 1}", t)
    return t, t_relative, channels, sources, ignored
