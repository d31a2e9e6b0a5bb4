"""The `identify/examples/spinning_link` example: a flexible link spun up and coasting, whose
synthetic logs have geometric stiffening that the papers' linear link model lacks.

In CI: `make_logs.py` reproduces the shipped logs exactly, the two experiment files differ
only in the option, and the model check flags the linear model on these logs. Slow: both
`identify fit` runs, with the numbers the example's README states, and `identify diagnose`
on the linear model, which must name geometric stiffening (the truth) and nothing else."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
from example_scripts import make_logs_module  # tests/ is on sys.path

import flexdyn as fd
from identify import load_experiment
from identify._diagnose import evidence
from identify.cli import main

EXAMPLE = Path(__file__).resolve().parents[2] / "identify" / "examples" / "spinning_link"


def _make_logs_module():
    return make_logs_module("spinning_link")


def test_make_logs_reproduces_the_shipped_logs(tmp_path):
    written = _make_logs_module().make_logs(tmp_path)
    assert sorted(p.name for p in written) == ["spin_fast.csv", "spin_mid.csv", "spin_slow.csv"]
    for p in written:
        ours, shipped = p.read_text().splitlines(), (EXAMPLE / "logs" / p.name).read_text().splitlines()
        assert ours[:3] == shipped[:3], p.name  # comments and header
        a = np.loadtxt(ours[3:], delimiter=",")
        b = np.loadtxt(shipped[3:], delimiter=",")
        # the same numbers up to the last printed digit (1e-5 deg / mm): another CPU's XLA
        # build may round a last digit the other way
        assert a.shape == b.shape and np.max(np.abs(a - b)) <= 2.01e-5, (p.name, np.max(np.abs(a - b)))


def test_the_experiment_files_differ_only_in_geometric_stiffening():
    linear = load_experiment(EXAMPLE / "experiment.toml")
    stiffened = load_experiment(EXAMPLE / "experiment_stiffened.toml")
    assert not linear.chain.links[0].geometric_stiffening and stiffened.chain.links[0].geometric_stiffening
    names = fd.parameter_names(linear.chain)
    assert names == fd.parameter_names(stiffened.chain)
    for n in names:
        assert float(fd.get_parameter(linear.chain, n)) == float(fd.get_parameter(stiffened.chain, n)), n
    assert (
        [p.name for p in linear.free]
        == [p.name for p in stiffened.free]
        == [
            "link1.EI",
            "joint1.damping",
            "hub1.inertia",
        ]
    )
    assert [s.name for s in linear.fit_logs] == ["spin_slow", "spin_fast"]
    assert [s.name for s in linear.validation_logs] == ["spin_mid"]


def test_the_model_check_flags_the_linear_link_on_these_logs():
    """The check reads the spin from the logs' encoder (here the measured angle, as a stand-in
    for the fitted simulation) and flags the linear link at its true parameters."""
    exp = load_experiment(EXAMPLE / "experiment.toml")
    traces = {
        s.name: {"t": np.asarray(s.log.t), "baseline": {"theta1": np.asarray(s.log.outputs["theta1"])}}
        for s in exp.logs
    }
    rates = evidence.link_spin_rates(exp.chain, traces)
    assert 13.0 < rates["link1"] < 15.0  # rad/s (the fast run coasts at ~14; the encoder noise adds a little)
    (check,) = evidence.stiffening_checks(exp.chain, rates)
    assert check["flagged"] and 0.15 < check["relative_shift_spin"] < 0.25, check
    truth = _make_logs_module().truth()
    assert evidence.stiffening_checks(truth, rates) == []  # the truth has the option
    # the EI bias at the fit logs' RMS and largest rates bracket the linear fit's EI (1.158,
    # measured: the slow test below checks it on a live fit), the chain at its values
    fit_traces = {k: v for k, v in traces.items() if k in ("spin_slow", "spin_fast")}
    fitted = fd.with_parameters(exp.chain, {"link1.EI": 1.158})
    (check,) = evidence.stiffening_checks_of(fitted, fit_traces)
    assert check["ei_bias_factor_rms"] < 1.158 < check["ei_bias_factor"], check
    assert "RMS" in check["message"] and "not a mode of the whole arm" in check["message"]


@pytest.mark.slow
def test_fits_of_both_experiment_files(tmp_path):
    """Measured 2026-11-26 (README of the example): linear EI 1.158 [1.156, 1.161], flagged,
    held-out tip RMS 2.83 mm; stiffened EI 1.000 [0.99999, 1.00001], held-out tip RMS
    0.0198 mm (noise 0.02 mm)."""
    docs = {}
    for name in ("experiment", "experiment_stiffened"):
        assert main(["fit", str(EXAMPLE / f"{name}.toml"), "--out", str(tmp_path / name), "--quiet"]) == 0
        docs[name] = json.loads((tmp_path / name / "result.json").read_text())
    lin, stiff = docs["experiment"], docs["experiment_stiffened"]
    ei = {d["name"]: d for d in lin["parameters"]}["link1.EI"]
    assert ei["value"] == pytest.approx(1.158, rel=0.01) and ei["ci95"][0] > 1.1, ei
    (check,) = lin["model_checks"]
    assert check["flagged"] and check["ei_bias_factor"] > ei["value"], check  # an upper estimate
    assert check["ei_bias_factor_rms"] < ei["value"], check  # the RMS rate's: a lower one here
    held = lin["validation"]["spin_mid"]["residuals"]["tip1"]["rms"]
    assert held > 50 * 0.02e-3, held
    ei = {d["name"]: d for d in stiff["parameters"]}["link1.EI"]
    assert ei["ci95"][0] <= 1.0 <= ei["ci95"][1], ei
    assert stiff["model_checks"] == []
    held = stiff["validation"]["spin_mid"]["residuals"]["tip1"]["rms"]
    assert held < 1.1 * 0.02e-3, held
    assert math.isclose(stiff["cost"], stiff["n_residuals"], rel_tol=0.1), (stiff["cost"], stiff["n_residuals"])
    # against the logs' model-free noise floor (identify.noise_floor): the linear link's tip
    # residual is far above it (a missing effect), the stiffened one's at it
    assert lin["fit_quality"]["tip1"]["ratio"] > 10, lin["fit_quality"]
    assert all(0.8 < q["ratio"] < 1.2 for q in stiff["fit_quality"].values()), stiff["fit_quality"]


@pytest.mark.slow
def test_diagnose_names_geometric_stiffening(tmp_path):
    """The catalogue's `geometric_stiffening` entry (offered because the model check flags
    the link) on the linear model's experiment. Before it existed, diagnose named a pair of
    calibration errors with gains of 12 and 17 (README of the example). Measured 2026-12-03
    (37 min of CPU): round 1 geometric_stiffening dBIC -75818, held-out gain 99.6x (tip
    143x, 0.0198 mm); EI 1.000 [0.99999, 1.00001]; from the stiffened model (cost 8041 over
    8004 residuals) nothing else is named. Since the same day the stiffened model, at the
    noise on the held-out run, is not searched for structural changes again (the notes say
    so): 20 min of CPU (21 min wall, two cores shared with another job), of which the
    round-2 refits of joint elasticity and a missing mode had taken 23 min of a 67 min run."""
    out = tmp_path / "diagnosis"
    assert main(["diagnose", str(EXAMPLE / "experiment.toml"), "--out", str(out), "--quiet"]) == 0
    doc = json.loads((out / "diagnosis.json").read_text())
    assert doc["named"] == ["geometric_stiffening"], doc["named"]
    assert doc["causes"][0]["where"] == "link1"
    # the stiffened model recovers the true EI (1 N m^2) and predicts the held-out run at
    # the noise (tip 0.02 mm, encoder 0.02 deg)
    lo, hi = doc["extended_intervals"]["link1.EI"]["ci95"]
    assert lo <= 1.0 <= hi, doc["extended_intervals"]["link1.EI"]
    held = doc["held_out"]
    assert held["extended"]["tip1"] < 1.2 * 0.02e-3, held
    assert held["gain"]["tip1"] > 50, held
    # the baseline's model check, which offered the entry, flags the link
    assert [c["link"] for c in doc["model_checks"] if c["flagged"]] == ["link1"], doc["model_checks"]
    # from the stiffened model, whose held-out residual is white at its noise floor, no
    # structural candidate is refitted (`identify.diagnose.held_out_headroom`)
    assert [(n["round"], n["text"].split(" not refitted")[0]) for n in doc["notes"]] == [
        (2, "joint_elasticity:joint1, missing_mode:link1")
    ], doc["notes"]
