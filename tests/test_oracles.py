"""The independent oracles are themselves checked against textbook values and independent
models (finite elements, quadrature, DOP853, finite-difference Lagrangians): see
check_oracles.py. An error there would make every physics test wrong."""

import os
import runpy

import pytest


def test_oracles_self_check(capsys):
    pytest.importorskip("mujoco")
    with pytest.raises(SystemExit) as done:
        runpy.run_path(os.path.join(os.path.dirname(__file__), "check_oracles.py"), run_name="__main__")
    out = capsys.readouterr().out
    assert done.value.code == 0, out[-3000:]
    assert "ALL OK" in out
