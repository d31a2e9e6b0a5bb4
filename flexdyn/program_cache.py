"""Keeping a long-running process clear of the kernel's memory-mapping limit.

Every program that XLA compiles for the CPU is loaded into memory as a handful of object
files, and each object file takes three memory mappings (code, read-only data, data). JAX
keeps every compiled program for as long as the function it was compiled for lives: for
our module-level jitted functions, the whole process. A Linux process may hold at most
`vm.max_map_count` mappings (65,530 by default). When the limit is reached, the next
`mmap` in XLA's compiler fails and the process dies: "Segmentation fault" or "Fatal Python
error: Aborted" inside `backend_compile_and_load`, with no Python exception to catch.

One diagnosis of the simulated pendulum compiles ~160 programs and adds ~3,700 mappings
(a fitted 1-DOF model and every catalogue candidate); a second diagnosis of the same
layout reuses them all. Diagnoses of *different* models (other rigs, other numbers of
modes, other candidate structures) each add their own, so a process that diagnoses a
dozen different models can reach the limit (`docs/performance.md`).

`ensure_mapping_headroom` is called by `identify.fit`, `identify.fit_independent` and
`identify.diagnose` before each model they compile, and may be called by user code
that compiles many distinct programs in one process (sweeps over model structures): when
fewer than `reserve` mappings are left, it clears JAX's compilation caches
(`jax.clear_caches()`: programs compile again on their next use, results are unchanged)
and warns once with `MappingLimitWarning`. The lasting fix is the system's: raise the
limit, e.g. `sudo sysctl -w vm.max_map_count=262144` (recent Fedora, Ubuntu and Arch releases
ship 1,048,576).

Where `/proc` is missing (macOS, Windows), every function here returns `None` or does
nothing.
"""

from __future__ import annotations

import gc
import warnings

import jax

_MAPS = "/proc/self/maps"
_LIMIT = "/proc/sys/vm/max_map_count"
_warned = False


class MappingLimitWarning(RuntimeWarning):
    """JAX's compilation caches were cleared because the process neared `vm.max_map_count`."""


def mapping_count() -> int | None:
    """Number of memory mappings this process holds (lines of `/proc/self/maps`), or None
    where the kernel does not report it."""
    try:
        with open(_MAPS, "rb") as f:
            return f.read().count(b"\n")
    except OSError:
        return None


def mapping_limit() -> int | None:
    """The kernel's limit on a process's memory mappings (`vm.max_map_count`), or None
    where the kernel does not report it."""
    try:
        with open(_LIMIT) as f:
            return int(f.read().strip())
    except (OSError, ValueError):
        return None


def ensure_mapping_headroom(reserve: int = 16384) -> bool:
    """Clear JAX's compilation caches if fewer than `reserve` memory mappings are left.

    **Arguments:**
    - `reserve`: mappings to keep free for the programs compiled before the next check.
      The default (a quarter of Linux's default limit) covers one diagnosis candidate or
      one fit with a wide margin (a full pendulum diagnosis adds ~3,700).

    **Returns:** True if the caches were cleared. Never call it inside a function being
    traced by `jax.jit` (it is a host-side check between compilations).

    Warns with `MappingLimitWarning` the first time it clears the caches in a process,
    naming the count, the limit and the `sysctl` setting that removes the need.
    """
    if reserve < 0:
        raise ValueError(f"ensure_mapping_headroom: reserve expected >= 0, got {reserve}")
    limit = mapping_limit()
    count = mapping_count() if limit is not None else None
    if count is None or limit - count >= reserve:
        return False
    jax.clear_caches()
    gc.collect()
    global _warned
    if not _warned:
        _warned = True
        warnings.warn(
            f"flexdyn: this process holds {count} memory mappings, near the kernel's limit "
            f"vm.max_map_count = {limit} (each program XLA compiles holds some); JAX's compilation "
            f"caches were cleared so that the next compilation does not crash (programs compile "
            f"again on their next use; results are unchanged). To avoid the recompilation, raise "
            f"the limit: sudo sysctl -w vm.max_map_count=262144 (see flexdyn.program_cache).",
            MappingLimitWarning,
            stacklevel=2,
        )
    return True
