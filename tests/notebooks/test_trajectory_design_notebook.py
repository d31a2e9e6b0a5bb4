"""Execute notebooks/trajectory_design.ipynb and check its claims with numbers: the optimised move ends at the goal at
rest (re-simulated here with a different solver and tighter tolerance), its residual vibration is smaller than every
comparison's, the robust design holds over the payload range where the nominal one degrades, and the torque limit
holds at every sample."""

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("nbformat")
pytest.importorskip("nbclient")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from notebook_runner import assert_stored_without_outputs, notebook_path, run_notebook  # noqa: E402

import flexdyn as fd  # noqa: E402
from flexdyn import design  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOK = notebook_path("trajectory_design.ipynb")

# Stated tolerances of the optimised move (issue 7): at T the link angles are within 1e-4 rad of the goal and the joint
# rates below 1e-4 rad/s; the RMS tip deflection over [T, T + 1 s] is below 1e-4 m (bang-bang: 2e-2 m).
ANGLE_TOL = 1e-4  # rad
RATE_TOL = 1e-4  # rad/s
VIBRATION_TOL = 1e-4  # m


def execute():
    return run_notebook(NOTEBOOK, timeout=1200)


def test_notebook_stored_without_outputs():
    assert_stored_without_outputs(NOTEBOOK)


@pytest.fixture(scope="module")
def results():
    return execute()


def _move(results, payload_kg=0.0):
    return design.RestToRestMove(
        fd.rigs.two_link_flexible_arm(payload_mass=payload_kg),
        [0.0, 0.0],
        results["goal"],
        results["T"],
        results["tau_max"],
        settle=1.0,
        n_window=101,
        dt=2e-3,
    )


@pytest.mark.slow
def test_optimised_move_ends_at_rest_independent_resimulation(results):
    # re-simulated here with adaptive Tsit5 at rtol 1e-10 (the design used fixed-step RK4 at 2 ms; the notebook's check
    # used Dopri8)
    move = _move(results)
    torque = design.BSplineTorque(np.asarray(results["control_points_nominal"]), results["T"], results["tau_max"])
    ts = move.output_times()
    traj = fd.simulate(move.chain, move.initial_state(), ts, torque, rtol=1e-10, atol=1e-12)
    out = fd.observe(move.chain, traj, torque)
    goal = np.asarray(results["goal"])
    assert np.max(np.abs(np.asarray(out.joint_angle[1]) - goal)) < ANGLE_TOL
    assert np.max(np.abs(np.asarray(out.joint_rate[1]))) < RATE_TOL
    assert np.max(np.abs(np.asarray(out.joint_angle[1:]) - goal)) < ANGLE_TOL  # stays there over the window
    tip = np.asarray(out.tip_deflection[1:])
    vibration = np.sqrt(np.mean(np.sum(tip**2, axis=1)))
    assert vibration < VIBRATION_TOL
    np.testing.assert_allclose(vibration, results["metrics"]["optimised"]["residual_vibration"], rtol=0.05)
    # and the notebook's Dopri8 run agrees
    assert results["dopri8"]["angle_error_T"] < ANGLE_TOL and results["dopri8"]["rate_T"] < RATE_TOL
    assert results["dopri8"]["residual_vibration"] < VIBRATION_TOL
    assert results["rk4_vs_dopri8_state_T"] < 1e-6


@pytest.mark.slow
def test_residual_vibration_below_every_comparison(results):
    metrics = results["metrics"]
    optimised = metrics["optimised"]["residual_vibration"]
    comparisons = ("bang-bang", "ZV bang-bang", "ZVD bang-bang", "composite (paper gains)", "composite (stiffer gains)")
    assert set(metrics) == {"optimised", *comparisons}
    for name in comparisons:
        factor = metrics[name]["residual_vibration"] / optimised
        print(f"{name}: residual vibration {factor:.0f} x the optimised move's")
        assert factor > 10.0
        assert results["vibration_factors"][name] == pytest.approx(factor, rel=1e-12)
    # the shapers do their job on the nominal model: less vibration than the bang-bang they shape
    assert metrics["ZV bang-bang"]["residual_vibration"] < metrics["bang-bang"]["residual_vibration"]
    assert metrics["ZVD bang-bang"]["residual_vibration"] < metrics["bang-bang"]["residual_vibration"]


@pytest.mark.slow
def test_robust_design_holds_over_payloads(results):
    # designed on 0 / 50 / 100 g; 25 and 75 g are not in the design batch. Measured (2026-12-04, the notebook, with
    # Marquardt's damping update in design_move): worst case over 0-100 g 6.8e-4 m robust vs 3.4e-3 m nominal (5.0x),
    # bang-bang 2.0e-2 to 2.2e-2 m (2026-11-24, optimistix's default trust region: 8.1e-4 vs 3.5e-3 m, 4.3x). With
    # the window angles measured from theta(T) in the payloads' residuals (before) the robust design reached 2.5e-3 m.
    vib = {k: np.asarray(v) for k, v in results["sweep_vibration"].items()}
    assert results["payloads_g"] == [0.0, 25.0, 50.0, 75.0, 100.0]
    # the nominal design degrades with payload...
    assert vib["nominal"][-1] > 10 * vib["nominal"][0]
    # ...the robust one keeps the worst case over 0-100 g at least 3x lower, and stays far below the bang-bang
    assert vib["robust"].max() < vib["nominal"].max() / 3
    assert np.all(vib["robust"] < vib["bang-bang"] / 10)


@pytest.mark.slow
def test_torque_limits_hold_at_every_sample(results):
    tau_max = results["tau_max"]
    ts = jnp.linspace(-0.1, results["T"] + 0.1, 20001)
    for key in ("control_points_nominal", "control_points_robust"):
        torque = design.BSplineTorque(np.asarray(results[key]), results["T"], tau_max)
        tau = np.asarray(jax.vmap(torque)(ts))
        assert np.all(np.abs(tau) <= tau_max)
    assert np.all(np.asarray(results["metrics"]["optimised"]["peak_torque"]) <= tau_max)
    for peaks in results["sweep_peak_torque"]["robust"]:
        assert np.all(np.asarray(peaks) <= tau_max)
