"""Parameter validation shared by the model parts.

Concrete values are checked when a part is built (a `ValueError` naming the
parameter); traced values (under `jit`, `vmap`, `grad`) are checked inside the
computation with `eqx.error_if` by `checked`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def as_float_array(value):
    """A float64 (when x64 is on) JAX array of `value`; tracers pass through."""
    if isinstance(value, jax.Array):
        return value if jnp.issubdtype(value.dtype, jnp.floating) else value.astype(float)
    return jnp.asarray(value, dtype=float)


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
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{owner}.{name}: expected a finite number, got {value!r}")
    if positive and np.any(arr <= 0):
        raise ValueError(f"{owner}.{name}: expected a value > 0, got {value!r}")
    if not positive and not signed and np.any(arr < 0):
        raise ValueError(f"{owner}.{name}: expected a value >= 0, got {value!r}")


def checked(value, owner: str, name: str, *, positive: bool = False):
    """`value` with a run-time check (works under jit/vmap/grad) that it is finite and
    > 0 (`positive`) or >= 0."""
    bad = ~jnp.isfinite(value) | ((value <= 0) if positive else (value < 0))
    bound = "> 0" if positive else ">= 0"
    return eqx.error_if(value, jnp.any(bad), f"{owner}.{name} must be finite and {bound}")
