"""Execute notebooks/paper002_two_link.ipynb and check its RESULTS against independent oracles: conservation of
angular momentum, the linearised arm's modes, the clamped-mass frequency equation, non-vmapped runs, the paper's
trends."""

import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("nbformat")
pytest.importorskip("nbclient")

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import oracles  # noqa: E402  (tests/ is on sys.path via conftest.py)
from notebook_runner import assert_stored_without_outputs, notebook_path, run_notebook  # noqa: E402

import flexdyn as fd  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOK = notebook_path("paper002_two_link.ipynb")


def execute(full: bool):
    return run_notebook(NOTEBOOK, env={"FLEXDYN_FULL": "1" if full else "0"}, timeout=600)


def test_notebook_stored_without_outputs():
    assert_stored_without_outputs(NOTEBOOK)


@pytest.fixture(scope="module")
def results():
    return execute(full=False)


def _table(results, key):
    """Table rows (0, 20, ..., 100 g) of a per-payload result, as an array."""
    return np.asarray(results[key])[results["table_rows"]]


def test_payload_grid(results):
    assert np.asarray(results["payloads_g"])[results["table_rows"]].tolist() == [0, 20, 40, 60, 80, 100]


def test_vmapped_sweep_equals_separate_runs(results):
    # two payloads integrated on their own (no vmap, a different compiled program) give the sweep's final state
    chain0 = fd.rigs.two_link_flexible_arm()
    y0 = fd.initial_state(chain0, joint_angles=[0.0, 0.0])
    torque = fd.BangBang([0.2, 0.2], 0.5)
    ts = jnp.linspace(0.0, 5.0, 5001)
    for payload_g in (0.0, 60.0):
        k = results["payloads_g"].index(payload_g)
        chain = eqx.tree_at(lambda c: c.payload.mass, chain0, jnp.asarray(payload_g / 1000))
        traj = fd.simulate(chain, y0, ts, torque, dt=1e-3)
        np.testing.assert_allclose(results["final_Q"][k], np.asarray(traj.Q[-1]), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(results["final_Qd"][k], np.asarray(traj.Qd[-1]), rtol=1e-9, atol=1e-12)


def test_angular_momentum_about_base(results):
    # theta1 is cyclic: dp/dt = tau1, so p = 0.2 N m x 0.5 s at 0.5 s and 0 once the bang-bang is over
    np.testing.assert_allclose(results["p_theta1_at_half"], 0.1, atol=1e-8)
    assert results["p_theta1_max_after_1s"] < 1e-8


def test_final_angles_follow_the_papers_description(results):
    # "the angular position for link-1 increases towards the negative direction while for link-2 the angular position
    # decreases with increasing payloads"
    theta = _table(results, "final_theta")
    assert np.all(theta[:, 0] < 0) and np.all(np.diff(theta[:, 0]) < 0)
    assert np.all(theta[:, 1] > 0) and np.all(np.diff(theta[:, 1]) < 0)


def test_table2_trends(results):
    overshoot, rise = _table(results, "overshoot"), _table(results, "rise_time")
    # reproduced: link-1 overshoot falls with payload, both rise times grow
    assert np.all(np.diff(overshoot[:, 0]) < 0)
    assert np.all(np.diff(rise[:, 0]) > 0) and np.all(np.diff(rise[:, 1]) > 0)
    # link 1 swings back past its final angle by more than the whole net rotation (reaction of the elbow torque):
    # this is why its overshoot is far above the paper's 10-26 %
    final1, min1 = _table(results, "final_theta")[:, 0], _table(results, "link1_min_theta")
    assert np.all(min1 < 1.5 * final1)
    np.testing.assert_allclose(overshoot[:, 0], 100 * (min1 - final1) / final1, rtol=1e-9)


def test_link2_drift_explains_settling_and_overshoot(results):
    # zero angular momentum but a free elbow: link 2 keeps opening after the torque ends, so it never passes its value
    # at 5 s (0 % overshoot) and leaves the 2 % band late
    drift = _table(results, "drift_rate_link2")
    assert np.all(drift > 0.01)
    assert np.all(_table(results, "overshoot")[:, 1] == 0.0)
    assert np.all(_table(results, "settling_time")[:, 1] > 2.0)


def test_finite_difference_acceleration(results):
    assert results["fd_vs_exact_acc"] < 5e-3


def _modal_hz(Q, payload_kg):
    chain = eqx.tree_at(lambda c: c.payload.mass, fd.rigs.two_link_flexible_arm(), jnp.asarray(payload_kg))
    f = np.asarray(fd.modal_analysis(chain, jnp.asarray(Q)).natural_frequency)
    return f[f > 1e-3]


def test_link2_second_mode_vs_linear_modes_and_clamped_mass(results):
    peaks = np.asarray(results["psd_peaks"])  # [payload, link, mode]
    rho, length, EI = 0.2, 0.5, 1.0
    f_link2 = []
    for k, payload_g in enumerate(results["payloads_g"]):
        f = peaks[k, 1, 1]
        f_link2.append(f)
        linear = _modal_hz(results["final_Q"][k], payload_g / 1000)
        assert len(linear) == 4
        assert np.min(np.abs(linear / f - 1)) < 0.02
        x = oracles.clamped_mass_roots(2, payload_g / 1000 / (rho * length), 0.0)[1]
        assert f == pytest.approx(x**2 / length**2 * math.sqrt(EI / rho) / (2 * math.pi), rel=0.02)
    assert np.all(np.diff(f_link2) < 0)  # the paper's trend: resonances shift down with payload


def test_link1_first_mode_is_payload_independent(results):
    peaks = np.asarray(results["psd_peaks"])
    f = peaks[:, 0, 0]
    linear0 = _modal_hz(results["final_Q"][0], 0.0)
    assert f[0] == pytest.approx(linear0[0], rel=0.02)
    assert np.ptp(f) / f.mean() < 0.02  # paper: 2 Hz at every payload
    # the linearised link-2 first mode falls with payload (paper: 6 -> 3 Hz)
    modal = np.asarray(results["modal_hz_final"])
    assert np.all(np.diff(modal[:, 1]) < 0) and modal[0, 1] > 1.5 * modal[-1, 1]


@pytest.mark.slow
def test_full_grid():
    full = execute(full=True)
    assert len(full["payloads_g"]) == 21
    overshoot = np.asarray(full["overshoot"])[:, 0]
    assert np.all(np.diff(overshoot) < 0)
    assert np.all(np.diff(np.asarray(full["psd_peaks"])[:, 1, 1]) < 0)
