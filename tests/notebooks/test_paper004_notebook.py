"""Execute notebooks/paper004_arm.ipynb and check its RESULTS against independent oracles: the static joint
deflection tau/k_s, the rotor equation (paper eq. 56), the rigid-joint arm as the k_s -> infinity limit, Rayleigh's
monotonicity."""

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("nbformat")
pytest.importorskip("nbclient")

from notebook_runner import assert_stored_without_outputs, notebook_path, run_notebook  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOK = notebook_path("paper004_arm.ipynb")
TAU, K_S = 0.2, 100.0  # N m, N m/rad (Table 1 and section 6)


def execute(full: bool):
    return run_notebook(NOTEBOOK, env={"FLEXDYN_FULL": "1" if full else "0"}, timeout=900)


def test_notebook_stored_without_outputs():
    assert_stored_without_outputs(NOTEBOOK)


@pytest.fixture(scope="module")
def results():
    return execute(full=False)


def test_joint_deflection_is_of_order_tau_over_ks(results):
    static = TAU / K_S
    assert results["tau_over_ks"] == pytest.approx(static)
    peak = np.asarray(results["deflection_peak"])
    mean = np.asarray(results["deflection_mean_first_pulse"])
    # a suddenly applied torque at most doubles a spring's static deflection, the +tau -> -tau switch at most
    # triples it; the rotor's inertia takes part of the torque or (joint 1, turned backwards) adds to it
    assert np.all(peak > static) and np.all(peak < 3 * static)
    assert np.all(mean > 0.3 * static) and np.all(mean < 1.5 * static)
    # the rotor equation J alpha_ddot + k_s (alpha - theta) = tau holds along the trajectory (finite differences)
    assert results["eq56_residual"] < 5e-3


def test_flexible_and_rigid_joint_arms_differ_by_order_tau_over_ks(results):
    dtheta = np.asarray(results["max_dtheta_flex_vs_rigid"])
    assert np.all(dtheta < 5 * TAU / K_S) and np.all(dtheta > 0.1 * TAU / K_S)
    assert np.all(np.asarray(results["max_theta_rigid"]) > 50 * dtheta)  # the links turn by far more
    np.testing.assert_allclose(results["final_theta_flexible"], results["final_theta_rigid"], atol=5 * TAU / K_S)


def test_oscillations_decay_with_both_joint_types(results):
    # not the paper's non-decaying flexible-joint oscillations: with D = 0.1 sqrt(K) everything decays
    assert np.all(np.asarray(results["modal_decay_flexible"]) < 0.2)
    assert np.all(np.asarray(results["modal_decay_rigid"]) < 0.2)
    assert np.all(np.asarray(results["deflection_decay"]) < 0.2)


def test_rigid_joint_limit_and_rayleigh_monotonicity(results):
    rigid = np.asarray(results["modal_hz"]["rigid joints"])
    soft = np.asarray(results["modal_hz"]["k_s = 100"])
    stiff = np.asarray(results["modal_hz"]["k_s = 1e6"])
    assert len(rigid) == 4 and len(soft) == len(stiff) == 6  # two joint modes more
    np.testing.assert_allclose(stiff[:4], rigid, rtol=1e-4)  # k_s -> infinity is eq. (55)
    assert stiff[4] > 100 * rigid[-1]
    # a softer joint lowers every frequency (Rayleigh), by little at k_s = 100
    assert np.all(soft[:4] < rigid) and np.all(soft[:4] > 0.95 * rigid)


def test_undamped_arm(results):
    assert results["undamped_reached_s"] == 5.0
    assert results["undamped_energy_drift"] < 1e-3  # no damping: energy constant once the torque is off
    assert results["undamped_tip_peak"] < 0.1


@pytest.mark.slow
def test_full_stiff_joint_time_response():
    full = execute(full=True)
    stiff = full["stiff_joint"]
    # k_s = 1e4: 100x stiffer than Table 1, so the difference from the rigid-joint arm shrinks by about 100
    assert np.all(np.asarray(stiff["max_dtheta_vs_rigid"]) < 0.05 * np.asarray(full["max_dtheta_flex_vs_rigid"]))
    assert np.all(np.asarray(stiff["peak_deflection"]) < 3 * TAU / 1e4)
