"""Execute notebooks/paper004_controller.ipynb (paper 004's composite controller) and check its RESULTS."""

import ast
import math
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
pytest.importorskip("nbclient")

from notebook_runner import assert_stored_without_outputs, notebook_path, run_notebook  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOK = notebook_path("paper004_controller.ipynb")


def test_notebook_stored_without_outputs():
    assert_stored_without_outputs(NOTEBOOK)


@pytest.fixture(scope="module")
def results():
    return run_notebook(NOTEBOOK, timeout=600)


@pytest.mark.slow  # the notebook's run: 80-90 s in a 2-worker run; the controller's oracles stay in CI (test_control)
def test_time_scales(results):
    # k_c is the smallest stiffness: the joint springs (Table 1, 100 N m/rad), epsilon = 1/sqrt(k_c)
    assert results["k_c"] == pytest.approx(100.0, rel=1e-12)
    assert results["epsilon"] == pytest.approx(0.1, rel=1e-12)
    assert results["fast_closed_loop_max_real"] < 0.0


@pytest.mark.slow  # the notebook's run: 80-90 s in a 2-worker run; the controller's oracles stay in CI (test_control)
def test_closed_loop_tracking(results):
    """Computed torque with the paper's slow gains on the flexible arm: the link angles stay within
    10 deg of the quintic reference and settle on the final position (pi/2, pi/6)."""
    for key in ("max_err_deg_composite", "max_err_deg_slow"):
        assert max(results[key]) < 10.0, (key, results[key])
    assert max(results["rms_err_deg_composite"]) < 4.0
    assert max(results["final_err_deg_composite"]) < 1.5
    final = results["final_joint_angles_deg_composite"]
    assert final[0] == pytest.approx(90.0, abs=1.5) and final[1] == pytest.approx(30.0, abs=1.5)
    # the fast part does not spoil the tracking of the slow control (same order of error)
    for comp, slow in zip(results["max_err_deg_composite"], results["max_err_deg_slow"]):
        assert comp < 1.5 * slow


@pytest.mark.slow  # the notebook's run: 80-90 s in a 2-worker run; the controller's oracles stay in CI (test_control)
def test_composite_suppresses_vibration(results):
    """The fast LQR removes most of the vibration (link modes and joint deflections minus their
    quasi-steady values) that the slow control alone leaves: composite / slow-only ratios."""
    assert results["vibration_ratio_modes"] < 0.6
    assert results["vibration_ratio_joints"] < 0.6
    assert results["vibration_ratio_modes_after"] < 0.6
    assert results["vibration_ratio_joints_after"] < 0.6
    for r in ("vibration_ratio_modes", "vibration_ratio_joints"):
        assert math.isfinite(results[r]) and results[r] > 0.0


def test_results_printed_in_last_cell():
    nb = nbformat.read(NOTEBOOK, as_version=4)
    src = [c for c in nb.cells if c.cell_type == "code"][-1].source
    ast.parse(src)
    assert "RESULTS" in src and "print" in src
