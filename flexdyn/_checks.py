"""Parameter validation shared by the model parts.

Concrete values are checked when a part is built (a `ValueError` naming the
parameter); traced values (under `jit`, `vmap`, `grad`) are checked inside the
computation with `eqx.error_if` by `checked`.
"""

from __future__ import annotations

import re
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def as_float_array(value, name: str | None = None):
    """A float64 (when x64 is on) JAX array of `value`; tracers pass through. `name` (e.g.
    "RigidLink.length") is named in the error when `value` is not numeric."""
    if isinstance(value, jax.Array):
        return value if jnp.issubdtype(value.dtype, jnp.floating) else value.astype(float)
    try:
        return jnp.asarray(value, dtype=float)
    except (TypeError, ValueError) as e:
        raise TypeError(f"{name or 'value'}: expected a number or an array of numbers (SI), got {value!r}") from e


def warn_if_single_precision(caller: str, consequence: str, stacklevel: int = 4) -> None:
    """Warn that JAX runs in float32 (`jax_enable_x64` off, e.g. `FLEXDYN_NO_X64=1`):
    `consequence` says what that costs `caller`. flexdyn expects float64. (`stacklevel`
    4: the user's line when called from a function called by the public one.)"""
    if jnp.result_type(float) != jnp.float64:
        warnings.warn(
            f"{caller}: JAX runs in single precision (jax_enable_x64 is off, e.g. FLEXDYN_NO_X64=1): "
            f"{consequence}; flexdyn expects float64",
            stacklevel=stacklevel,
        )


def _is_concrete(value) -> bool:
    return not isinstance(value, jax.core.Tracer)


def check_parameter(owner: str, name: str, value, *, positive: bool = False, signed: bool = False, shape=None):
    """Raise `ValueError` if a concrete parameter is not finite, has the wrong shape,
    or (with `positive`) is not > 0 (`>= 0` unless `signed`). Tracers are left to `checked`."""
    if shape is not None and tuple(np.shape(value)) != tuple(shape):
        raise ValueError(f"{owner}.{name}: expected shape {tuple(shape)}, got {tuple(np.shape(value))}")
    if not _is_concrete(value):
        return
    arr = np.asarray(value, dtype=float)
    shown = f"{arr.item():g}" if arr.ndim == 0 else np.array2string(arr, precision=6)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{owner}.{name}: expected a finite number, got {shown}")
    if positive and np.any(arr <= 0):
        raise ValueError(f"{owner}.{name}: expected a value > 0, got {shown}")
    if not positive and not signed and np.any(arr < 0):
        raise ValueError(f"{owner}.{name}: expected a value >= 0, got {shown}")


def warn_if_degrees(owner: str, name: str, angles) -> None:
    """Warn when a concrete angle (rad) exceeds `2 pi` in magnitude: flexdyn takes
    radians, and `90` meant as degrees is a quarter of a turn read as 14 turns. Angles
    beyond a turn are legitimate (a hub wound several turns), so this warns, not raises.
    Traced values are not looked at."""
    if not _is_concrete(angles):
        return
    arr = np.atleast_1d(np.asarray(angles, dtype=float))
    big = np.flatnonzero(np.isfinite(arr) & (np.abs(arr) > 2 * np.pi))
    if big.size:
        i = int(big[0])
        warnings.warn(
            f"{owner}.{name}[{i}] = {arr[i]:g} rad is more than a turn; flexdyn takes angles in radians "
            f"(if {arr[i]:g} is in degrees, pass np.deg2rad: {np.deg2rad(arr[i]):.6g} rad)",
            UserWarning,
            stacklevel=3,
        )


POSITIVE, NONNEGATIVE, SIGNED = "positive", "nonnegative", "signed"


def checked(value, owner: str, name: str, kind: str = NONNEGATIVE, shape=None):
    """`value` as a float array, checked to be finite and > 0 (`POSITIVE`), >= 0
    (`NONNEGATIVE`) or of any sign (`SIGNED`), and of `shape` if given (the shape at
    once, always). A concrete value is checked at once
    (`check_parameter`'s `ValueError`); a traced one (under jit/vmap/grad) at run time
    with `eqx.error_if`."""
    if kind not in (POSITIVE, NONNEGATIVE, SIGNED):
        raise ValueError(f"checked: unknown kind {kind!r}")
    check_parameter(owner, name, value, positive=kind == POSITIVE, signed=kind == SIGNED, shape=shape)
    if _is_concrete(value):
        return as_float_array(value)
    bad = ~jnp.isfinite(value)
    if kind != SIGNED:
        bad = bad | ((value <= 0) if kind == POSITIVE else (value < 0))
    bound = {POSITIVE: " and > 0", NONNEGATIVE: " and >= 0", SIGNED: ""}[kind]
    return eqx.error_if(value, jnp.any(bad), f"{owner}.{name} must be finite{bound}")


def _shape(part, name: str) -> tuple:
    return (part.n_modes,) if name == "damping_ratio" else ()


def check_part(part) -> None:
    """Check every parameter of `part` named in its `PARAMETERS` table ((name, kind)
    pairs; None values skipped) when it is built: shape, and for concrete values
    finiteness and sign (a `ValueError` naming the part and the parameter)."""
    owner = type(part).__name__
    for name, kind in part.PARAMETERS:
        value = getattr(part, name)
        if value is not None:
            check_parameter(
                owner, name, value, positive=kind == POSITIVE, signed=kind == SIGNED, shape=_shape(part, name)
            )
    length = getattr(part, "length", None)
    if length is not None and _is_concrete(length) and float(np.asarray(length)) > LONG_LINK:
        value = float(np.asarray(length))
        warnings.warn(
            f"{owner}.length = {value:g} m is over {LONG_LINK:g} m; flexdyn takes lengths in metres "
            f"(if {value:g} is in mm, pass {value / 1e3:g})",
            UserWarning,
            stacklevel=4,
        )


#: `check_part` warns of a link longer than this (m): a length in millimetres, most likely
LONG_LINK = 50.0


def checked_part(part, owner: str | None = None):
    """`part` with every parameter of its `PARAMETERS` table passed through `checked`:
    the chain's assembly applies it, so that values set after construction
    (`eqx.tree_at`, `with_parameters`, traced values under jit/vmap/grad) are held to the
    same rules as at construction, and a Python float becomes an array. Messages name
    the parameter as `owner.name` (default owner: the part's class)."""
    owner = type(part).__name__ if owner is None else owner
    present = [(name, kind) for name, kind in part.PARAMETERS if getattr(part, name) is not None]
    names = [name for name, _ in present]
    values = [checked(getattr(part, name), owner, name, kind, _shape(part, name)) for name, kind in present]
    return eqx.tree_at(lambda p: [getattr(p, name) for name in names], part, values, is_leaf=lambda x: x is None)


def runtime_check_message(e: Exception) -> str | None:
    """The message of a run-time check (`eqx.error_if`) in `e`, an error raised by a
    jitted program, without the stacks JAX and Equinox put around it ("... Equinox
    RuntimeError: link1.EI must be finite and > 0" -> "link1.EI must be finite and > 0");
    None if `e` holds none."""
    m = re.search(r"EquinoxRuntimeError: (.+)", str(e))
    return m.group(1).strip() if m else None


def error_reason(e: Exception) -> str:
    """`runtime_check_message(e)`, else the first non-empty line of `e`'s message (else
    its type's name): what to print of an error in one line."""
    check = runtime_check_message(e)
    if check is not None:
        return check
    lines = [line.strip() for line in str(e).splitlines() if line.strip()]
    return lines[0] if lines else type(e).__name__
