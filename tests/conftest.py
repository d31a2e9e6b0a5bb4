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
