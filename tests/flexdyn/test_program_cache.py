"""`flexdyn.program_cache`: the guard against the kernel's memory-mapping limit.

Oracle: the kernel's own count of the process's mappings (`/proc/self/maps`) and JAX's own
count of a jitted function's cached programs. Linux only (elsewhere the guard does nothing,
checked at the end)."""

import os
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import flexdyn as fd
from flexdyn import program_cache

linux_only = pytest.mark.skipif(not os.path.exists("/proc/self/maps"), reason="needs /proc (Linux)")


def _fresh_program(scale: float):
    # a new function object: its own cache, its own compiled program
    return jax.jit(lambda x: jnp.linalg.cholesky(x @ x.T + scale * jnp.eye(x.shape[0])).sum())


@linux_only
def test_mapping_count_is_the_kernels_and_grows_with_compiled_programs():
    with open("/proc/sys/vm/max_map_count") as f:
        assert fd.mapping_limit() == int(f.read())
    before = fd.mapping_count()
    kept = [_fresh_program(10.0 + k) for k in range(5)]
    for f in kept:
        f(jnp.ones((4, 4))).block_until_ready()
    after = fd.mapping_count()
    # each compiled CPU program is loaded as object files of three mappings each
    assert after >= before + 3 * len(kept), (before, after)


@linux_only
def test_headroom_check_clears_the_caches_and_warns_once(monkeypatch):
    monkeypatch.setattr(program_cache, "_warned", False)
    f = _fresh_program(3.0)
    x = jnp.arange(9.0).reshape(3, 3)
    expected = float(f(x))
    assert f._cache_size() == 1
    # enough headroom: nothing happens
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert fd.ensure_mapping_headroom(reserve=0) is False
    assert f._cache_size() == 1
    # a reserve larger than the limit can never be met: the caches are cleared, with a warning
    # that names the count, the limit and the setting that avoids it
    limit = fd.mapping_limit()
    with pytest.warns(fd.MappingLimitWarning, match=r"holds \d+ memory mappings.*vm.max_map_count = \d+.*sysctl"):
        assert fd.ensure_mapping_headroom(reserve=limit + 1) is True
    assert f._cache_size() == 0
    # the function still works (compiled again) and gives the same value
    np.testing.assert_equal(float(f(x)), expected)
    # once per process: a second clearing is silent
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert fd.ensure_mapping_headroom(reserve=limit + 1) is True


def test_headroom_check_rejects_a_negative_reserve():
    with pytest.raises(ValueError, match="reserve expected >= 0, got -1"):
        fd.ensure_mapping_headroom(reserve=-1)


def test_headroom_check_does_nothing_where_the_kernel_reports_no_mappings(monkeypatch):
    monkeypatch.setattr(program_cache, "_MAPS", "/nonexistent/maps")
    monkeypatch.setattr(program_cache, "_LIMIT", "/nonexistent/max_map_count")
    f = _fresh_program(5.0)
    f(jnp.ones((2, 2)))
    assert fd.mapping_count() is None and fd.mapping_limit() is None
    assert fd.ensure_mapping_headroom(reserve=10**9) is False
    assert f._cache_size() == 1
