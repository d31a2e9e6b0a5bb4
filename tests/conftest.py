"""Shared test set-up: float64, strict dtype promotion, a seeded RNG, helpers."""

import gc
import os
import sys

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")

# tests/ holds the independent oracles (oracles.py); make it importable.
sys.path.insert(0, os.path.dirname(__file__))


# Memory one pytest-xdist worker may need at its peak: a full run with two workers peaked at
# 6.8 GB for the two, the controller and the notebook kernels together (2026-11-26).
_WORKER_MEMORY_BYTES = 3.2e9


def _available_memory_bytes():
    from identify._data.csv_rows import available_memory  # (the readers' own measure)

    return available_memory()


def pytest_xdist_auto_num_workers(config):
    """Workers for `-n auto` (pyproject's addopts): one per core, no more than the available
    memory holds at `_WORKER_MEMORY_BYTES` each, and none (the run stays in this process)
    where only one would fit."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    memory = _available_memory_bytes()
    fits = cores if memory is None else int(memory // _WORKER_MEMORY_BYTES)
    workers = min(cores, fits)
    return workers if workers >= 2 else 0


@pytest.fixture
def rng():
    return np.random.default_rng(20261123)


def tree_allclose(x, y, *, rtol, atol):
    """True when every leaf of two pytrees agrees within the given tolerances."""
    lx, ly = jax.tree_util.tree_leaves(x), jax.tree_util.tree_leaves(y)
    return len(lx) == len(ly) and all(np.allclose(a, b, rtol=rtol, atol=atol) for a, b in zip(lx, ly))


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module. A full run compiles thousands of
    programs in one process, and each holds memory mappings until it is dropped: at the
    kernel's limit (vm.max_map_count, 65,530 by default) XLA's compiler crashes (seen on a
    fresh clone and in the slow diagnosis grid; `flexdyn.program_cache` has the measurements
    and the guard that `identify` runs before each fit). So each module starts clean."""
    yield
    jax.clear_caches()
    gc.collect()
