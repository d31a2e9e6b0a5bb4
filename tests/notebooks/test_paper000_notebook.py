"""Execute notebooks/paper000_pendulums.ipynb and check its RESULTS against independent oracles."""

import ast
import math
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
pytest.importorskip("nbclient")

import oracles  # noqa: E402  (tests/ is on sys.path via conftest.py)
from notebook_runner import assert_stored_without_outputs, notebook_path, run_notebook  # noqa: E402

import flexdyn as fd  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOK = notebook_path("paper000_pendulums.ipynb")


def test_notebook_stored_without_outputs():
    assert_stored_without_outputs(NOTEBOOK)


@pytest.fixture(scope="module")
def results():
    return run_notebook(NOTEBOOK, timeout=300)


def _rigid_oracle_hz():
    c = fd.rigs.rigid_pendulum()
    get = lambda name: float(fd.get_parameter(c, name))  # noqa: E731
    m, l, m_p, I_h = get("link1.mass"), get("link1.length"), get("payload.mass"), get("hub1.inertia")
    g = -get("gravity[1]")
    inertia = m * l**2 / 3 + m_p * l**2 + I_h
    m_g_lc = (m * l / 2 + m_p * l) * g
    return 1.0 / oracles.pendulum_period_exact(inertia, m_g_lc, math.pi / 2)


def test_rigid_frequency_from_horizontal(results):
    f = results["rigid_freq_horizontal_undamped_hz"]
    assert f == pytest.approx(_rigid_oracle_hz(), rel=5e-3)
    assert 0.87 <= f <= 0.91
    # the damped trace's first quarter swing is in the paper's band too
    assert 0.87 <= results["rigid_freq_horizontal_quarter_hz"] <= 0.91


def test_log_decrement_damping(results):
    xi = results["xi_logdec_small_amplitude"]
    assert xi == pytest.approx(1.9e-3, rel=0.30)
    assert xi < 1.9e-3


def _tip_oracle_hz(mass):
    c = fd.rigs.flexible_pendulum(n_modes=2, mass=mass, damping_ratio=0.01)
    get = lambda name: float(fd.get_parameter(c, name))  # noqa: E731
    w = oracles.hub_beam_frequencies(1, get("link1.EI"), get("link1.rho"), get("link1.length"), 2e-5)
    return float(w[0]) / (2 * math.pi)


def test_flexible_tip_frequency(results):
    assert results["flex_strip_tip_hz"] == pytest.approx(_tip_oracle_hz(None), rel=0.02)
    assert results["flex_060_tip_hz"] == pytest.approx(35.0, rel=0.03)
    assert results["flex_060_tip_hz"] == pytest.approx(_tip_oracle_hz(0.60), rel=0.02)


def test_results_printed_in_last_cell():
    # the notebook's own last cell prints the dict (checked statically: it must reference RESULTS and print)
    nb = nbformat.read(NOTEBOOK, as_version=4)
    src = [c for c in nb.cells if c.cell_type == "code"][-1].source
    ast.parse(src)
    assert "RESULTS" in src and "print" in src
